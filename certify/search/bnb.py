"""Generic batched branch and bound over boxes: bound the maximum of a function soundly.

The caller supplies `evaluate(lo, hi) -> BoxEval`: for each box a sound upper bound of the
function over the box, its float64 value at the box centre (a falsification point) and a
split score per dimension. The driver keeps the open boxes as tensors, takes the worst
(largest upper bound) `batch` of them each step (in decision mode: half worst, half nearest to
closing), bisects each along its best dimension and evaluates the children together.
A box is closed when its bound is at most `threshold`
(decision mode: proved) or within `tol` of the best value found (maximisation mode). NaN or
Inf bounds never close a box; a box split past `max_depth` is set aside as UNKNOWN.

The loop runs in deterministic rounds (the executor contract,
`certify.search.distributed.executor`): each round
takes the `batch` worst open boxes (`certify.search.frontier.Frontier.take`), bisects them and
dispatches all children as one evaluation; up to `lag` rounds are in flight at once
(`certify.search.rounds`: round k+1 is chosen before round k is merged, so workers never wait for
the driver), and rounds are merged oldest first: children closed, set aside or added to the
frontier in order. A batch is chosen only from merged results, and only when fewer than
`lag` rounds are in flight and the frontier can fill it (or nothing is in flight), so the
schedule depends on the results alone, never on timing; the serial path runs the same
schedule. In decision mode half of each batch is instead the open boxes nearest to the
threshold (the rest the worst), so a run cut short by its budget has closed what was nearly
closed. A run that stops (budget, violation) first merges the rounds in flight, so the
bound covers every box it dispatched.
With an `executor` of more than one worker and a picklable `remote = (chunk_fn, payload)`
(`chunk_fn(payload, lo, hi) -> BoxEval`, module level), the children are cut into
`executor.workers * CHUNKS_PER_WORKER` contiguous chunks (the batch raised to fill the workers,
`certify.search.distributed.executor.round_batch`; unchanged up to 2 workers) submitted together and
concatenated in order, so the boxes, bounds and verdict are those of the serial run for the
same box budget and lag (up to the last bits of BLAS products whose blocking depends on the
chunk size; bounds stay sound either way).

The time budget (`seconds`, counted from `started`) holds within a few seconds whatever a
box costs (`RoundClock`): a round evaluated in this process is evaluated in one call where its
predicted time fits (the cost per box is measured on every evaluation, and before the first
round by two small timing probes of it, thrown away), so a run that finishes within its
budget evaluates the same boxes in the same calls as with no clock (and a first round of at
most SETUP_SECONDS_ANYWAY is evaluated even when a caller's set-up used the budget up); a
round that may not fit is evaluated in chunks sized to the time left, the clock read between
them, and a round on an executor is waited for until the deadline, then cancelled.
Soundness of a round cut short: a box not evaluated keeps its parent's bound (a bound over a
superset; a first-round box has none: NaN, so the upper bound is +inf), stays open and is not
counted as processed; the run stops there, so its verdict is UNKNOWN unless every box closed
(nothing closes unevaluated, except in maximisation mode a box whose parent's bound is
already below the closing level).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from certify.arith.boxes import Box, initial_grid, split
from certify.arith.intervals import ROUNDING
from certify.progress import NullProgress, Progress
from certify.results import ProofStats
from certify.search.evaluation import BoxEval, join
from certify.search.frontier import Frontier
from certify.search.rounds import RoundPipeline


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


#: rounds in flight before the oldest is merged (1: synchronous rounds). 2 keeps the next
#: round queued on the workers while the driver merges. In a decision proof that closes, the
#: lag changes only the order in which boxes are refined, not which: each box is split or
#: closed on its own bound against the fixed threshold.
PIPELINE_LAG = 2


def split_dimensions(lo: torch.Tensor, hi: torch.Tensor, score: torch.Tensor | None,
                     scale: torch.Tensor) -> torch.Tensor:
    """The dimension [N] each box is bisected along: the largest of the caller's split score
    (normalised per box; NaN and +inf count as 0), ties broken by the width relative to the
    root's `scale`; the widest relative side where there is no score."""
    widths = (hi - lo) / scale
    s = widths
    if score is not None:
        ws = torch.nan_to_num(score, nan=0.0, posinf=0.0)
        norm = ws.amax(-1, keepdim=True)
        s = torch.where(norm > 0, ws / norm.clamp_min(1e-300) + 1e-3 * widths, widths)
    return torch.argmax(s, -1)


