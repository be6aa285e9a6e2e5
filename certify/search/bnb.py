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

A run is described by a few objects: its `ClosingRule` (when a box closes, when to stop),
its `Budget` (boxes, optional cap), its `Schedule` (batch, first round, lag, depth limit) and
its `Output` (progress, leaves kept for the report).

Budgets: `max_boxes` counts the boxes evaluated, and a run honours it exactly (its first
round and its last are clipped to what is left), so where it binds a run evaluates the
same boxes on any machine. An optional wall-clock cap (`Budget.deadline`, e.g. from
`Budget.capped(seconds=...)`; None: no cap, and the clock is never read to decide anything)
holds within a few seconds whatever a box costs (`RoundClock`): a round evaluated in this
process is evaluated in one call where its predicted time fits (the cost per box is measured
on every evaluation, and before the first round by two small timing probes of it, thrown
away), so a
run that finishes within its cap evaluates the same boxes in the same calls as with no
clock (and a first round of at most SETUP_SECONDS_ANYWAY is evaluated even when a caller's
set-up used the cap up); a round that may not fit is evaluated in chunks sized to the time
left, the clock read between them, and a round on an executor is waited for until the
deadline, then cancelled. A run the cap stopped says so (`ProofStats.stopped_by_cap`).
Soundness of a round cut short: a box not evaluated keeps its parent's bound (a bound over a
superset; a first-round box has none: NaN, so the upper bound is +inf), stays open and is not
counted as processed; the run stops there, so its verdict is UNKNOWN unless every box closed
(nothing closes unevaluated, except in maximisation mode a box whose parent's bound is
already below the closing level).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from certify.arith.boxes import Box, initial_grid, split
from certify.arith.intervals import ROUNDING
from certify.budget import cap_deadline
from certify.progress import NullProgress, Progress
from certify.results import ProofStats
from certify.search.evaluation import BoxEval, add_counts, join
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


@dataclass(frozen=True)
class ClosingRule:
    """When a box closes and when a run stops for its bounds (`branch_and_bound`'s
    docstring): decision mode with a `threshold`, else maximisation with the tolerances
    `tol` and `rel_tol` (relaxed to `coarse_after[1]` once `coarse_after[0]` boxes were
    evaluated); `give_up = (N, level)` and `stop_on_violation` say when to stop early."""

    threshold: float | None = None
    tol: float = 0.0
    rel_tol: float = 0.0
    coarse_after: tuple[int, float] | None = None
    give_up: tuple[int, float] | None = None
    stop_on_violation: bool = True

    @property
    def decision(self) -> bool:
        return self.threshold is not None

    def level(self, best: float, processed: int) -> float:
        """Boxes whose bound is at most this close: the threshold, or (maximisation, or a
        tolerance given) the best value found plus the tolerance in force after `processed`
        boxes, whichever is higher."""
        lvl = -math.inf
        if self.threshold is not None:
            lvl = self.threshold
        rt = self.rel_tol
        if self.coarse_after is not None and processed >= self.coarse_after[0]:
            rt = max(self.rel_tol, self.coarse_after[1])
        if self.threshold is None or self.tol > 0 or rt > 0:
            if math.isfinite(best):
                lvl = max(lvl, best + max(self.tol, rt * abs(best)))
        return lvl


@dataclass(frozen=True)
class Budget:
    """What a run may spend: `max_boxes` boxes evaluated (honoured exactly) and an optional
    wall-clock cap, `deadline` (a `time.perf_counter()` value; None: no cap, and the clock is
    never read to decide anything), held inside long rounds (`RoundClock`). `box_seconds`:
    a caller's estimate of the seconds a box costs (e.g. from an earlier run on the same
    problem), which spares the timing probes of the first round under a cap."""

    max_boxes: int
    deadline: float | None = None
    box_seconds: float | None = None

    @classmethod
    def capped(cls, max_boxes: int, *, seconds: float | None = None,
               deadline: float | None = None, started: float | None = None,
               box_seconds: float | None = None) -> Budget:
        """The budget whose cap is the earlier of `deadline` and `seconds` counted from
        `started` (default now: a caller's set-up before the run then counts)."""
        start = time.perf_counter() if started is None else started
        return cls(max_boxes, cap_deadline(deadline, seconds, start), box_seconds)


