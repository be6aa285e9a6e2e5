"""The metric check: presents a constant metric P found by SDP (`certify.design.metric`).

Run by `certify check` (pre-flight), not by `verify()`, whose problem already fixes P;
registered so that reports can present its result.
"""

from __future__ import annotations

from typing import Any

from certify.checks.base import Check
from certify.presentation import Presentation, Quantity
from certify.results import MetricResult

# ----------------------------------------------------------------------------- check protocol

class MetricCheck(Check):
    """A constant metric P by SDP. Run by `certify check` (pre-flight), not by `verify()`,
    whose problem already fixes P; registered so that reports can present its result."""

    name = "metric"
    title = "Metric P (SDP)"
    result_type = MetricResult

    def present(self, r: MetricResult, certificate: Any) -> Presentation:
        solver = r.solver or {}
        facts = [Quantity("P", r.P), Quantity("cond(P)", r.condition_number),
                 Quantity("SDP margin", r.margin, signed=True), Quantity("\u03bb", r.lam),
                 Quantity("Output-injection gain K", r.K)]
        facts += [Quantity(f"Solver {k}", v) for k, v in solver.items()
                  if not isinstance(v, (dict, list))]
        if r.witness is not None:
            facts += [Quantity("Witness x\u0302 (no constant P works here)", r.witness),
                      Quantity("Witness y", r.witness_y)]
        return Presentation(
            sampled=Quantity("condition number of P", r.condition_number),
            proved=Quantity("SDP margin", r.margin, signed=True),
            setting=(Quantity("\u03bb =", r.lam), Quantity("solver", solver.get("name", "SDP"))),
            numbers=(Quantity("P", r.P, sig=6), Quantity("cond P", r.condition_number, sig=6),
                     Quantity("margin", r.margin, sig=6)),
            facts=tuple(facts))


CHECK = MetricCheck()
