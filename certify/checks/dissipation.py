"""The dissipation certificate V' <= -alpha V + mu ||v||^2 (`certify.prove.dissipation`).

It bounds the estimation error under bounded measurement noise without the Cauchy-Schwarz
step of the ISS bound: the noise's effect is proved together with the contraction, by the
same branch and bound as the MPDI, in one proof of the path certificate (dk/dy at the same
point as the contraction), or for the pieces of a cover of dk/dy where that proves a smaller
bound. The inequality implies contraction at rate alpha/4 on its own, so it does not rest on
the MPDI at the design rate. Inputs: the problem's P and gain, the noise level (to choose
alpha and mu: the inequality itself holds for every noise) and, for a direct gain, the
residual check's eps_bar_P.

Status: PROVED (alpha, mu proved); UNKNOWN (no candidate proved within the box budget, or
none at the samples); NOT APPLICABLE when a direct gain's residual has no sound bound.
"""

from __future__ import annotations

import time
from typing import Any

from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context, setting_quantity
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.results import DissipationResult, ProofStats, ResidualResult, Status
from certify.settings import VerifySettings


def check_dissipation(problem: Problem, settings: VerifySettings, *,
                      residual: ResidualResult | None = None,
                      deadline: float | None = None) -> DissipationResult:
    """Choose and prove (alpha, mu) for `problem` (on the run's device) at the settings'
    noise level, within `settings.dissipation_boxes` boxes (see the module docstring for the
    statuses); `deadline`: the run's wall-clock cap (None: none)."""
    from certify.prove.dissipation import prove_dissipation

    t0 = time.perf_counter()
    eps_P = 0.0
    if not problem.structural:
        eps_P = residual.upper_P if residual is not None else None
        if eps_P is None:
            return DissipationResult(Status.NOT_APPLICABLE, "not applicable: no sound bound "
                                     "of ||P^(1/2) k(x, h(x))|| (residual check)")
    out = prove_dissipation(problem, vbar=settings.noise, eps_P=eps_P,
                            max_boxes=settings.dissipation_boxes, deadline=deadline,
                            seed=settings.seed)
    return DissipationResult(
        status=out.status, message=out.message, alpha=out.alpha, mu=out.mu,
        mu_residual=out.mu_residual, eps_bar=eps_P if out.mu_residual else None,
        vertices=out.vertices, candidates=out.candidates, boxes=out.boxes,
        route=out.route or None, seconds=time.perf_counter() - t0,
        proof=ProofStats(boxes_processed=out.boxes, seconds=time.perf_counter() - t0,
                         stopped_by_cap=out.stopped_by_cap))


class DissipationCheck(Check):
    """V = e^T P e with V' <= -alpha V + mu ||v||^2 (+ mu_r ||P^(1/2) r||^2), proved over X x Y."""

    name = "dissipation"
    title = "Dissipation certificate"
    result_type = DissipationResult
    reads = ("noise", "dissipation_boxes", "seed")
    uses = ("residual",)

    def run(self, context: Context) -> DissipationResult:
        return check_dissipation(context.on_device(), context.settings,
                                 residual=context.result("residual"),
                                 deadline=context.deadline)

    def present(self, r: DissipationResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        return Presentation(
            sampled=Quantity("sampled aim", r.candidates[0]["bound"] if r.candidates else None,
                             "no candidate"),
            proved=Quantity("\u03b1, \u03bc", None if r.alpha is None else
                            f"{lower_text(r.alpha, 4)}, {upper_text(r.mu, 4)}", "not proved"),
            setting=(setting_quantity("dissipation_boxes", s),),
            numbers=(Quantity("alpha", r.alpha, sig=6, bound="lower"),
                     Quantity("mu", r.mu, sig=6, bound="upper"),
                     Quantity("mu_residual", r.mu_residual, sig=6, bound="upper"),
                     Quantity("route", r.route),
                     Quantity("pieces proved", r.vertices),
                     Quantity("boxes", r.boxes)),
            facts=(Quantity("Status", r.status.value),
                   Quantity("Rate of V (alpha)", r.alpha, "not proved", sig=6, bound="lower"),
                   Quantity("Noise gain (mu)", r.mu, "not proved", sig=6, bound="upper"),
                   Quantity("Residual gain", r.mu_residual, "none (structural gain)", sig=6,
                            bound="upper"),
                   Quantity("Certificate", {"path": "path (one proof, dk/dy at the same "
                                            "point)", "cover": "cover of dk/dy (one proof per "
                                            "piece)"}.get(r.route or "", None), "none"),
                   Quantity("Pieces proved", r.vertices),
                   Quantity("Candidates tried", len(r.candidates))))


CHECK = DissipationCheck()
