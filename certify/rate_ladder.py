"""Raising a proved lower bound on lam_cert by MPDI decisions (the rate check's ladder,
`certify.checks.rate`): lam_cert >= t iff D(t) <= 0 on X x Y, which `prove_mpdi(lam=t)`
decides with the decision-mode bounds."""

from __future__ import annotations

import time
from dataclasses import dataclass

from certify.problem import Problem
from certify.progress import Progress
from certify.prover import prove_mpdi
from certify.results import Status


@dataclass
class RateLadder:
    """Where `raise_rate` got: lam_cert >= lower (proved), and lam_cert < upper when
    `violated` (a sound witness at that rate), else upper is the caller's sampled value."""

    lower: float
    upper: float
    violated: bool
    attempts: list[tuple[float, str, float]]  # (rate, status, seconds)


def raise_rate(problem: Problem, lower: float, upper: float, *, seconds: float,
               max_boxes: int = 2_000_000, rel_tol: float = 1e-4,
               progress: Progress | None = None) -> RateLadder:
    """Raise a proved lower bound `lower` on lam_cert towards a sampled upper value `upper`
    by MPDI decisions: lam_cert >= t iff D(t) <= 0 on X x Y, which `prove_mpdi(lam=t)`
    decides with the decision-mode bounds (the Cholesky vertex tests, the mixed-row linear
    bounds). With an ill-conditioned P those are far stronger than the generalised-eigenvalue
    bound of `prove_rate`'s maximisation: on examples/vdp2_lmi.ckpt (P's condition ~1e3)
    `prove_rate` gained nothing over the design rate 1.0 in 20 s, while the decision at 1.11
    (sampled upper 1.119) proves in 0.2 s.

    Each target halves the gap to `upper`, until it is below rel_tol |upper|. A target gets
    at most 4x the time of the last proved one (at least 1 s; in all at most `seconds`): the
    proofs grow as the margin shrinks, and the first target not decided ends the ladder. A
    VIOLATED target (a sound witness) is an upper bound and the ladder goes on below it."""
    t_start = time.perf_counter()
    last = 0.25
    attempts: list[tuple[float, str, float]] = []
    violated = False
    while upper - lower > rel_tol * abs(upper):
        left = seconds - (time.perf_counter() - t_start)
        if left <= 0.05:
            break
        target = 0.5 * (lower + upper)
        if not lower < target < upper:  # no float between them
            break
        t0 = time.perf_counter()
        out = prove_mpdi(problem, lam=target, seconds=min(left, max(4.0 * last, 1.0)),
                         max_boxes=max_boxes, progress=progress,
                         task=f"rate decision at {target:.6g}", estimate_points=0)
        took = time.perf_counter() - t0
        attempts.append((target, out.status.value, round(took, 3)))
        if out.status is Status.PROVED:
            lower, last = target, took
        elif out.status is Status.VIOLATED:
            upper, violated = target, True
        else:
            break
    return RateLadder(lower, upper, violated, attempts)
