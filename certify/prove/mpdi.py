"""The sound prover: the MPDI decision and the proved rate (side proofs: `certify.prove.side`).

Every function here runs `certify.search.bnb.branch_and_bound` with bounds from
`certify.enclose` (interval + second-order Taylor forms, outward rounding as in
`certify.arith.intervals.ROUNDING`). Only a bound that covers every box of the domain is called
proved; NaN/Inf anywhere leaves the box UNKNOWN; a violation is a concrete float64 point.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.arith.boxes import Box, initial_grid
from certify.arith.intervals import ROUNDING, up
from certify.budget import OutOfTime, cap_deadline, passed
from certify.enclose.mpdi import (
    choose_preconditioner,
    estimate_crown_gain,
    mpdi_box_bounds,
    plain_screen_pays,
)
from certify.enclose.options import BoxBoundOptions, Technique, box_bound_options
from certify.enclose.preconditioner import (
    Preconditioner,
    make_preconditioner,
    to_lam_max_D,
    with_shift,
)
from certify.enclose.stages import LINEAR_BOUNDS, MIXED_ROWS
from certify.model.kernels import pointwise_rate, problem_lam_max
from certify.model.problem import Problem
from certify.progress import NullProgress, Progress
from certify.results import Counterexample, ProofStats, Status
from certify.search.bnb import (
    SETUP_SECONDS_ANYWAY,
    Budget,
    ClosingRule,
    Output,
    Schedule,
    branch_and_bound,
)
from certify.search.evaluation import BoxEval
from certify.search.tree_estimate import completion_text, estimate_tree, forecast_text
from certify.search.witness import is_witness, mpdi_lower
from certify.settings import DEFAULTS

__all__ = ["ProofOutcome", "RateOutcome", "prove_mpdi", "prove_rate", "ROUNDING"]

#: the MPDI proof's first round is batch / COARSE_START boxes where the plain interval bound
#: closes boxes on the problem (`prove_mpdi`)
COARSE_START = 4


@dataclass
class ProofOutcome:
    """Decision on max lam_max(D) <= 0 over X x Y."""

    status: Status
    upper: float  # proved upper bound on max lam_max(D) (<= 0 when PROVED; inf if none)
    lower: float  # best value found at evaluated points
    counterexample: Counterexample | None
    stats: ProofStats
    boxes: dict[str, list] = field(default_factory=dict)
    message: str = ""


@dataclass
class RateOutcome:
    """lam_cert in [lower, upper_sampled]: lower proved, upper from evaluated points."""

    lower: float | None
    upper_sampled: float
    stats: ProofStats
    worst: Counterexample | None


def root_box(problem: Problem) -> tuple[torch.Tensor, torch.Tensor]:
    """The root box X x Y as (lo, hi) [d] float64 on the problem's device."""
    s = problem.system
    box = np.concatenate([s.X, s.Y], 0)
    t = torch.as_tensor(box, dtype=torch.float64, device=problem.device)
    return t[:, 0].clone(), t[:, 1].clone()


def seed_box(seeds: object | None, d: int, device: str = "cpu") -> Box | None:
    if seeds is None:
        return None
    if isinstance(seeds, torch.Tensor):
        seeds = seeds.detach().cpu()
    pts = torch.as_tensor(np.asarray(seeds, dtype=np.float64), dtype=torch.float64,
                          device=device)
    if pts.ndim != 2 or pts.shape[1] != d or pts.shape[0] == 0:
        return None
    return Box(pts, pts.clone(), torch.zeros(pts.shape[0], dtype=torch.long, device=device))