#: a round predicted to take at most this many seconds is evaluated in one call whatever the
#: time left (the overshoot it can cause is this small)
ROUND_SECONDS_ANYWAY = 1.0
#: a first round predicted to take at most this many seconds is evaluated in one call even
#: when the budget ran out before it (a caller's set-up, a loaded machine), so that a small
#: budget on a cheap problem still gives a bound; a caller's set-up (e.g.
#: `certify.prove.mpdi.mpdi_decision`) stops at max(budget, this)
SETUP_SECONDS_ANYWAY = 3.0
#: boxes of the two timing probes of the first round (their difference cancels the fixed
#: cost of a call); only where a box would have to cost more than MAX_BOX_SECONDS for the
#: round not to fit are they skipped
PROBE_BOXES = (4, 32)
MAX_BOX_SECONDS = 1.0
#: the smallest chunk of a round evaluated against the clock
MIN_CHUNK = 8


def unevaluated(n: int, d: int, device: torch.device | str = "cpu") -> BoxEval:
    """The `BoxEval` of n boxes [n, d] that were not evaluated (`BoxEval.done`)."""
    nan = torch.full((n,), math.nan, dtype=torch.float64, device=device)
    return BoxEval(upper=nan, centre_value=nan.clone(),
                   score=torch.zeros(n, d, dtype=torch.float64, device=device),
                   done=torch.zeros(n, dtype=torch.bool, device=device))


