"""The error bound with a metric that follows the state (`certify.prove.metric`).

A checkpoint may carry a metric M(x) (`certify.model.metric.PolyMetric`; `certify train
--preset bound` designs one). This check proves, after the constant-metric dissipation
inequality of the `dissipation` check (the first stage), the Riemannian path certificate with
M(x) on tubes around the output manifold, stage by stage, with the metric's constants; the
`bounds` check turns it into a bound in stages.

Status: PROVED (every stage and constant proved); UNKNOWN (something not proved within the box
budget); NOT APPLICABLE without a metric in the checkpoint, without a proved dissipation
inequality (the first stage), or for a gain whose boundary condition is not exact (the path's
plant end must be a solution of the observer's vector field).
"""

from __future__ import annotations

import math
import time
from typing import Any

from certify.arith.intervals import up
from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.results import DissipationResult, MetricBoundResult, ResidualResult, Status
from certify.settings import VerifySettings


def _not_applicable(why: str) -> MetricBoundResult:
    return MetricBoundResult(Status.NOT_APPLICABLE, "not applicable: " + why)


def check_metric_bound(problem: Problem, settings: VerifySettings, *,
                       dissipation: DissipationResult | None = None,
                       residual: ResidualResult | None = None) -> MetricBoundResult:
    """Prove the stages with the checkpoint's metric at the settings' noise level (module
    docstring for the statuses)."""
    import torch

    from certify.prove.metric import prove_metric_chain

    t0 = time.perf_counter()
    if problem.metric is None:
        return _not_applicable("the checkpoint has no metric that follows the state "
                               "(certify train --preset bound designs one)")
    exact = problem.structural or (residual is not None and residual.upper == 0.0)
    if not exact:
        return _not_applicable("the gain's boundary condition is not exact (the residual is "
                               "not proved 0): the metric's path argument needs the plant to "
                               "solve the observer's equation")
    if dissipation is None or dissipation.status != Status.PROVED or dissipation.mu_residual:
        return _not_applicable("the first stage, the dissipation inequality with the constant "
                               "metric P, was not proved")
    vbar = float(settings.noise)
    v1 = dissipation.mu * vbar * vbar / dissipation.alpha
    net = problem.network if problem.device == "cpu" else problem.on("cpu").network
    with torch.no_grad():
        out = prove_metric_chain(problem.system, net, problem.metric, vbar=vbar, P1=problem.P,
                                 V1_inf=v1, max_boxes=settings.metric_boxes,
                                 seed=settings.seed)
    c = out.constants
    ultimate = None
    if out.ultimate is not None:
        last = out.stages[-1]
        # sqrt(mu / alpha) vbar / sqrt(m_min), each step rounded up
        ultimate = float(up(torch.tensor(math.sqrt(last.mu / last.alpha) * vbar
                                         / math.sqrt(c.m_min) * (1 + 1e-12))))
    return MetricBoundResult(
        status=out.status, message=out.message, metric=problem.metric.to_dict(),
        m_min=c.m_min if c else None, a=c.a if c else None,
        gamma_h=c.gamma_h if c else None, gamma=list(c.gamma) if c else [],
        stages=[dict(tau=s.tau, alpha=s.alpha, mu=s.mu, entry=s.entry, v_inf=s.v_inf,
                     boxes=s.boxes, duration=s.duration) for s in out.stages],
        plant_box=out.plant_box, ultimate=ultimate, boxes=out.boxes,
        candidates=out.candidates, seconds=time.perf_counter() - t0)


class MetricBoundCheck(Check):
    """The Riemannian path certificate with the checkpoint's metric M(x), in stages."""

    name = "metric_bound"
    title = "Error bound with a metric M(x)"
    result_type = MetricBoundResult
    reads = ("noise", "metric_boxes", "seed")
    uses = ("dissipation", "residual")

    def run(self, context: Context) -> MetricBoundResult:
        return check_metric_bound(context.problem, context.settings,
                                  dissipation=context.result("dissipation"),
                                  residual=context.result("residual"))

    def present(self, r: MetricBoundResult, certificate: Any) -> Presentation:
        last = r.stages[-1] if r.stages else None
        stages = "; ".join(
            f"stage {i + 2}: tube {upper_text(s['tau'], 3)}, alpha {lower_text(s['alpha'], 4)},"
            f" mu {upper_text(s['mu'], 4)}" for i, s in enumerate(r.stages)) or None
        box = (", ".join(f"[{lower_text(lo, 3)}, {upper_text(hi, 3)}]" for lo, hi in
                         r.plant_box) if r.plant_box else None)
        return Presentation(
            sampled=Quantity("no sampled side (the stages are proved or not)", None,
                             "\u2014"),
            proved=Quantity("\u2016e\u2016 limit", r.ultimate, "not proved", bound="upper"),
            numbers=(Quantity("ultimate bound", r.ultimate, sig=6, bound="upper"),
                     Quantity("m_min", r.m_min, sig=6, bound="lower"),
                     Quantity("a (M <= a P)", r.a, sig=6, bound="upper"),
                     Quantity("gamma_h", r.gamma_h, sig=6, bound="upper"),
                     Quantity("stages", stages, "none"),
                     Quantity("plant box", box, "none"),
                     Quantity("last tube", last["tau"] if last else None, sig=6),
                     Quantity("boxes", r.boxes)),
            facts=(Quantity("Status", r.status.value),
                   Quantity("Metric", _metric_text(r.metric, certificate), "none"),
                   Quantity("Limit of \u2016e\u2016", r.ultimate, "not proved", sig=4,
                            bound="upper"),
                   Quantity("Stages after the constant metric", stages, "none"),
                   Quantity("Plant box (where the bound holds)", box, "none"),
                   Quantity("M \u2265 m_min I", r.m_min, "not proved", sig=4, bound="lower")))


def _metric_text(data: dict | None, certificate: Any) -> str | None:
    if not data:
        return None
    from certify.model.metric import PolyMetric

    names = (getattr(certificate, "system", None) or {}).get("states")
    return PolyMetric.from_dict(data).text(names)


CHECK = MetricBoundCheck()
