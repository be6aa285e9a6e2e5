"""How many boxes a complete decision proof takes, estimated by random descents.

A budgeted proof that ends UNKNOWN says how much volume it closed, not how far it is from
done. In decision mode the branch-and-bound tree is fixed by the box bound and the split rule
alone: each box is closed or split on its own bound against the fixed threshold, whatever
order the rounds take (`certify.search.bnb`). So the tree can be sampled (Knuth's estimator): follow
uniform random points z of the root box down from their first-round box, evaluating each box
on the way with the proof's own evaluation and splitting it by the proof's own rule
(`certify.search.bnb.split_dimensions`) until the box containing z closes. A leaf at depth L
(halvings from the root) holds 2^-L of the volume, so the tree has E_z[2^L(z)] leaves; grown
from F first-round boxes by S splits it has F + S leaves and F + 2 S boxes, so a complete
proof evaluates 2 leaves - F boxes. The mean is unbiased but heavy-tailed (a few deep points
near the critical region carry much of it), hence the relative standard error beside it.
Cost: one box evaluation per point and level, batched over the points. A point still open
at `max_depth` (NaN/Inf bounds: the proof would set it aside) is counted as stuck and left
out.

Nothing here is a bound or part of a verdict: the estimate only tells a user whether a
larger budget is worth it (`certify.prove.mpdi.prove_mpdi`), and bench/tree_size.py measures
the prover with it. Its work is bounded in descents and box evaluations; an optional time
limit (`estimate_tree(seconds=...)`, what is left of a run's wall-clock cap) sizes the
batches of descents to it and leaves out a batch not finished in time (no batch finished:
no estimate).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from certify.arith.boxes import Box, initial_grid, split
from certify.search.bnb import split_dimensions
from certify.search.evaluation import BoxEval


@dataclass
class TreeEstimate:
    """The estimated size of a complete decision proof (module docstring)."""

    leaves: float  # leaves of the whole tree (nan when every point was stuck)
    boxes: float  # boxes a complete proof evaluates: 2 leaves - first round
    rel_stderr: float  # standard error of the leaf estimate, relative
    points: int  # random descents
    stuck: int  # descents still open at the depth limit (left out)
    evaluations: int  # boxes evaluated by the descents
    depth_quantiles: list[int]  # leaf depths at 10, 50, 90, 99 %


def leaf_depths(evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval], lo: torch.Tensor,
                hi: torch.Tensor, first_round: int, z: torch.Tensor, threshold: float = 0.0,
                max_depth: int = 80, deadline: float | None = None
                ) -> tuple[torch.Tensor | None, int]:
    """(depth of the closed leaf containing each point z [P, d] of the root box [lo, hi], -1
    where stuck; box evaluations spent) in the decision tree of `evaluate` at `threshold`
    whose first round splits the root into about `first_round` boxes. `deadline` (a
    `time.perf_counter()` value): the clock is read before each level, and past it the
    descents stop unfinished (depths None)."""
    scale = (hi - lo).clamp_min(1e-300)
    z = z.to(device=lo.device, dtype=torch.float64)
    points = z.shape[0]
    grid = initial_grid(lo, hi, first_round)
    inside = ((z[:, None] >= grid.lo[None]) & (z[:, None] <= grid.hi[None])).all(-1)
    first = inside.to(torch.int8).argmax(1)  # the first box holding z (shared faces: any)
    blo, bhi = grid.lo[first].clone(), grid.hi[first].clone()
    depth = grid.depth[first].clone()
    leaf = torch.full((points,), -1, dtype=torch.long, device=lo.device)
    active = torch.arange(points, device=lo.device)
    evaluations = 0
    while len(active):
        if deadline is not None and time.perf_counter() > deadline:
            return None, evaluations
        ev = evaluate(blo[active], bhi[active])
        evaluations += len(active)
        closed = (ev.upper <= threshold) & torch.isfinite(ev.upper)
        leaf[active[closed]] = depth[active[closed]]
        go = ~closed & (depth[active] < max_depth)  # the rest are stuck: stay -1
        active, score = active[go], None if ev.score is None else ev.score[go]
        if not len(active):
            break
        dims = split_dimensions(blo[active], bhi[active], score, scale)
        kids = split(Box(blo[active], bhi[active], depth[active]), dims)  # the prover's halves
        m = len(active)
        ar = torch.arange(m, device=lo.device)
        upper = z[active, dims] > kids.hi[ar, dims]  # z lies in the second half
        pick = ar + m * upper.long()
        blo[active], bhi[active], depth[active] = kids.lo[pick], kids.hi[pick], kids.depth[pick]
    return leaf.cpu(), evaluations


#: the fewest descents in a batch sized to a time limit (`estimate_tree`)
MIN_POINTS = 16


def summarize(leaf: torch.Tensor, evaluations: int, first_round: int = 0) -> TreeEstimate:
    """The `TreeEstimate` from leaf depths (-1: stuck) of a tree grown from `first_round`
    boxes."""
    ok = leaf >= 0
    stuck = int((~ok).sum())
    if not bool(ok.any()):
        return TreeEstimate(math.nan, math.nan, math.inf, len(leaf), stuck, evaluations, [])
    w = torch.pow(2.0, leaf[ok].to(torch.float64))
    mean = float(w.mean())
    se = float(w.std()) / math.sqrt(len(w)) if len(w) > 1 else math.inf
    q = torch.quantile(leaf[ok].to(torch.float64),
                       torch.tensor([0.1, 0.5, 0.9, 0.99], dtype=torch.float64,
                                    device=leaf.device))
    return TreeEstimate(mean, max(2.0 * mean - first_round, mean), se / mean, len(leaf), stuck,
                        evaluations, [int(v) for v in q])


def estimate_tree(evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval], lo: torch.Tensor,
                  hi: torch.Tensor, first_round: int, points: int = 256, seed: int = 0,
                  threshold: float = 0.0, max_depth: int = 80, *,
                  target_rel_stderr: float | None = None, max_points: int | None = None,
                  max_evaluations: int | None = None, seconds: float | None = None,
                  box_seconds: float | None = None, levels: int | None = None
                  ) -> TreeEstimate:
    """`points` seeded uniform descents (drawn on the CPU: the same points on every device)
    through the decision tree of `evaluate`, summarised. With `target_rel_stderr`, further
    batches of `points` descents (the next seeds) follow until the relative standard error
    is at most that, or `max_points` descents or `max_evaluations` box evaluations are spent:
    budgets in descents and boxes, so the estimate depends on the inputs alone, except
    where the time limit `seconds` binds: then the batches hold fewer descents, as many as
    fit in it at `box_seconds` per box evaluation and about `levels` evaluations per descent
    (when both are given; at least MIN_POINTS), and a batch the clock stops is left out. No
    batch finished: an estimate of nan boxes from 0 descents."""
    deadline = None if seconds is None else time.perf_counter() + seconds
    if seconds is not None and box_seconds is not None and levels is not None:
        fit = int(seconds / max(box_seconds * max(levels, 1), 1e-12))
        points = max(MIN_POINTS, min(points, fit))
    leaves: list[torch.Tensor] = []
    evaluations, batch = 0, 0
    est = summarize(torch.empty(0, dtype=torch.long, device="cpu"), 0, first_round)
    while True:
        gen = torch.Generator().manual_seed(seed + batch)
        u = torch.rand(points, lo.shape[0], generator=gen, dtype=torch.float64, device="cpu")
        z = lo.cpu() + (hi - lo).cpu() * u
        leaf, spent = leaf_depths(evaluate, lo, hi, first_round, z, threshold, max_depth,
                                  deadline)
        evaluations += spent
        if leaf is None:  # out of time: the batch is left out
            est.evaluations = evaluations
            return est
        leaves.append(leaf)
        batch += 1
        est = summarize(torch.cat(leaves), evaluations, first_round)
        if (target_rel_stderr is None or est.rel_stderr <= target_rel_stderr
                or (max_points is not None and est.points + points > max_points)
                or (max_evaluations is not None
                    and evaluations + spent > max_evaluations)):
            return est


def completion_text(boxes: float | None, rel_stderr: float | None, done: int) -> str:
    """The user's line on an unfinished proof: about how many boxes a complete one evaluates,
    from the estimate ("" without one). No timings: a verdict's message depends on the
    inputs alone, not on the machine (the seconds are in the proof's stats)."""
    if boxes is None or not math.isfinite(boxes) or boxes <= 0:
        return ""
    spread = (f", +-{100 * rel_stderr:.0f}%" if rel_stderr is not None
              and math.isfinite(rel_stderr) else "")
    return (f"a complete proof would evaluate about {boxes:.2g} boxes (random-descent "
            f"estimate{spread}; this run: {done})")


#: an estimate this many times the budget is "far above" it (`forecast_text`)
FAR_ABOVE = 10.0


def forecast_text(boxes: float | None, rel_stderr: float | None, budget: int) -> str:
    """The user's line before a proof starts: the estimated boxes of a complete proof against
    the box budget ("" without an estimate); where the estimate is FAR_ABOVE times the budget
    or more, that the proof is not expected to finish. An estimate, not a bound: the words say
    "likely", never what the verdict will be."""
    if boxes is None or not math.isfinite(boxes) or boxes <= 0:
        return ""
    spread = (f", +-{100 * rel_stderr:.0f}%" if rel_stderr is not None
              and math.isfinite(rel_stderr) else "")
    text = (f"tree estimate: a complete proof evaluates about {boxes:.2g} boxes (random-descent "
            f"estimate{spread}); the budget is {budget:,} boxes")
    if boxes >= FAR_ABOVE * budget:
        text += ("; far above the budget: the proof is not expected to finish, and unless a "
                 "counterexample is found the result will likely be INCONCLUSIVE")
    return text


__all__ = ["TreeEstimate", "leaf_depths", "summarize", "estimate_tree", "completion_text",
           "forecast_text"]