class RoundClock:
    """`evaluate` against a deadline (a `time.perf_counter()` value), for the rounds of one
    branch and bound evaluated in this process (module docstring).

    A round of N boxes is evaluated in one call when its predicted time, fixed + per_box N,
    is at most max(ROUND_SECONDS_ANYWAY, half the time left) and there is time left, or, for
    the first round, at most max(SETUP_SECONDS_ANYWAY, half the time left) whatever the time
    left: then the call is the one `evaluate(lo, hi)` of a run without a clock, and the
    boxes and bounds are the same bit for bit (evaluating in pieces can change the last bits
    of BLAS products). Otherwise the
    round is evaluated in chunks of at least MIN_CHUNK boxes, each sized to half the time
    left, the clock read between them; the boxes left when the deadline passes are returned
    unevaluated (`unevaluated`, `BoxEval.done`) and `expired` is set. The cost per box is
    measured on every call (the last one counts); before the first measurement a round
    larger than the probes is timed by evaluating its first PROBE_BOXES[0] and
    PROBE_BOXES[1] boxes (results thrown away: only the time is used), unless even a box
    cost of MAX_BOX_SECONDS would fit. Nothing here changes a bound; it only chooses how
    many boxes are evaluated per call and when to stop."""

    def __init__(self, evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
                 deadline: float, box_seconds: float | None = None) -> None:
        self.evaluate = evaluate
        self.deadline = deadline
        self.per_box = box_seconds  # seconds per box (None: not measured yet)
        self.fixed = 0.0  # seconds per call beside the boxes (from the probes)
        self.expired = False
        self.first = True  # the next call is the first round

    def left(self) -> float:
        return self.deadline - time.perf_counter()

    def predict(self, n: int) -> float:
        return self.fixed + (self.per_box or 0.0) * n

    def _timed(self, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        t = time.perf_counter()
        out = self.evaluate(lo, hi)
        self.per_box, self.fixed = (time.perf_counter() - t) / max(len(lo), 1), 0.0
        return out

    def _probe(self, lo: torch.Tensor, hi: torch.Tensor) -> None:
        a, b = PROBE_BOXES
        t = time.perf_counter()
        self.evaluate(lo[:a], hi[:a])
        ta = time.perf_counter() - t
        t = time.perf_counter()
        self.evaluate(lo[:b], hi[:b])
        tb = time.perf_counter() - t
        self.per_box = max(tb - ta, 0.0) / (b - a)
        self.fixed = max(tb - self.per_box * b, 0.0)

    def __call__(self, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        n, left = len(lo), self.left()
        first, self.first = self.first, False
        if left <= 0 and not first:
            self.expired = True
            return unevaluated(n, lo.shape[1], lo.device)
        anyway = SETUP_SECONDS_ANYWAY if first else ROUND_SECONDS_ANYWAY
        room = max(anyway, 0.5 * left)
        if self.per_box is None and n > PROBE_BOXES[1] and room < MAX_BOX_SECONDS * n:
            self._probe(lo, hi)
            left = self.left()
            room = max(anyway, 0.5 * left)
        if self.per_box is None or ((left > 0 or first) and self.predict(n) <= room):
            return self._timed(lo, hi)
        return self._chunked(lo, hi)

    def _chunked(self, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        n = len(lo)
        parts: list[BoxEval] = []
        start = 0
        while start < n:
            left = self.left()
            if left <= 0:
                break
            per_box = max(self.per_box or 0.0, 1e-9)
            m = max(MIN_CHUNK, int((0.5 * left - self.fixed) / per_box))
            stop = min(n, start + m)
            parts.append(self._timed(lo[start:stop], hi[start:stop]))
            start = stop
        if start < n:
            self.expired = True
            parts.append(unevaluated(n - start, lo.shape[1], lo.device))
        return join(parts)


def branch_and_bound(
    root_lo: torch.Tensor,
    root_hi: torch.Tensor,
    evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
    *,
    threshold: float | None = None,
    tol: float = 0.0,
    rel_tol: float = 0.0,
    coarse_after: tuple[int, float] | None = None,
    give_up: tuple[int, float] | None = None,
    stop_on_violation: bool = True,
    seconds: float = 60.0,
    max_boxes: int = 2_000_000,
    batch: int = 1024,
    first_round: int | None = None,
    max_depth: int = 80,
    progress: Progress | None = None,
    task: str = "proof",
    keep_leaves: int = 5000,
    project: tuple[int, int] | None = (0, 1),
    seeds: Box | None = None,
    executor: Any = None,
    remote: tuple[Callable[..., BoxEval], Any] | None = None,
    lag: int = PIPELINE_LAG,
    started: float | None = None,
    box_seconds: float | None = None,
) -> BnBOutcome:
    """Sound upper bound of max f over [root_lo, root_hi] [d], refining the worst boxes first.

    Decision mode (`threshold` given): boxes with upper <= threshold close as proved; a
    centre value > threshold is a violation (stops when `stop_on_violation`). Maximisation
    mode: boxes with upper <= best + max(tol, rel_tol |best|) close; the result `upper` is
    the max over closed and open boxes. `coarse_after = (N, coarse)`: once N boxes have been
    evaluated the closing tolerance relaxes to `coarse` (a fine precision where it is cheap,
    never more than N boxes spent on it beyond the coarse one; boxes closed before stay
    closed, their bounds are below either level). `give_up = (N, level)` (maximisation): once
    N boxes have been evaluated, the run stops as if its budget were spent when the largest
    bound of the merged boxes, open or closed, is still above `level` (the caller has a
    better way past that level); the check only chooses when to stop, the bound is then
    formed as for any budgeted run. Budgets: `seconds` (wall clock from `started`, a
    `time.perf_counter()` value, default the call: a caller's own set-up counts in its
    budget) and `max_boxes` (boxes evaluated); the time budget is held inside long rounds
    (module docstring, `RoundClock`; `box_seconds`: a caller's estimate of the seconds a box
    costs, e.g. from an earlier run on the same problem, which spares the timing probes).
    `first_round`: the root is first split into about that many equal boxes
    (default and at most `batch`). `executor` / `remote`: where each round's children are
    evaluated; `lag`: rounds in flight before the oldest is merged (module docstring). The
    outcome depends on `lag` and the budgets, not on the executor.
    """
    progress = progress or NullProgress()
    t0 = time.perf_counter()
    deadline = (t0 if started is None else started) + seconds
    if remote is not None and executor is not None:
        from certify.search.distributed.executor import round_batch

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

    def record(lo: torch.Tensor, hi: torch.Tensor, status: int) -> None:
        if px is None or len(lo) == 0:
            return
        lo2, hi2 = lo[:, px], hi[:, px]
        leaves_lo.append(lo2)
        leaves_hi.append(hi2)
        leaves_st.append(torch.full((len(lo),), status, dtype=torch.int8, device=lo.device))
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

    def closing_level() -> float:
        lvl = -math.inf
        if threshold is not None:
            lvl = threshold
        rt = rel_tol
        if coarse_after is not None and processed >= coarse_after[0]:
            rt = max(rel_tol, coarse_after[1])
        if threshold is None or tol > 0 or rt > 0:
            if math.isfinite(best):
                lvl = max(lvl, best + max(tol, rt * abs(best)))
        return lvl

    def close(lo: torch.Tensor, hi: torch.Tensor, ub: torch.Tensor) -> None:
        nonlocal closed_vol, closed_max
        if len(lo):
            closed_vol += float((hi - lo).prod(-1).sum()) / root_vol
            closed_max = max(closed_max, float(ub.max()))
            record(lo, hi, 0)

    # seeds: falsification points first (degenerate boxes give exact centre values)
    if seeds is not None and len(seeds) > 0:
        ev = evaluate(seeds.lo, seeds.hi)
        update_best(ev, seeds)
        if threshold is not None and best > threshold and stop_on_violation:
            violated = True

    frontier = Frontier(d, device=root_lo.device)
    clock = RoundClock(evaluate, deadline, box_seconds)
    rounds = RoundPipeline(clock, executor, remote)
    # the boxes of each round in flight, oldest first, with their parents' bounds
    in_flight: deque[tuple[Box, torch.Tensor]] = deque()
    scanned_level = -math.inf  # the frontier holds no box closed at this level
    cut_short = False  # some dispatched box was not evaluated in time
    # an executor's first round is waited for at least SETUP_SECONDS_ANYWAY (as RoundClock
    # evaluates a cheap first round in this process whatever the time left)
    first_wait = [time.perf_counter() + SETUP_SECONDS_ANYWAY]

    def dispatch(box: Box, parent_upper: torch.Tensor) -> None:
        nonlocal processed
        rounds.dispatch(box.lo, box.hi)
        in_flight.append((box, parent_upper))
        processed += len(box)

    def merge() -> None:
        """The oldest round in flight: best point, violation, then its boxes closed, set
        aside (too deep) or added to the frontier, in order. A box its round did not
        evaluate in time keeps its parent's bound and is not counted as processed."""
        nonlocal violated, scanned_level, stuck_count, stuck_max, processed, cut_short
        box, parent_upper = in_flight.popleft()
        ev = rounds.collect(max(deadline, first_wait.pop()) if first_wait else deadline)
        if ev is None:  # an executor's round not back by the deadline (cancelled)
            ev = unevaluated(len(box), d, root_lo.device)
        if ev.done is not None and not bool(ev.done.all()):
            skipped = ~ev.done
            processed -= int(skipped.sum())
            cut_short = True
            ev = BoxEval(upper=torch.where(skipped, parent_upper, ev.upper),
                         centre_value=ev.centre_value, score=ev.score)
        update_best(ev, box)
        if threshold is not None and best > threshold and stop_on_violation:
            violated = True
        lvl = closing_level()
        if lvl > scanned_level:  # the level rose (maximisation): open boxes may close now
            shut = frontier.close(lvl)
            if shut is not None:
                close(*shut)
            scanned_level = lvl
        ub = ev.upper
        shut = (ub <= lvl) & (ub < math.inf)  # NaN compares False: stays open
        close(box.lo[shut], box.hi[shut], ub[shut])
        deep = ~shut & (box.depth >= max_depth)
        if bool(deep.any()):  # cannot be split further: set aside as UNKNOWN
            stuck_count += int(deep.sum())
            stuck_max = max(stuck_max, float(torch.nan_to_num(ub[deep], nan=math.inf).max()))
            record(box.lo[deep], box.hi[deep], 2)
        keep = ~shut & ~deep
        frontier.add(box.lo[keep], box.hi[keep], box.depth[keep], ub[keep],
                     ev.score[keep] if ev.score is not None else None)

    first = initial_grid(root_lo, root_hi, batch if first_round is None
                         else max(1, min(first_round, batch)))
    dispatch(first, torch.full((len(first),), math.nan, dtype=torch.float64,
                               device=root_lo.device))  # the root has no bound
    budget_hit = False
    last_report = t0
    try:
        while True:
            # merge the oldest round while `lag` rounds are in flight, while the frontier
            # cannot fill a batch, and (to stop) after a violation: a function of the
            # merged results only, so every executor runs the same schedule
            while in_flight and (len(in_flight) >= lag or len(frontier) < batch or violated):
                merge()
            now = time.perf_counter()
            if now - last_report > 0.25:
                history.append([now - t0, closed_vol])
                progress.update(task, 0.0, proved=closed_vol, boxes=processed)
                last_report = now
            if len(frontier) == 0 or violated:
                break
            if now > deadline or cut_short or clock.expired or processed >= max_boxes:
                budget_hit = True
                break
            if give_up is not None and processed >= give_up[0]:
                if max(closed_max, frontier.open_max(), stuck_max) > give_up[1]:
                    budget_hit = True
                    break
                give_up = None  # checked once
            # the boxes to refine: the worst ones; in decision mode half of the batch is the
            # boxes nearest to closing instead, so that a budgeted run closes regions early
            # while the worst boxes (counterexamples) are still refined
            lo, hi, depth, wscore, ub = frontier.take(batch, threshold is not None,
                                                      with_upper=True)
            kids = split(Box(lo, hi, depth), split_dimensions(lo, hi, wscore, scale))
            max_seen_depth = max(max_seen_depth, int(kids.depth.max()))
            dispatch(kids, torch.cat([ub, ub]))  # split() puts the first halves first
        while in_flight:  # stopped: merge what was dispatched (the bound covers it all)
            merge()
    finally:
        rounds.cancel()
    budget_exhausted = budget_hit and len(frontier) > 0

    elapsed = time.perf_counter() - t0
    history.append([elapsed, closed_vol])
    upper = max(closed_max, frontier.open_max(), stuck_max)
    complete = len(frontier) == 0 and stuck_count == 0 and not violated
    if len(frontier):
        record(*frontier.boxes(), 2)
    if violated and best_point is not None:
        record(best_point[None], best_point[None], 1)
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