def mpdi_options(problem: Problem, lam: float, pc: Preconditioner,
                 technique: Technique = Technique.TAYLOR, crown: bool = True,
                 plain_screen: bool | None = None, deadline: float | None = None
                 ) -> BoxBoundOptions:
    """The box bound of the MPDI decision at rate `lam`, made once per proof: a decision at
    the level 0 (`screen=0.0, decide=True`) under the congruence `pc`, with the choices only
    a probe of the problem can make. Where the mixed rows apply, whether the plain interval
    stage screens the boxes first (`plain_screen_pays`, or `plain_screen` when the caller
    has the answer); where the linear bounds follow the Taylor models, the remainder
    reduction that chooses their boxes (`estimate_crown_gain`). Deterministic in the
    problem, so every worker of a distributed proof builds the same. `deadline`: a proof's
    wall-clock cap (None: none), `certify.budget.OutOfTime` past it while the probes run."""
    rlo, rhi = root_box(problem)
    options = box_bound_options(problem, lam, pc=pc, technique=technique, crown=crown,
                                screen=0.0, decide=True, root_width=rhi - rlo)
    if MIXED_ROWS.applies(options):
        pays = plain_screen_pays(problem, lam, pc) if plain_screen is None else plain_screen
        return dataclasses.replace(options, plain_screen=pays)
    if LINEAR_BOUNDS.applies(options):
        gain = estimate_crown_gain(problem.network, rlo, rhi, deadline=deadline)
        return dataclasses.replace(options, crown_gain=gain)
    return options


def _mpdi_evaluator(problem: Problem, options: BoxBoundOptions):
    """The MPDI box evaluation under `options` (`mpdi_options`): the bound converted to one
    of lam_max(D) (NaN where not finite), the float value at each box's centre, the split
    score and the stage counts."""
    n = problem.n
    P = problem.P_t
    pc = options.pc
    lam = options.lam

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        bb = mpdi_box_bounds(options, lo, hi)
        ub = to_lam_max_D(bb.upper, P, pc)
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        c = 0.5 * (lo + hi)
        val = problem_lam_max(problem, lam, c[:, :n], c[:, n:])
        return BoxEval(upper=ub, centre_value=val, score=bb.score, counts=bb.counts)

    return evaluate


def _mpdi_preconditioner(problem: Problem, lam: float, technique: Technique,
                         deadline: float | None = None) -> Preconditioner:
    """The congruence for the MPDI proof: probed (`choose_preconditioner`) for the default
    prover, M ~ L^-1 for the plain-interval and mean-value comparison provers."""
    if technique is Technique.TAYLOR:
        return choose_preconditioner(problem, lam, deadline=deadline)
    return with_shift(make_preconditioner(problem.P_t), problem.shift_t)


def mpdi_box_chunk(payload: dict, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """Executor task (module level, picklable): the MPDI box evaluation of one chunk; the
    evaluator is rebuilt from plain data once per worker process
    (`certify.search.distributed.payload`)."""
    from certify.search.distributed.executor import worker_cache
    from certify.search.distributed.payload import PROBLEM_KEYS, problem_from_payload
    from certify.search.threads import torch_threads

    def build():
        base = {k: payload[k] for k in PROBLEM_KEYS}
        problem = problem_from_payload(base)
        lam, technique = payload["prove_lam"], Technique(payload["technique"])
        pc = _mpdi_preconditioner(problem, lam, technique)
        return _mpdi_evaluator(problem, mpdi_options(problem, lam, pc, technique,
                                                     payload["crown"]))

    evaluate = worker_cache("mpdi-boxes:" + payload["key"], build)
    with torch_threads(1):
        return evaluate(lo, hi)


def _mpdi_remote(problem: Problem, lam: float, technique: Technique, crown: bool,
                 executor: object) -> tuple | None:
    """(chunk_fn, payload) for an executor whose work runs in other processes (a Dask cluster,
    even of one worker), else None (evaluate in process). A problem on a GPU is bounded in
    process, on that GPU (the workers would rebuild it on their CPUs)."""
    if not (getattr(executor, "remote", False) or getattr(executor, "workers", 1) > 1):
        return None
    if torch.device(problem.device).type != "cpu":
        return None
    from certify.search.distributed.executor import payload_key
    from certify.search.distributed.payload import problem_payload

    payload = problem_payload(problem)
    payload.update(prove_lam=float(lam), technique=technique.value, crown=bool(crown))
    payload["key"] = payload_key(payload)
    return mpdi_box_chunk, payload


@dataclass
class DecisionSetup:
    """What the MPDI decision proof runs on (`mpdi_decision`): the box evaluation, the root
    box [d] and the number of boxes of the first round. The proof's tree (which boxes are
    split, which closed) is a function of these and the split rule alone."""

    evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval]
    lo: torch.Tensor
    hi: torch.Tensor
    first_round: int


