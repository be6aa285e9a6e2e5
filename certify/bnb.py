"""Generic batched branch and bound over boxes: bound the maximum of a function soundly.

The caller supplies `evaluate(lo, hi) -> BoxEval`: for each box a sound upper bound of the
function over the box, its float64 value at the box centre (a falsification point) and a
split score per dimension. The driver keeps the open boxes as tensors, takes the worst
(largest upper bound) `batch` of them each step (in decision mode: half worst, half nearest to
closing), bisects each along its best dimension and evaluates the children together.
A box is closed when its bound is at most `threshold`
(decision mode: proved) or within `tol` of the best value found (maximisation mode). NaN or
Inf bounds never close a box; a box split past `max_depth` is set aside as UNKNOWN.

The loop runs in deterministic rounds (the executor contract, `certify.executor`): each round
takes the `batch` worst open boxes in a fixed order (stable sort on the bound), bisects them,
evaluates all children with one `evaluate(lo, hi)` call, then closes / sets aside in order.
In decision mode half of each batch is instead the open boxes nearest to the threshold (the
rest the worst), so a run cut short by its budget has closed what was nearly closed.
With an `executor` of more than one worker and a picklable `remote = (chunk_fn, payload)`
(`chunk_fn(payload, lo, hi) -> BoxEval`, module level), the children are cut into
`executor.workers * CHUNKS_PER_WORKER` contiguous chunks (the batch raised to fill the workers,
`certify.executor.round_batch`; unchanged up to 2 workers) evaluated with
`executor.map_chunks` and concatenated in order, so the boxes, bounds and verdict are those
of the serial run for the same box budget (up to the last bits of BLAS products whose
blocking depends on the chunk size; bounds stay sound either way).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from certify.intervals import ROUNDING
from certify.progress import NullProgress, Progress
from certify.results import ProofStats


@dataclass
class Box:
    """A batch of boxes: lo, hi [batch, d] (float64) and their bisection depth [batch]."""

    lo: torch.Tensor
    hi: torch.Tensor
    depth: torch.Tensor

    @property
    def centre(self) -> torch.Tensor:
        return 0.5 * (self.lo + self.hi)

    def volume(self) -> torch.Tensor:
        return (self.hi - self.lo).prod(-1)

    def __len__(self) -> int:
        return int(self.lo.shape[0])


@dataclass
class BoxEval:
    """What `evaluate` returns for N boxes."""

    upper: torch.Tensor  # [N] sound upper bound over the box (NaN: unknown)
    centre_value: torch.Tensor  # [N] value at the centre in float64 (a lower bound of the max)
    score: torch.Tensor | None = None  # [N, d] split score (None: widest scaled dimension)


@dataclass
class BnBOutcome:
    """Result of one branch-and-bound run."""

    upper: float  # sound upper bound of the max over the root box (inf/NaN if unknown)
    lower: float  # best value found at evaluated points
    best_point: torch.Tensor | None  # [d] where `lower` was found
    violated: bool  # a point with value > threshold was found (decision mode)
    complete: bool  # every box closed (the bound is final)
    stats: ProofStats
    leaves: dict[str, list] = field(default_factory=dict)  # projected leaves for the report
    stuck: int = 0  # boxes set aside as UNKNOWN (NaN or max depth)


def initial_grid(lo: torch.Tensor, hi: torch.Tensor, target: int) -> Box:
    """Split the root box [d] into about `target` equal boxes (more cuts on wider sides)."""
    d = lo.shape[0]
    width = (hi - lo).double()
    cuts = torch.ones(d, dtype=torch.long)
    while int(cuts.prod()) * 2 <= max(target, 1):
        i = int(torch.argmax(width / cuts))
        cuts[i] *= 2
    axes = [torch.linspace(0.0, 1.0, int(c) + 1, dtype=torch.float64) for c in cuts]
    los = torch.cartesian_prod(*[a[:-1] for a in axes]).reshape(-1, d)
    his = torch.cartesian_prod(*[a[1:] for a in axes]).reshape(-1, d)
    blo = lo + los * width
    bhi = lo + his * width
    # exact shared faces and the exact root faces
    blo = torch.where(los == 0, lo.expand_as(blo), blo)
    bhi = torch.where(his == 1, hi.expand_as(bhi), bhi)
    depth = torch.full((blo.shape[0],), int(torch.log2(cuts.double()).sum()), dtype=torch.long)
    return Box(blo, bhi, depth)


def _cat(a: Box, b: Box) -> Box:
    return Box(torch.cat([a.lo, b.lo]), torch.cat([a.hi, b.hi]), torch.cat([a.depth, b.depth]))


def _take(a: Box, idx: torch.Tensor) -> Box:
    return Box(a.lo[idx], a.hi[idx], a.depth[idx])


CHUNKS_PER_WORKER = 1  # one task per worker per round: fewest round trips


def _evaluate_round(evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
                    lo: torch.Tensor, hi: torch.Tensor, executor: Any, remote: Any) -> BoxEval:
    """One round's evaluation: in process, or chunked over the executor's workers."""
    if executor is None or remote is None \
            or not (getattr(executor, "remote", False) or getattr(executor, "workers", 1) > 1) \
            or len(lo) < 2:
        return evaluate(lo, hi)
    from certify.executor import chunk_ranges

    chunk_fn, payload = remote
    ranges = chunk_ranges(len(lo), executor.workers * CHUNKS_PER_WORKER)
    parts = executor.map_chunks(chunk_fn, payload, [(lo[a:b], hi[a:b]) for a, b in ranges])
    score = None
    if all(p.score is not None for p in parts):
        score = torch.cat([p.score for p in parts])
    return BoxEval(upper=torch.cat([p.upper for p in parts]),
                   centre_value=torch.cat([p.centre_value for p in parts]), score=score)


def split(box: Box, dims: torch.Tensor) -> Box:
    """Bisect each box along dims [N]; the two halves share the (float) midpoint exactly."""
    N = len(box)
    ar = torch.arange(N)
    mid = 0.5 * (box.lo[ar, dims] + box.hi[ar, dims])
    lo1, hi1 = box.lo.clone(), box.hi.clone()
    lo2, hi2 = box.lo.clone(), box.hi.clone()
    hi1[ar, dims] = mid
    lo2[ar, dims] = mid
    depth = box.depth + 1
    return Box(torch.cat([lo1, lo2]), torch.cat([hi1, hi2]), torch.cat([depth, depth]))


def branch_and_bound(
    root_lo: torch.Tensor,
    root_hi: torch.Tensor,
    evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
    *,
    threshold: float | None = None,
    tol: float = 0.0,
    rel_tol: float = 0.0,
    stop_on_violation: bool = True,
    seconds: float = 60.0,
    max_boxes: int = 2_000_000,
    batch: int = 1024,
    max_depth: int = 80,
    progress: Progress | None = None,
    task: str = "proof",
    keep_leaves: int = 5000,
    project: tuple[int, int] | None = (0, 1),
    seeds: Box | None = None,
    executor: Any = None,
    remote: tuple[Callable[..., BoxEval], Any] | None = None,
) -> BnBOutcome:
    """Sound upper bound of max f over [root_lo, root_hi] [d], refining the worst boxes first.

    Decision mode (`threshold` given): boxes with upper <= threshold close as proved; a
    centre value > threshold is a violation (stops when `stop_on_violation`). Maximisation
    mode: boxes with upper <= best + max(tol, rel_tol |best|) close; the result `upper` is
    the max over closed and open boxes. Budgets: `seconds` and `max_boxes` (boxes evaluated).
    `executor` / `remote`: where each round's children are evaluated (module docstring).
    """
    progress = progress or NullProgress()
    t0 = time.perf_counter()
    if remote is not None and executor is not None:
        from certify.executor import round_batch

        batch = round_batch(executor, batch)  # rounds sized to the workers
    root_lo = root_lo.to(torch.float64)
    root_hi = root_hi.to(torch.float64)
    d = root_lo.shape[0]
    scale = (root_hi - root_lo).clamp_min(1e-300)
    root_vol = float(scale.prod())
    progress.start(task, total=1.0)

    best = -math.inf
    best_point: torch.Tensor | None = None
    closed_max = -math.inf
    closed_vol = 0.0
    processed = 0
    max_seen_depth = 0
    history: list[list[float]] = [[0.0, 0.0]]
    violated = False
    stuck_count = 0
    stuck_max = -math.inf
    leaves_lo: list[torch.Tensor] = []
    leaves_hi: list[torch.Tensor] = []
    leaves_st: list[torch.Tensor] = []  # 0 proved/closed, 1 violated, 2 unknown
    leaves_area: list[torch.Tensor] = []
    px = list(project) if project is not None and d >= 2 else None

    def record(box: Box, status: int) -> None:
        if px is None or len(box) == 0:
            return
        lo2, hi2 = box.lo[:, px], box.hi[:, px]
        leaves_lo.append(lo2)
        leaves_hi.append(hi2)
        leaves_st.append(torch.full((len(box),), status, dtype=torch.int8))
        leaves_area.append((hi2 - lo2).prod(-1))
        # keep memory bounded: prune the smallest proved leaves beyond 20x the cap
        if sum(len(a) for a in leaves_area) > 20 * max(keep_leaves, 1):
            _compact(keep_leaves * 4)

    def _compact(cap: int) -> None:
        lo_all, hi_all = torch.cat(leaves_lo), torch.cat(leaves_hi)
        st_all, ar_all = torch.cat(leaves_st), torch.cat(leaves_area)
        pri = ar_all + (st_all > 0).double() * 1e300
        keep = torch.topk(pri, min(cap, len(pri))).indices
        leaves_lo[:] = [lo_all[keep]]
        leaves_hi[:] = [hi_all[keep]]
        leaves_st[:] = [st_all[keep]]
        leaves_area[:] = [ar_all[keep]]

    def update_best(ev: BoxEval, box: Box) -> None:
        nonlocal best, best_point
        cv = torch.nan_to_num(ev.centre_value, nan=-math.inf)
        if len(cv) == 0:
            return
        i = int(torch.argmax(cv))
        if float(cv[i]) > best:
            best = float(cv[i])
            best_point = box.centre[i].clone()

    # seeds: falsification points first (degenerate boxes give exact centre values)
    if seeds is not None and len(seeds) > 0:
        ev = evaluate(seeds.lo, seeds.hi)
        update_best(ev, seeds)
        if threshold is not None and best > threshold and stop_on_violation:
            violated = True

    open_box = initial_grid(root_lo, root_hi, batch)
    ev = _evaluate_round(evaluate, open_box.lo, open_box.hi, executor, remote)
    processed += len(open_box)
    update_best(ev, open_box)
    open_ub = ev.upper
    open_score = ev.score
    budget_exhausted = False

    def closing_level() -> float:
        lvl = -math.inf
        if threshold is not None:
            lvl = threshold
        if threshold is None or tol > 0 or rel_tol > 0:
            if math.isfinite(best):
                lvl = max(lvl, best + max(tol, rel_tol * abs(best)))
        return lvl

    last_report = t0
    while True:
        if threshold is not None and best > threshold and stop_on_violation:
            violated = True
        # close boxes
        lvl = closing_level()
        close = (open_ub <= lvl) & (open_ub < math.inf)  # NaN compares False: stays open
        if bool(close.any()):
            cb = _take(open_box, close)
            closed_vol += float(cb.volume().sum()) / root_vol
            closed_max = max(closed_max, float(open_ub[close].max()))
            record(cb, 0)
            keep = ~close
            open_box = _take(open_box, keep)
            open_ub = open_ub[keep]
            open_score = open_score[keep] if open_score is not None else None
        # set aside boxes that cannot be split further
        too_deep = open_box.depth >= max_depth
        if bool(too_deep.any()):
            sb = _take(open_box, too_deep)
            stuck_count += len(sb)
            ub = open_ub[too_deep]
            stuck_max = max(stuck_max, float(torch.nan_to_num(ub, nan=math.inf).max()))
            record(sb, 2)
            keep = ~too_deep
            open_box = _take(open_box, keep)
            open_ub = open_ub[keep]
            open_score = open_score[keep] if open_score is not None else None
        now = time.perf_counter()
        if now - last_report > 0.25:
            history.append([now - t0, closed_vol])
            progress.update(task, 0.0, proved=closed_vol, boxes=processed)
            last_report = now
        if len(open_box) == 0 or violated:
            break
        if now - t0 > seconds or processed >= max_boxes:
            budget_exhausted = True
            break
        # pick the boxes (stable order: deterministic rounds): the worst ones; in decision
        # mode half of the batch is the boxes nearest to closing instead, so that a budgeted
        # run closes regions early while the worst boxes (counterexamples) are still refined
        key = torch.nan_to_num(open_ub, nan=math.inf)
        k = min(batch, len(open_box))
        order = torch.sort(key, descending=True, stable=True).indices
        if threshold is not None and len(order) > k:
            kw = (k + 1) // 2
            idx = torch.cat([order[:kw], order[len(order) - (k - kw):]])
        else:
            idx = order[:k]
        mask = torch.zeros(len(open_box), dtype=torch.bool)
        mask[idx] = True
        work = _take(open_box, mask)
        wscore = open_score[mask] if open_score is not None else None
        open_box = _take(open_box, ~mask)
        open_ub = open_ub[~mask]
        open_score = open_score[~mask] if open_score is not None else None
        # split dimension: the caller's score, ties broken by scaled width
        widths = (work.hi - work.lo) / scale
        s = widths.clone()
        if wscore is not None:
            ws = torch.nan_to_num(wscore, nan=0.0, posinf=0.0)
            norm = ws.amax(-1, keepdim=True)
            use = norm > 0
            s = torch.where(use, ws / norm.clamp_min(1e-300) + 1e-3 * widths, widths)
        dims = torch.argmax(s, -1)
        kids = split(work, dims)
        max_seen_depth = max(max_seen_depth, int(kids.depth.max()))
        ev = _evaluate_round(evaluate, kids.lo, kids.hi, executor, remote)
        processed += len(kids)
        update_best(ev, kids)
        open_box = _cat(open_box, kids)
        open_ub = torch.cat([open_ub, ev.upper])
        if open_score is not None and ev.score is not None:
            open_score = torch.cat([open_score, ev.score])
        else:
            open_score = None

    elapsed = time.perf_counter() - t0
    history.append([elapsed, closed_vol])
    open_max = float(torch.nan_to_num(open_ub, nan=math.inf).max()) if len(open_box) else -math.inf
    upper = max(closed_max, open_max, stuck_max)
    complete = len(open_box) == 0 and stuck_count == 0 and not violated
    if len(open_box):
        record(open_box, 2)
    if violated and best_point is not None:
        vb = Box(best_point[None], best_point[None], torch.zeros(1, dtype=torch.long))
        record(vb, 1)
    leaves: dict[str, list] = {"lo": [], "hi": [], "status": []}
    if leaves_lo:
        _compact(keep_leaves)
        names = {0: "proved", 1: "violated", 2: "unknown"}
        leaves = {"lo": leaves_lo[0].tolist(), "hi": leaves_hi[0].tolist(),
                  "status": [names[int(v)] for v in leaves_st[0]]}
    stats = ProofStats(
        boxes_processed=processed,
        boxes_per_second=processed / max(elapsed, 1e-9),
        seconds=elapsed,
        proved_volume_fraction=min(closed_vol, 1.0),
        max_depth=max_seen_depth,
        budget_exhausted=budget_exhausted,
        rounding=ROUNDING,
        volume_history=_thin(history, 200),
    )
    progress.finish(task, f"{processed} boxes, {closed_vol:.4f} of the volume closed")
    return BnBOutcome(upper=upper, lower=best, best_point=best_point, violated=violated,
                      complete=complete, stats=stats, leaves=leaves, stuck=stuck_count)


def _thin(history: list[list[float]], cap: int) -> list[list[float]]:
    if len(history) <= cap:
        return history
    step = len(history) / cap
    out = [history[int(i * step)] for i in range(cap)]
    out[-1] = history[-1]
    return out