@dataclass(frozen=True)
class Schedule:
    """How a run refines (module docstring): `batch` boxes taken per round, the root first
    split into about `first_round` equal boxes (default and at most `batch`), `lag` rounds in
    flight before the oldest is merged, boxes split past `max_depth` set aside as UNKNOWN."""

    batch: int = 1024
    first_round: int | None = None
    lag: int = PIPELINE_LAG
    max_depth: int = 80


@dataclass(frozen=True)
class Output:
    """What a run reports beside its bound: progress on `progress` under the name `task`,
    and up to `keep_leaves` leaves projected on the coordinates `project` for the report's
    figure (`Leaves`; None: none)."""

    progress: Progress | None = None
    task: str = "proof"
    keep_leaves: int = 5000
    project: tuple[int, int] | None = (0, 1)


class Leaves:
    """The leaves of a run projected onto two coordinates `project` (for the report's
    figure): lo, hi [k, 2], status (0 proved or closed, 1 violated, 2 unknown) and area;
    beyond 20 `keep` the smallest closed ones are pruned to 4 `keep` (unknown and violated
    leaves first), so memory stays bounded however long the run."""

    NAMES = {0: "proved", 1: "violated", 2: "unknown"}

    def __init__(self, project: tuple[int, int] | None, d: int, keep: int) -> None:
        self.px = list(project) if project is not None and d >= 2 else None
        self.keep = keep
        self.lo: list[torch.Tensor] = []
        self.hi: list[torch.Tensor] = []
        self.status: list[torch.Tensor] = []
        self.area: list[torch.Tensor] = []

    def record(self, lo: torch.Tensor, hi: torch.Tensor, status: int) -> None:
        if self.px is None or len(lo) == 0:
            return
        lo2, hi2 = lo[:, self.px], hi[:, self.px]
        self.lo.append(lo2)
        self.hi.append(hi2)
        self.status.append(torch.full((len(lo),), status, dtype=torch.int8, device=lo.device))
        self.area.append((hi2 - lo2).prod(-1))
        if sum(len(a) for a in self.area) > 20 * max(self.keep, 1):
            self.compact(self.keep * 4)

    def compact(self, cap: int) -> None:
        """Keep the `cap` leaves of largest priority: unknown and violated, then by area."""
        lo_all, hi_all = torch.cat(self.lo), torch.cat(self.hi)
        st_all, ar_all = torch.cat(self.status), torch.cat(self.area)
        pri = ar_all + (st_all > 0).double() * 1e300
        keep = torch.topk(pri, min(cap, len(pri))).indices
        self.lo[:] = [lo_all[keep]]
        self.hi[:] = [hi_all[keep]]
        self.status[:] = [st_all[keep]]
        self.area[:] = [ar_all[keep]]

    def result(self) -> dict[str, list]:
        """The kept leaves (at most `keep`) as lists: {"lo", "hi", "status"}."""
        if not self.lo:
            return {"lo": [], "hi": [], "status": []}
        self.compact(self.keep)
        return {"lo": self.lo[0].tolist(), "hi": self.hi[0].tolist(),
                "status": [self.NAMES[int(v)] for v in self.status[0]]}