def mpdi_decision(problem: Problem, lam: float, technique: Technique = Technique.TAYLOR,
                  crown: bool = True, batch: int = 1024, deadline: float | None = None
                  ) -> DecisionSetup:
    """The `DecisionSetup` of `prove_mpdi` at rate `lam` (also used by bench/tree_size.py,
    which follows the same tree). The probes that choose the bounds are bounded work;
    `deadline` (a `time.perf_counter()` value; None: no cap, the clock is not read): they
    read the clock between their pieces and raise `certify.budget.OutOfTime` once it has
    passed (they choose only, so the setup does not depend on it otherwise)."""
    pc = _mpdi_preconditioner(problem, lam, technique, deadline)
    lo, hi = root_box(problem)
    # where the plain bound probe closes part of the root split into 1024 boxes, coarser
    # boxes close too: a coarse first round saves refining them; where it closes nothing,
    # every region needs that depth and the full first round saves the coarse levels
    # (`bench/tree_size.py` compares the two on the Van der Pol families)
    coarse = (crown and technique is Technique.TAYLOR
              and plain_screen_pays(problem, lam, pc, deadline=deadline))
    options = mpdi_options(problem, lam, pc, technique, crown, plain_screen=coarse,
                           deadline=deadline)
    return DecisionSetup(_mpdi_evaluator(problem, options), lo, hi,
                         batch // COARSE_START if coarse else batch)


def prove_mpdi(problem: Problem, *, lam: float | None = None,
               max_boxes: int = DEFAULTS.max_boxes, seconds: float | None = None,
               deadline: float | None = None, progress: Progress | None = None,
               seeds: object | None = None, batch: int = 1024, taylor: bool | str = True,
               keep_leaves: int = 5000, crown: bool = True,
               executor: object | None = None, task: str = "mpdi proof",
               estimate_points: int = 256, box_seconds: float | None = None,
               forecast: Callable[[str], None] | None = None) -> ProofOutcome:
    """Decide D(xhat, y) <= 0 over X x Y for rate `lam` (default problem.lam) and P.

    PROVED: every sub-box has a sound bound lam_max(D) <= 0. VIOLATED: a point (a box
    centre or one of `seeds` [m, n+p]) with float64 lam_max(D) > 0. UNKNOWN: the box budget
    `max_boxes` spent, the wall-clock cap stopped it, or NaN/Inf in some bound; `upper` is
    then the best bound. `taylor=False` uses plain interval arithmetic only (for
    comparison); `crown=False` keeps the forward Taylor models without backward linear bound
    propagation. `executor`: where the rounds' boxes are evaluated (default
    `current_executor()`; the verdict and bounds do not depend on it). `task`: the name the
    progress display shows.
    The budget is work: `max_boxes` boxes, honoured exactly, so the outcome is the same on
    any machine. The optional wall-clock cap (None: none, the clock is never read): `seconds`
    from this call and/or a `deadline` (a `time.perf_counter()` value), the earlier binding;
    it counts the set-up of the bounds too and holds within a few seconds however slow a box
    is (`certify.search.bnb.RoundClock`: boxes a round had no time for stay open with their
    parent's bound, and the proof is then UNKNOWN, `stats.stopped_by_cap`); the set-up
    itself stops at SETUP_SECONDS_ANYWAY past the call at the earliest and a cheap first
    round is always evaluated, so that a small cap on a cheap problem still gives a bound;
    `box_seconds`: an estimate of a box's cost, e.g. from an earlier proof on the problem
    (spares the timing probes of the first round under a cap).
    A proof that spent its box budget estimates, by random descents (batches of
    `estimate_points` while the standard error is above 20%, within 16 batches and 5% of the
    boxes the proof evaluated: bounded work), how many boxes a complete one needs
    (`certify.search.tree_estimate`; in `stats` and the message); under a cap, within what
    is left of it.
    `forecast`: where given, before the first round FORECAST_POINTS random descents estimate
    the complete tree and `certify.search.tree_estimate.forecast_text` (estimate against
    `max_boxes`) is passed to it (bounded work outside the box budget; under a cap, within
    a twentieth of what is left; nothing of the verdict rests on it).
    """
    from certify.search.distributed.executor import current_executor

    started = time.perf_counter()
    deadline = cap_deadline(deadline, seconds, started)
    progress = progress or NullProgress()
    lam = float(problem.lam if lam is None else lam)
    technique = Technique.of(taylor)
    try:
        setup = mpdi_decision(problem, lam, technique, crown, batch,
                              deadline=None if deadline is None
                              else max(deadline, started + SETUP_SECONDS_ANYWAY))
    except OutOfTime:
        return _spent_in_setup(max_boxes, time.perf_counter() - started)
    lo, hi = setup.lo, setup.hi
    n = problem.n
    if forecast is not None:
        _forecast(setup, max_boxes, deadline, forecast)
    executor = current_executor() if executor is None else executor
    out = branch_and_bound(
        lo, hi, setup.evaluate, ClosingRule(threshold=0.0),
        Budget(max_boxes, deadline, box_seconds),
        Schedule(batch=batch, first_round=setup.first_round),
        Output(progress=progress, task=task, keep_leaves=keep_leaves),
        seeds=seed_box(seeds, lo.shape[0], problem.device), executor=executor,
        remote=_mpdi_remote(problem, lam, technique, crown, executor))
    cex = None
    if out.best_point is not None:
        pt = out.best_point[None]
        v = float(problem_lam_max(problem, lam, pt[:, :n], pt[:, n:])[0])
        cex = Counterexample(xhat=pt[0, :n].tolist(), y=pt[0, n:].tolist(), value=v,
                             sound_bound=float(mpdi_lower(problem, pt, lam)[0]))
    st = out.stats
    if out.violated and cex is not None and is_witness(cex.sound_bound):
        status = Status.VIOLATED
        msg = f"lam_max(D) = {cex.value:.6g} > 0 at xhat={cex.xhat}, y={cex.y}"
    elif out.complete and out.upper <= 0 and math.isfinite(out.upper):
        status = Status.PROVED
        msg = f"proved max lam_max(D) <= {out.upper:.6g} over {st.boxes_processed} boxes"
        cex = None if cex is None or cex.value <= 0 else cex
    else:
        status = Status.UNKNOWN
        why = (f"{out.stuck} boxes gave NaN/Inf or hit the depth limit" if out.stuck
               else "stopped by the wall-clock cap" if st.stopped_by_cap
               else f"box budget spent (max_boxes={max_boxes})")
        msg = (f"{why}; best upper bound {out.upper:.6g}, proved volume "
               f"{st.proved_volume_fraction:.4f}")
        if st.budget_exhausted and not out.stuck and estimate_points > 0 \
                and not passed(deadline):
            # more descents while the estimate is rough, within 5% of the proof's boxes
            first_depth = int(initial_grid(lo, hi, setup.first_round).depth[0])
            est = estimate_tree(setup.evaluate, lo, hi, setup.first_round, estimate_points,
                                target_rel_stderr=0.2, max_points=16 * estimate_points,
                                max_evaluations=max(4096, st.boxes_processed // 20),
                                seconds=None if deadline is None
                                else deadline - time.perf_counter(),
                                box_seconds=st.seconds / max(st.boxes_processed, 1),
                                levels=max(1, st.max_depth - first_depth + 1))
            if math.isfinite(est.boxes):
                st.estimated_boxes, st.estimate_rel_stderr = est.boxes, est.rel_stderr
            tail = completion_text(est.boxes, est.rel_stderr, st.boxes_processed)
            msg += "; " + tail if tail else ""
    upper = out.upper if math.isfinite(out.upper) else float("inf")
    return ProofOutcome(status=status, upper=upper, lower=out.lower, counterexample=cex,
                        stats=st, boxes=out.leaves, message=msg)


#: descents of the estimate before a proof (`prove_mpdi(forecast=...)`)
FORECAST_POINTS = 64


def _forecast(setup: DecisionSetup, max_boxes: int, deadline: float | None,
              say: Callable[[str], None]) -> None:
    """The up-front tree estimate of `prove_mpdi(forecast=...)`: one seeded batch of
    FORECAST_POINTS descents (a twentieth of the cap's time left, if any), its line to `say`
    ("" is not said)."""
    seconds = None if deadline is None else max(0.0, (deadline - time.perf_counter()) / 20)
    est = estimate_tree(setup.evaluate, setup.lo, setup.hi, setup.first_round,
                        FORECAST_POINTS, seconds=seconds)
    text = forecast_text(est.boxes, est.rel_stderr, max_boxes)
    if text:
        say(text)


def _spent_in_setup(max_boxes: int, elapsed: float) -> ProofOutcome:
    """The UNKNOWN outcome of a decision the wall-clock cap stopped before its first round."""
    stats = ProofStats(boxes_processed=0, seconds=elapsed, budget_exhausted=True,
                       stopped_by_cap=True, rounding=ROUNDING,
                       volume_history=[[0.0, 0.0], [elapsed, 0.0]])
    return ProofOutcome(status=Status.UNKNOWN, upper=float("inf"), lower=-math.inf,
                        counterexample=None, stats=stats,
                        message=("stopped by the wall-clock cap while the bounds were being "
                                 f"set up, before the first box (max_boxes={max_boxes})"))


def prove_rate(problem: Problem, *, max_boxes: int = DEFAULTS.rate_boxes,
               seconds: float | None = None, deadline: float | None = None,
               progress: Progress | None = None, tol: float = 1e-9, rel_tol: float = 1e-3,
               batch: int = 1024, seeds: object | None = None,
               coarse_after: tuple[int, float] | None = None,
               give_up: tuple[int, float] | None = None) -> RateOutcome:
    """Proved lower bound on lam_cert = -max lam_max(He{P J_cl}, P) / 2 over X x Y.

    Direct branch and bound on phi(z) = lam_max(He{P J_cl(z)}, P) (no bisection): boxes are
    refined worst-first until the gap between the proved max and the best point is within
    max(tol, rel_tol |phi|) or the budget ends; lower = -(proved max of phi) / 2.
    The generalised eigenvalue uses the congruence with M ~ L^-1: with A0 = M He{PJ} M^T
    and C = M P M^T in [c_min, c_max] (bounded), lam_max(A0, C) <= mu / c_min (mu >= 0) or
    mu / c_max (mu < 0), mu >= lam_max(A0).
    `seeds` [S, n + p]: points evaluated first (the rate grid's worst points): their values
    set the closing level from the start, so boxes far below the max close in the first
    rounds instead of being refined until the search finds a point as bad. They only choose
    what is refined; the bound is the max over every box's sound bound either way.
    `coarse_after`: see `branch_and_bound` (the tolerance relaxes after that many boxes).
    `give_up = (N, rate)`: after N boxes, stop (budget spent) unless the bound so far
    already proves more than `rate` (`branch_and_bound`'s give_up at phi = -2 rate).
    Budget: `max_boxes` boxes; optional wall-clock cap `seconds` from this call and/or
    `deadline` (as in `prove_mpdi`; `stats.stopped_by_cap` when it stopped the proof).
    """
    started = time.perf_counter()
    deadline = cap_deadline(deadline, seconds, started)
    if problem.shift is not None or problem.noise is not None:
        raise ValueError("the proved rate is defined for D without a constant term or noise "
                         "input")
    progress = progress or NullProgress()
    pc = make_preconditioner(problem.P_t)
    lo, hi = root_box(problem)
    n = problem.n
    P = problem.P_t

    level = Level(rel_tol, tol)
    try:
        gain = estimate_crown_gain(problem.network, lo, hi,
                                   deadline=None if deadline is None
                                   else max(deadline, started + SETUP_SECONDS_ANYWAY))
    except OutOfTime:  # the cap left no time for a single box: no bound
        return RateOutcome(lower=None, upper_sampled=math.inf,
                           stats=ProofStats(seconds=time.perf_counter() - started,
                                            budget_exhausted=True, stopped_by_cap=True,
                                            rounding=ROUNDING),
                           worst=None)

    options = box_bound_options(problem, 0.0, pc=pc, crown_gain=gain, root_width=hi - lo)

    def evaluate(blo: torch.Tensor, bhi: torch.Tensor) -> BoxEval:
        c = 0.5 * (blo + bhi)
        val = -2.0 * pointwise_rate(problem.system, problem.network, P, c[:, :n], c[:, n:])
        cv = torch.nan_to_num(val, nan=-math.inf)
        level.best = max(level.best, float(cv.max())) if len(cv) else level.best
        lv = level.value()  # phi-level -> mu-level (mu / c_min or mu / c_max <= lv)
        screen = None if not math.isfinite(lv) else (lv * pc.c_min if lv >= 0
                                                      else lv * pc.c_max)
        bb = mpdi_box_bounds(dataclasses.replace(options, screen=screen), blo, bhi)
        mu = bb.upper
        ub = torch.where(mu >= 0, up(mu / pc.c_min), up(mu / pc.c_max))
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=val, score=bb.score, counts=bb.counts)

    rule = ClosingRule(tol=tol, rel_tol=rel_tol, coarse_after=coarse_after,
                       give_up=None if give_up is None else (give_up[0], -2.0 * give_up[1]))
    out = branch_and_bound(lo, hi, evaluate, rule, Budget(max_boxes, deadline),
                           Schedule(batch=batch), Output(progress=progress, task="rate proof"),
                           seeds=seed_box(seeds, lo.shape[0], problem.device))
    lower = -out.upper / 2.0 if math.isfinite(out.upper) else None
    worst = None
    upper_sampled = -out.lower / 2.0 if math.isfinite(out.lower) else float("inf")
    if out.best_point is not None:
        pt = out.best_point
        worst = Counterexample(xhat=pt[:n].tolist(), y=pt[n:].tolist(), value=upper_sampled)
    if lower is not None:
        lower = math.nextafter(lower, -math.inf)
    return RateOutcome(lower=lower, upper_sampled=upper_sampled, stats=out.stats, worst=worst)


class Level:
    """The closing level of a maximisation branch and bound, tracked from the centre values
    the evaluator sees (the same points `branch_and_bound` ranks): boxes whose cheap bound is
    already at or below it skip the expensive bound. Only the choice of bound depends on it,
    never soundness."""

    def __init__(self, rel_tol: float, tol: float) -> None:
        self.best = -math.inf
        self.rel_tol, self.tol = rel_tol, tol

    def value(self) -> float:
        if not math.isfinite(self.best):
            return math.inf
        return self.best + max(self.tol, self.rel_tol * abs(self.best))

    def tighten(self, cheap: torch.Tensor, centre: torch.Tensor, tight) -> torch.Tensor:
        """min(cheap, tight(mask)) on the boxes whose cheap bound is above the level."""
        cv = torch.nan_to_num(centre, nan=-math.inf)
        if len(cv):
            self.best = max(self.best, float(cv.max()))
        work = ~(cheap <= self.value())
        if not bool(work.any()):
            return cheap
        out = cheap.clone()
        t = tight(work)
        out[work] = torch.where(torch.isnan(t) | torch.isnan(cheap[work]), cheap[work],
                                torch.minimum(cheap[work], t))
        return out
