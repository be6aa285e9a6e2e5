"""`certify train`'s pre-flight: whether what a preset is about to train can pass at all.

Before training with a given metric P and rate lam (presets paper and tiny, and certified
with `--metric`), the network-independent necessary condition of METHOD §3.5
(`certify.checks.necessary`) is checked at that P and lam. When it is VIOLATED (a sound
witness: q > 0 at a point of the output manifold), no C^1 gain meets the contraction
condition and the boundary condition together, so training would only produce a network
that fails the certificate's MPDI, or one that breaks its boundary condition by at least
the residual price. `certify train` then stops before training (`Infeasible`, exit
`EXIT_INFEASIBLE`) with the reason and the routes that can work: the metric SDP's P at
this lam (`certify.design.metric.synthesize_metric`), presets that design the metric, or
none at all when no constant metric works at any rate on the box
(`certify.design.metric.undetectable_at_every_rate`). `--force` trains anyway; preset tiny
(a smoke test, never a gain to certify) says so and trains.

The presets that design their own metric (certified without `--metric`, bound) need no
pre-flight: their design is the test. When it finds nothing they end with `Infeasible`
too, naming the reason when one is proved (`no_design`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from certify.arith.text import lower_text
from certify.results import NecessaryResult, Status

if TYPE_CHECKING:  # the command line imports this module for its exit code: no torch here
    import numpy as np

    from certify.spec.system import System

#: exit code of `certify train` when nothing was trained: the pre-flight proves the design
#: infeasible, or the preset found no design (the message says which); nothing is written
EXIT_INFEASIBLE = 5

class Infeasible(Exception):
    """Nothing will be trained or written: the design is infeasible (proved), or the preset
    found no design. The text is the reason and the routes that can work (several lines)."""


def _point(v: list[float] | None) -> str:
    return "(" + ", ".join(f"{a:.4g}" for a in v or []) + ")"


def _metric_text(P: np.ndarray) -> str:
    import numpy as np

    return "P = I" if np.array_equal(P, np.eye(len(P))) else "P = " + json.dumps(P.tolist())


def check(system: System, P: np.ndarray, lam: float, preset: str, *, force: bool,
          log: Callable[[str], None], warn: Callable[[str], None]) -> NecessaryResult:
    """The pre-flight at (P, lam) for `preset`: raises `Infeasible` on a proved violation
    (unless `force`, or the preset is tiny: then `warn` says it and training goes on);
    `log` gets one line otherwise."""
    import numpy as np

    from certify.checks.necessary import check_necessary

    P = np.asarray(P, dtype=np.float64)
    r = check_necessary(system, P, lam)
    if r.status is not Status.VIOLATED:
        if r.status is Status.PROVED:
            log(f"pre-flight passed: {r.message}")
        else:
            log(f"pre-flight undecided (training goes on): {r.message}")
        return r
    reason = violation_text(system, P, lam, r)
    if force or preset == "tiny":
        why = "--force" if force else "preset tiny is a smoke test"
        warn(f"{reason}\ntraining anyway ({why}): the network it writes fails the MPDI or the "
             "boundary condition with this P and lam")
        return r
    raise Infeasible(f"stopped before training: {reason}; nothing was written\n  "
                     + "\n  ".join([*routes(system, lam, preset, r), "--force trains anyway"]))


def violation_text(system: System, P: np.ndarray, lam: float, r: NecessaryResult) -> str:
    """What the pre-flight proved, in two sentences (witness, q, its sound lower bound)."""
    import torch

    from certify.search.witness import manifold_witness_lower

    q_low = manifold_witness_lower(system, P, lam, torch.tensor(r.witness, dtype=torch.float64))
    text = (f"the pre-flight proves that no C^1 gain meets the contraction condition (MPDI) "
            f"and the boundary condition together for {system.name} with {_metric_text(P)} "
            f"and lam = {lam:g}: q = {r.q_max:.4g} > 0 at xhat = {_point(r.witness)}, "
            f"y = {_point(r.witness_y)} (sound lower bound {lower_text(q_low)})")
    if r.residual_price is not None and r.residual_price > 0:
        text += (f"; a gain that meets the MPDI everywhere breaks the boundary condition by "
                 f"eps_bar >= {r.residual_price:.4g}, which adds at least "
                 f"{r.residual_price / (2 * lam):.4g} to its error bound")
    return text


def routes(system: System, lam: float, preset: str, r: NecessaryResult) -> list[str]:
    """The routes that can work after a violation at rate lam (one line each): a metric the
    SDP finds at this lam, a lower lam under the rate cap, the presets that design their
    metric; or the proved reason why no constant metric works at any rate on this box."""
    from certify.design.metric import synthesize_metric, undetectable_at_every_rate

    never = undetectable_at_every_rate(system)
    if never is not None:
        return [f"no route on this box (no preset can help): {never}"]
    metric = synthesize_metric(system, lam, margin=0.05)
    if metric.status is Status.PROVED and metric.P is not None:
        lines = [f"routes: keep preset {preset} with the metric the SDP finds at lam {lam:g} "
                 f"(cond P {metric.condition_number:.4g}), which passes the pre-flight: "
                 f"--metric '{json.dumps(metric.P)}'"]
    else:
        lines = [f"routes: (the metric SDP found no constant metric at lam {lam:g}: "
                 f"{metric.message})"]
    if r.rate_cap is not None and r.rate_cap > 0 and math.isfinite(r.rate_cap):
        lines.append(f"or a rate below this metric's rate cap: --lam below {r.rate_cap:.4g}")
    lines.append("or let a preset design the metric with the gain: --preset certified without "
                 "--metric (joint LMI, then counterexample-guided training) or --preset bound "
                 "(a linear observer designed for the error bound)")
    return lines


def check_designable(system: System, preset: str) -> None:
    """Before a preset that designs its own metric (certified, bound) starts: raises
    `Infeasible` when no constant metric works at any rate on this box (a proved reason,
    found in well under a second, where the design would search for minutes)."""
    from certify.design.metric import undetectable_at_every_rate

    never = undetectable_at_every_rate(system)
    if never is not None:
        raise _impossible(system, preset, never)


def _impossible(system: System, preset: str, reason: str, said: str = "") -> Infeasible:
    said = f"\n  (the design said: {said})" if said else ""
    return Infeasible(f"preset {preset}: {system.name} has no certifiable observer of this "
                      f"kind: {reason}; nothing was written{said}")


def no_design(system: System, preset: str, message: str) -> Infeasible:
    """`Infeasible` for a preset that designs its metric and found none: the proved reason
    when there is one (no constant metric at any rate on this box), else the design's
    message (not found is not proved impossible)."""
    from certify.design.metric import undetectable_at_every_rate

    never = undetectable_at_every_rate(system)
    if never is not None:
        return _impossible(system, preset, never, message)
    return Infeasible(f"preset {preset} found no observer for {system.name}: {message}; "
                      "nothing was written\n  (not a proof that none exists: another rate, "
                      "box or preset may work)")