class BranchAndBound:
    """One run of branch and bound (module docstring; the arguments are `branch_and_bound`'s).

    Its state, all named here and changed only by the methods below:
    `frontier` (the open boxes), `in_flight` (the rounds dispatched and not merged, oldest
    first, each with its parents' bounds), `best` and `best_point` (the largest centre value
    and where), `closed_vol` and `closed_max` (volume fraction and largest bound of the
    closed boxes), `stuck` and `stuck_max` (boxes set aside at the depth limit),
    `processed` (boxes evaluated), `max_depth_seen`, `violated`, `cut_short` (a dispatched
    box was not evaluated in time), `scanned_level` (the frontier holds no box that closes at
    this level), `give_up` (None once checked), `stages` (the bound's stage counts, summed
    over merged rounds), `history` and `leaves`.

    `run()` is the loop: merge what the schedule says (`_merge_due`), report, stop
    (`_stop`), else take a batch, split and dispatch it (`_next_round`); then merge what is
    in flight and form the outcome (`_outcome`)."""

    def __init__(self, root_lo: torch.Tensor, root_hi: torch.Tensor,
                 evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval], rule: ClosingRule,
                 budget: Budget, schedule: Schedule = Schedule(), output: Output = Output(),
                 *, executor: Any = None,
                 remote: tuple[Callable[..., BoxEval], Any] | None = None,
                 t0: float | None = None) -> None:
        self.t0 = time.perf_counter() if t0 is None else t0
        self.rule = rule
        self.evaluate = evaluate
        self.deadline = budget.deadline
        self.max_boxes, self.max_depth, self.lag = (budget.max_boxes, schedule.max_depth,
                                                    schedule.lag)
        self.progress = output.progress or NullProgress()
        self.task = output.task
        self.root_lo = root_lo.to(torch.float64)
        self.root_hi = root_hi.to(torch.float64)
        self.d = self.root_lo.shape[0]
        self.scale = (self.root_hi - self.root_lo).clamp_min(1e-300)
        self.root_vol = float(self.scale.prod())
        self.batch = schedule.batch
        first = (schedule.batch if schedule.first_round is None
                 else max(1, min(schedule.first_round, schedule.batch)))
        self.first_round = min(first, budget.max_boxes)  # `initial_grid` makes at most this

        self.frontier = Frontier(self.d, device=self.root_lo.device)
        #: the rounds against the cap; None without one (each round one call, no clock read)
        self.clock = (None if self.deadline is None
                      else RoundClock(evaluate, self.deadline, budget.box_seconds))
        self.rounds = RoundPipeline(self.clock or evaluate, executor, remote)
        self.in_flight: deque[tuple[Box, torch.Tensor]] = deque()
        self.best = -math.inf
        self.best_point: torch.Tensor | None = None
        self.closed_max = -math.inf
        self.closed_vol = 0.0
        self.processed = 0
        self.max_depth_seen = 0
        self.stuck = 0
        self.stuck_max = -math.inf
        self.violated = False
        self.cut_short = False
        self.scanned_level = -math.inf
        self.give_up = rule.give_up
        #: an executor's first round is waited for until at least this time (set when the
        #: run starts: SETUP_SECONDS_ANYWAY later, as RoundClock evaluates a cheap first
        #: round in this process whatever the time left); None once it was merged
        self.first_wait: float | None = None
        self.stages: dict[str, dict[str, int]] = {}
        self.history: list[list[float]] = [[0.0, 0.0]]
        self.last_report = self.t0
        self.leaves = Leaves(output.project, self.d, output.keep_leaves)

    # ---- the run
    def run(self, seeds: Box | None = None) -> BnBOutcome:
        self.progress.start(self.task, total=1.0)
        if seeds is not None and len(seeds) > 0:
            self._evaluate_seeds(seeds)
        if self.deadline is not None:
            self.first_wait = time.perf_counter() + SETUP_SECONDS_ANYWAY
        first = initial_grid(self.root_lo, self.root_hi, self.first_round)
        self._dispatch(first, torch.full((len(first),), math.nan, dtype=torch.float64,
                                         device=self.root_lo.device))  # the root: no bound
        stop = None
        try:
            while True:
                self._merge_due()
                now = time.perf_counter()
                if now - self.last_report > 0.25:
                    self._report(now)
                stop = self._stop(now)
                if stop is not None:
                    break
                self._next_round()
            while self.in_flight:  # stopped: merge what was dispatched (the bound covers it)
                self._merge()
        finally:
            self.rounds.cancel()
        return self._outcome(stop)

    def _evaluate_seeds(self, seeds: Box) -> None:
        """Falsification points first (degenerate boxes give exact centre values)."""
        ev = self.evaluate(seeds.lo, seeds.hi)
        self._update_best(ev, seeds)
        if self._violation():
            self.violated = True

    def _merge_due(self) -> None:
        """Merge the oldest round while `lag` rounds are in flight, while the frontier cannot
        fill a batch, and (to stop) after a violation: a function of the merged results
        only, so every executor runs the same schedule."""
        while self.in_flight and (len(self.in_flight) >= self.lag
                                  or len(self.frontier) < self.batch or self.violated):
            self._merge()

    def _report(self, now: float) -> None:
        """The progress of the run (the clock read here only times the reports)."""
        self.history.append([now - self.t0, self.closed_vol])
        self.progress.update(self.task, 0.0, proved=self.closed_vol, boxes=self.processed,
                             budget=self.max_boxes)
        self.last_report = now

    def _stop(self, now: float) -> str | None:
        """"done" (nothing open, or a violation), "cap" (the wall-clock cap passed, or a
        round it cut short), "budget" (no boxes left for a round, a round its evaluation
        left unfinished, or `give_up`), else None."""
        if len(self.frontier) == 0 or self.violated:
            return "done"
        if self.deadline is not None and (now > self.deadline or self.cut_short
                                          or self.clock.expired):
            return "cap"
        if self.cut_short or self.max_boxes - self.processed < 2:
            return "budget"
        if self.give_up is not None and self.processed >= self.give_up[0]:
            if max(self.closed_max, self.frontier.open_max(), self.stuck_max) > self.give_up[1]:
                return "budget"
            self.give_up = None  # checked once
        return None

    def _next_round(self) -> None:
        """The boxes to refine: the worst ones; in decision mode half of the batch is the
        boxes nearest to closing instead, so that a budgeted run closes regions early while
        the worst boxes (counterexamples) are still refined; fewer where the box budget
        has not room for a batch's children. Bisected and dispatched."""
        take = min(self.batch, (self.max_boxes - self.processed) // 2)  # 2 children each
        lo, hi, depth, wscore, ub = self.frontier.take(take, self.rule.decision,
                                                       with_upper=True)
        kids = split(Box(lo, hi, depth), split_dimensions(lo, hi, wscore, self.scale))
        self.max_depth_seen = max(self.max_depth_seen, int(kids.depth.max()))
        self._dispatch(kids, torch.cat([ub, ub]))  # split() puts the first halves first

    def _dispatch(self, box: Box, parent_upper: torch.Tensor) -> None:
        self.rounds.dispatch(box.lo, box.hi)
        self.in_flight.append((box, parent_upper))
        self.processed += len(box)

    def _merge(self) -> None:
        """The oldest round in flight: best point, violation, then its boxes closed, set
        aside (too deep) or added to the frontier, in order. A box its round did not
        evaluate in time keeps its parent's bound and is not counted as processed."""
        box, parent_upper = self.in_flight.popleft()
        wait = self.deadline
        if self.first_wait is not None:
            wait, self.first_wait = max(self.deadline, self.first_wait), None
        ev = self.rounds.collect(wait)
        if ev is None:  # an executor's round not back by the deadline (cancelled)
            ev = unevaluated(len(box), self.d, self.root_lo.device)
        add_counts(self.stages, ev.counts)
        if ev.done is not None and not bool(ev.done.all()):
            skipped = ~ev.done
            self.processed -= int(skipped.sum())
            self.cut_short = True
            ev = BoxEval(upper=torch.where(skipped, parent_upper, ev.upper),
                         centre_value=ev.centre_value, score=ev.score)
        self._update_best(ev, box)
        if self._violation():
            self.violated = True
        lvl = self.rule.level(self.best, self.processed)
        if lvl > self.scanned_level:  # the level rose (maximisation): open boxes may close
            shut = self.frontier.close(lvl)
            if shut is not None:
                self._close(*shut)
            self.scanned_level = lvl
        ub = ev.upper
        shut = (ub <= lvl) & (ub < math.inf)  # NaN compares False: stays open
        self._close(box.lo[shut], box.hi[shut], ub[shut])
        deep = ~shut & (box.depth >= self.max_depth)
        if bool(deep.any()):  # cannot be split further: set aside as UNKNOWN
            self.stuck += int(deep.sum())
            self.stuck_max = max(self.stuck_max,
                                 float(torch.nan_to_num(ub[deep], nan=math.inf).max()))
            self.leaves.record(box.lo[deep], box.hi[deep], 2)
        keep = ~shut & ~deep
        self.frontier.add(box.lo[keep], box.hi[keep], box.depth[keep], ub[keep],
                          ev.score[keep] if ev.score is not None else None)

    def _violation(self) -> bool:
        """A centre value above the threshold, in a run that stops on one."""
        return (self.rule.threshold is not None and self.best > self.rule.threshold
                and self.rule.stop_on_violation)

    def _update_best(self, ev: BoxEval, box: Box) -> None:
        cv = torch.nan_to_num(ev.centre_value, nan=-math.inf)
        if len(cv) == 0:
            return
        i = int(torch.argmax(cv))
        if float(cv[i]) > self.best:
            self.best = float(cv[i])
            self.best_point = box.centre[i].clone()

    def _close(self, lo: torch.Tensor, hi: torch.Tensor, ub: torch.Tensor) -> None:
        if len(lo):
            self.closed_vol += float((hi - lo).prod(-1).sum()) / self.root_vol
            self.closed_max = max(self.closed_max, float(ub.max()))
            self.leaves.record(lo, hi, 0)

    def _outcome(self, stop: str | None) -> BnBOutcome:
        budget_exhausted = stop in ("budget", "cap") and len(self.frontier) > 0
        elapsed = time.perf_counter() - self.t0
        self.history.append([elapsed, self.closed_vol])
        upper = max(self.closed_max, self.frontier.open_max(), self.stuck_max)
        complete = len(self.frontier) == 0 and self.stuck == 0 and not self.violated
        if len(self.frontier):
            self.leaves.record(*self.frontier.boxes(), 2)
        if self.violated and self.best_point is not None:
            self.leaves.record(self.best_point[None], self.best_point[None], 1)
        stats = ProofStats(
            boxes_processed=self.processed,
            boxes_per_second=self.processed / max(elapsed, 1e-9),
            seconds=elapsed,
            proved_volume_fraction=min(self.closed_vol, 1.0),
            max_depth=self.max_depth_seen,
            budget_exhausted=budget_exhausted,
            stopped_by_cap=budget_exhausted and stop == "cap",
            rounding=ROUNDING,
            volume_history=_thin(self.history, 200),
            stages=self.stages,
        )
        self.progress.finish(self.task, f"{self.processed} boxes, {self.closed_vol:.4f} of the "
                             "volume closed")
        return BnBOutcome(upper=upper, lower=self.best, best_point=self.best_point,
                          violated=self.violated, complete=complete, stats=stats,
                          leaves=self.leaves.result(), stuck=self.stuck)


def branch_and_bound(
    root_lo: torch.Tensor,
    root_hi: torch.Tensor,
    evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
    rule: ClosingRule,
    budget: Budget,
    schedule: Schedule = Schedule(),
    output: Output = Output(),
    *,
    seeds: Box | None = None,
    executor: Any = None,
    remote: tuple[Callable[..., BoxEval], Any] | None = None,
) -> BnBOutcome:
    """Sound upper bound of max f over [root_lo, root_hi] [d], refining the worst boxes first
    (one `BranchAndBound` run).

    `rule` (`ClosingRule`): decision mode (`threshold` given): boxes with upper <= threshold
    close as proved; a centre value > threshold is a violation (stops when
    `stop_on_violation`). Maximisation mode: boxes with upper <= best + max(tol, rel_tol
    |best|) close; the result `upper` is the max over closed and open boxes. `coarse_after =
    (N, coarse)`: once N boxes have been evaluated the closing tolerance relaxes to `coarse`
    (a fine precision where it is cheap, never more than N boxes spent on it beyond the
    coarse one; boxes closed before stay closed, their bounds are below either level).
    `give_up = (N, level)` (maximisation): once N boxes have been evaluated, the run stops as
    if its budget were spent when the largest bound of the merged boxes, open or closed, is
    still above `level` (the caller has a better way past that level); the check only chooses
    when to stop, the bound is then formed as for any budgeted run.
    `budget` (`Budget`): the boxes (honoured exactly) and the optional wall-clock cap, held
    inside long rounds (module docstring, `RoundClock`). `schedule` (`Schedule`): the batch,
    the first round, the lag and the depth limit. `output` (`Output`): progress and the
    leaves kept for the report. `seeds`: points evaluated first (degenerate boxes: their
    centre values set the best value; not counted as processed). `executor` / `remote`:
    where each round's children are evaluated (module docstring). The outcome depends on
    the rule, the budget and the schedule, not on the executor. The evaluations' stage counts
    (`BoxEval.counts`) are summed over the merged rounds into `stats.stages`.
    """
    t0 = time.perf_counter()
    if remote is not None and executor is not None:
        from certify.search.distributed.executor import round_batch

        # rounds sized to the workers
        schedule = dataclasses.replace(schedule, batch=round_batch(executor, schedule.batch))
    run = BranchAndBound(root_lo, root_hi, evaluate, rule, budget, schedule, output,
                         executor=executor, remote=remote, t0=t0)
    return run.run(seeds)


def _thin(history: list[list[float]], cap: int) -> list[list[float]]:
    if len(history) <= cap:
        return history
    step = len(history) / cap
    out = [history[int(i * step)] for i in range(cap)]
    out[-1] = history[-1]
    return out
