"""Boundary-condition residual eps_bar = sup_{x in X} ||k(x, h(x))|| (METHOD §3.3)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from certify.arith.text import upper_text
from certify.checks.base import Check, Context, setting_quantity
from certify.model.kernels import gain_terms
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.prove.weighted import Weighting, weighting
from certify.results import ProofStats, ResidualResult, Status
from certify.search.falsify import maximize_over_box
from certify.search.witness import residual_lower
from certify.settings import VerifySettings


def residual_norm(problem: Problem, x: torch.Tensor) -> torch.Tensor:
    """||k(x, h(x))||_2 for x [B, n] -> [B]."""
    system = problem.system
    k = gain_terms(system, problem.network, x, system.h(x), with_dy=False).k
    return torch.linalg.vector_norm(k, dim=1)


def is_identity(P: np.ndarray) -> bool:
    """Whether the metric P is exactly I (then ||P^(1/2) k|| = ||k||: no weighted bound)."""
    P = np.asarray(P)
    return bool(np.array_equal(P, np.eye(P.shape[0])))


def check_residual(problem: Problem, settings: VerifySettings, *,
                   progress: Progress | None = None,
                   place: Callable[[Problem], Problem] | None = None,
                   weighted: Weighting | None = None,
                   deadline: float | None = None) -> ResidualResult:
    """Sampled + adversarial value of eps_bar (on `problem`) and a sound upper bound, with
    that of the weighted gain (`weighted`, default `weighting(problem)`) for a metric P != I;
    each bound within `settings.residual_boxes` boxes, on `place(problem)` (the run's
    device, `certify.checks.base.Context.on_device`; default the problem itself).
    `deadline`: the run's wall-clock cap (None: none)."""
    progress = progress or NullProgress()
    t0 = time.perf_counter()
    if problem.structural:
        return ResidualResult(Status.PROVED, "eps_bar = 0 exactly: the architecture "
                              "k = G(xhat, y)(y - h(xhat)) satisfies the boundary condition by "
                              "construction", 0.0, 0.0, structural=True,
                              seconds=time.perf_counter() - t0, upper_P=0.0)
    X = problem.system.X
    search = maximize_over_box(lambda x: residual_norm(problem, x), X[:, 0], X[:, 1],
                               grid_points=max(1000, settings.grid_points // 10),
                               starts=settings.adversarial_starts // 2 or 1,
                               steps=settings.adversarial_steps, top_k=1, seed=settings.seed,
                               progress=progress, task="residual grid")
    if search.nonfinite:
        return ResidualResult(Status.UNKNOWN, "k(x, h(x)) is NaN/Inf at some grid points",
                              float("nan"), None, seconds=time.perf_counter() - t0)
    from certify.prove.side import bound_residual

    worst = search.best_point.tolist()
    budget = dict(max_boxes=settings.residual_boxes, deadline=deadline, seeds=[worst])
    place = place or (lambda p: p)
    upper, _, stats = bound_residual(place(problem), **budget)
    proofs = [stats]
    # the reported eps_bar >= value is a SOUND lower bound at the worst point found
    sound = float(residual_lower(problem, torch.as_tensor(worst, dtype=torch.float64)[None])[0])
    sampled = max(sound, 0.0) if sound == sound else 0.0
    if upper is None or upper != upper:
        return ResidualResult(Status.UNKNOWN, f"eps_bar >= {sampled:.4g} (sampled); no sound "
                              "upper bound (a box stayed NaN/Inf)",
                              sampled, None, worst=worst, seconds=time.perf_counter() - t0,
                              proof=ProofStats.total(proofs))
    upper_P = None
    if not is_identity(problem.P):  # eps_bar_P, for the error bounds
        w = weighting(problem) if weighted is None else weighted
        bound_w, _, stats_w = bound_residual(place(w.problem), **budget)
        proofs.append(stats_w)
        upper_P = w.bound(bound_w, w.value_error)
    else:
        upper_P = float(upper)
    where = "" if upper_P is None else f"; ||P^(1/2) k(x, h(x))|| <= {upper_text(upper_P, 4)}"
    return ResidualResult(Status.PROVED,
                          f"eps_bar in [{sampled:.4g}, {upper_text(float(upper), 4)}]{where}",
                          sampled, float(upper), worst=worst, seconds=time.perf_counter() - t0,
                          upper_P=upper_P, proof=ProofStats.total(proofs))


# ----------------------------------------------------------------------------- check protocol

class ResidualCheck(Check):
    """The boundary-condition residual eps_bar = sup_X ||k(x, h(x))||: sampled and proved."""

    name = "residual"
    title = "Boundary residual \u03b5\u0304"
    result_type = ResidualResult
    reads = ("grid_points", "adversarial_starts", "adversarial_steps", "seed",
             "residual_boxes")

    def run(self, context: Context) -> ResidualResult:
        p = context.problem
        weighted = None if p.structural or is_identity(p.P) else context.weighted()
        return check_residual(p, context.settings, progress=context.progress,
                              place=context.on_device, weighted=weighted,
                              deadline=context.deadline)

    def present(self, r: ResidualResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        label = "\u03b5\u0304 \u2264 (interval B&B)"
        zero = r.structural and r.upper in (0, 0.0, None)
        proved = (Quantity(label, 0, suffix=" (by construction)") if zero
                  else Quantity(label, r.upper, "bound not established", bound="upper"))
        return Presentation(
            sampled=Quantity("\u03b5\u0304 \u2265 (sampled + ascent)", r.sampled, bound="lower"),
            proved=proved,
            setting=(setting_quantity("residual_boxes", s),),
            numbers=(Quantity("sampled", r.sampled, sig=6, bound="lower"),
                     Quantity("upper", r.upper, sig=6, bound="upper"),
                     Quantity("structural", r.structural)),
            facts=(Quantity("Status", r.status.value),
                   Quantity("Sampled \u03b5\u0304 \u2265", r.sampled, sig=6, bound="lower"),
                   Quantity("Sound bound \u03b5\u0304 \u2264", r.upper, "not established",
                            sig=6, bound="upper"),
                   Quantity("Zero by construction", r.structural),
                   Quantity("Worst x", r.worst, "none: zero by construction"
                            if r.structural else "not found")))


CHECK = ResidualCheck()
