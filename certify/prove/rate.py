"""Raising a proved lower bound on lam_cert by MPDI decisions (the rate check's ladder,
`certify.checks.rate`): lam_cert >= t iff D(t) <= 0 on X x Y, which `prove_mpdi(lam=t)`
decides with the decision-mode bounds."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from certify.model.problem import Problem
from certify.progress import Progress
from certify.prove.mpdi import prove_mpdi
from certify.results import ProofStats, Status


@dataclass
class RateLadder:
    """Where `raise_rate` got: lam_cert >= lower (proved), and lam_cert < upper when
    `violated` (a sound witness at that rate), else upper is the caller's sampled value."""

    lower: float
    upper: float
    violated: bool
    attempts: list[tuple[float, str, float]]  # (rate, status, seconds)
    #: each decision's stats, in order
    stats: list[ProofStats] = field(default_factory=list)


#: boxes the first target may take; each later one at most LADDER_GROWTH times the boxes of
#: the last proved (examples/vdp2_lmi.ckpt: 256, 256, 736, 2,272, 3,648 and 22,400 boxes for
#: successive halvings of the gap)
LADDER_FIRST_BOXES = 16_384
LADDER_GROWTH = 8


def raise_rate(problem: Problem, lower: float, upper: float, *, max_boxes: int,
               rel_tol: float = 1e-4, deadline: float | None = None,
               progress: Progress | None = None) -> RateLadder:
    """Raise a proved lower bound `lower` on lam_cert towards a sampled upper value `upper`
    by MPDI decisions: lam_cert >= t iff D(t) <= 0 on X x Y, which `prove_mpdi(lam=t)`
    decides with the decision-mode bounds (the Cholesky vertex tests, the mixed-row linear
    bounds). With an ill-conditioned P those are far stronger than the generalised-eigenvalue
    bound of `prove_rate`'s maximisation: on examples/vdp2_lmi.ckpt (P's condition ~1e3)
    `prove_rate` gained nothing over the design rate 1.0 in 20 s, while the decision at 1.11
    (sampled upper 1.119) proves in 0.2 s.

    Each target halves the gap to `upper`, until it is below rel_tol |upper|. A target gets
    at most LADDER_GROWTH times the boxes of the last proved one (LADDER_FIRST_BOXES for the
    first), within the `max_boxes` left of the ladder's budget: the proofs grow as the
    margin shrinks, and the first target not decided ends the ladder. Every cap is in
    boxes, so the ladder climbs to the same rate on a slow machine as on a fast one (with
    caps of 4x the last proof's time it stopped at 1.115 or 1.118 on vdp2_lmi, by the
    machine's load). A VIOLATED target (a sound witness) is an upper bound and the ladder
    goes on below it. `deadline`: the run's optional wall-clock cap (None: none); a decision
    it stops ends the ladder (`ProofStats.stopped_by_cap` in `stats`)."""
    cap = LADDER_FIRST_BOXES
    left = max_boxes
    stats: list[ProofStats] = []
    box_seconds = None  # a box's cost, measured by the last decision (spares its probes)
    attempts: list[tuple[float, str, float]] = []
    violated = False
    while upper - lower > rel_tol * abs(upper) and left > 0:
        target = 0.5 * (lower + upper)
        if not lower < target < upper:  # no float between them
            break
        t0 = time.perf_counter()
        out = prove_mpdi(problem, lam=target, max_boxes=min(left, cap), deadline=deadline,
                         progress=progress, task=f"rate decision at {target:.6g}",
                         estimate_points=0, box_seconds=box_seconds)
        took = time.perf_counter() - t0
        stats.append(out.stats)
        left -= out.stats.boxes_processed
        if out.stats.boxes_processed > 0 and out.stats.boxes_per_second > 0:
            box_seconds = 1.0 / out.stats.boxes_per_second
        attempts.append((target, out.status.value, round(took, 3)))
        if out.status is Status.PROVED:
            lower = target
            cap = max(LADDER_FIRST_BOXES, LADDER_GROWTH * out.stats.boxes_processed)
        elif out.status is Status.VIOLATED:
            upper, violated = target, True
        else:
            break
    return RateLadder(lower, upper, violated, attempts, stats)
