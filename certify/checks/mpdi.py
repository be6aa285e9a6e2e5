"""MPDI check: is D(xhat, y) <= 0 on all of X x Y? (METHOD §3.1)

Lower side: dense grid + adversarial search for the largest lam_max(D) in float64. A point
is a counterexample only when a SOUND lower bound of lam_max(D) there is > 0
(`certify.search.witness`); a float64 value > 0 without one is a near-tie (within rounding of 0).
Upper side: the branch-and-bound prover of `certify.prove.mpdi`, run when no counterexample was
found. PROVED comes only from the prover; a near-tie it cannot settle is UNKNOWN, saying so.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
import torch

from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context, setting_quantity
from certify.figuredata import ProofBoxes
from certify.model.kernels import mpdi_lam_max
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress, note
from certify.results import Counterexample, MpdiResult, Status
from certify.search.falsify import SearchOutcome, maximize_over_box
from certify.search.grid import GridKernel, float32_screen
from certify.search.witness import is_witness, mpdi_lower
from certify.settings import VerifySettings


def joint_box(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners of X x Y as [n + p] arrays."""
    box = np.vstack([problem.system.X, problem.system.Y])
    return box[:, 0].copy(), box[:, 1].copy()


def mpdi_score(problem: Problem, lam: float | None = None):
    """z = (xhat, y) [B, n+p] -> lam_max(D) [B] (float64, differentiable)."""
    n = problem.n
    P = problem.P_t
    lam = problem.lam if lam is None else lam

    def score(z: torch.Tensor) -> torch.Tensor:
        return mpdi_lam_max(problem.system, problem.network, P, lam, z[:, :n], z[:, n:],
                            problem.shift_t)

    return score


def counterexamples_from(search: SearchOutcome, n: int, above: float | None = None
                         ) -> list[Counterexample]:
    """Top distinct points of a search as Counterexamples (only those > `above`, if given)."""
    out = []
    for point, value in zip(search.top_points, search.top_values):
        if above is not None and not value > above:
            continue
        out.append(Counterexample(xhat=point[:n].tolist(), y=point[n:].tolist(),
                                  value=float(value)))
    return out


def sound_counterexamples(problem: Problem, candidates: list[Counterexample],
                          lam: float | None = None) -> list[Counterexample]:
    """The candidates whose SOUND lower bound of lam_max(D) is > 0 (`certify.search.witness`), with
    that bound recorded; the others are near-ties (float error could make them look > 0)."""
    if not candidates:
        return []
    z = torch.tensor([[*c.xhat, *c.y] for c in candidates], dtype=torch.float64,
                     device=problem.device)
    bounds = mpdi_lower(problem, z, lam).tolist()
    for c, b in zip(candidates, bounds):
        c.sound_bound = float(b)
    return [c for c in candidates if is_witness(c.sound_bound)]


def falsify_mpdi(problem: Problem, settings: VerifySettings, *, lam: float | None = None,
                 progress: Progress | None = None, executor: Any = None) -> SearchOutcome:
    """Grid + adversarial search for the largest lam_max(D) (float64 values throughout), on
    the problem's device and `executor` (default `current_executor()`).

    The grid is swept with a float32 copy of the kernel as a screen; every point that could be
    above 0 and every top candidate is re-evaluated in float64 (see `maximize_over_box`).
    Where a number of the problem does not fit float32 (`certify.search.grid.float32_misfit`),
    there is no screen: the sweep runs in float64 alone.
    """
    from certify.search.distributed.executor import current_executor

    device = torch.device(problem.device)
    lo, hi = joint_box(problem)
    exact = GridKernel(problem, lam)
    screen = float32_screen(problem, lam) if settings.float32_screen else None
    executor = current_executor() if executor is None else executor
    remote = None
    if executor.remote or executor.workers > 1:  # the sweep on the run's Dask workers
        from certify.search.distributed.payload import mpdi_grid_chunk, mpdi_payload

        remote = (executor, mpdi_grid_chunk, mpdi_payload(
            problem, exact.lam, screen is not None, str(device)))
    return maximize_over_box(exact, lo, hi, grid_points=settings.grid_points,
                             starts=settings.adversarial_starts, steps=settings.adversarial_steps,
                             top_k=settings.top_counterexamples, seed=settings.seed,
                             screen=screen, progress=progress, task="MPDI grid", remote=remote,
                             device=device)


def _search_fields(search: SearchOutcome, n: int) -> dict[str, Any]:
    """The falsification side of an `MpdiResult`, from a search."""
    worst = counterexamples_from(search, n)[:1]
    return dict(lower=search.best_value, worst=worst[0] if worst else None,
                violating_fraction=search.above_fraction, grid_points=search.grid_points,
                adversarial_starts=search.starts)


def _violated(search: SearchOutcome, cex: list[Counterexample], n: int, t0: float,
              coarse: bool = False) -> MpdiResult:
    """VIOLATED by the sound counterexamples `cex` a search found."""
    common = {**_search_fields(search, n), "worst": cex[0]}
    which = "the coarse first search's " if coarse else ""
    return MpdiResult(
        status=Status.VIOLATED, upper=None, counterexamples=cex,
        seconds=time.perf_counter() - t0,
        message=(f"D is not negative semidefinite: lam_max(D) = {search.best_value:.4g} > 0 "
                 f"at xhat={_fmt(cex[0].xhat)}, y={_fmt(cex[0].y)} (sound lower bound "
                 f"{lower_text(cex[0].sound_bound)}); "
                 f"{100 * search.above_fraction:.3g}% of {which}{search.grid_points:,} grid "
                 "points violate it"), **common)


#: the coarse first search of `check_mpdi(coarse_first=True)`: at most this many grid points,
#: ascent starts and steps per ascent (a few percent of the default search's work)
COARSE_POINTS = 16_384
COARSE_STARTS = 8
COARSE_STEPS = 40


def check_mpdi(problem: Problem, settings: VerifySettings, *,
               progress: Progress | None = None,
               figures: dict[str, Any] | None = None, executor: Any = None,
               deadline: float | None = None, coarse_first: bool = False) -> MpdiResult:
    """Decide D <= 0 over X x Y at the problem's lam and P, on the problem's device (the
    grid, the ascent, the sound re-check of candidates and the proof) and `executor`
    (default `current_executor()`). The proof's budget is `settings.max_boxes`; `deadline`:
    the run's wall-clock cap (None: none). `coarse_first`: for a caller that wants the
    verdict more than the numbers, a coarse search (COARSE_POINTS, _STARTS, _STEPS) first: a
    sound counterexample there is the result (VIOLATED, saying which search found it);
    else the full search follows as without it."""
    from certify.arith.device import proof_batch
    from certify.prove.mpdi import prove_mpdi
    from certify.search.tree_estimate import completion_text

    progress = progress or NullProgress()
    t0 = time.perf_counter()
    n = problem.n
    if coarse_first and settings.grid_points > COARSE_POINTS:
        coarse = dataclasses.replace(
            settings, grid_points=COARSE_POINTS,
            adversarial_starts=min(COARSE_STARTS, settings.adversarial_starts),
            adversarial_steps=min(COARSE_STEPS, settings.adversarial_steps))
        search = falsify_mpdi(problem, coarse, progress=progress, executor=executor)
        if not search.nonfinite:
            cex = sound_counterexamples(problem, counterexamples_from(search, n, above=0.0))
            if cex:
                return _violated(search, cex, n, t0, coarse=True)
    search = falsify_mpdi(problem, settings, progress=progress, executor=executor)
    common = _search_fields(search, n)
    if search.nonfinite:
        return MpdiResult(status=Status.UNKNOWN, upper=None, seconds=time.perf_counter() - t0,
                          message=f"lam_max(D) is NaN/Inf at {search.nonfinite} grid points: "
                                  "nothing can be proved", **common)
    cex = sound_counterexamples(problem, counterexamples_from(search, n, above=0.0))
    near_tie = search.best_value > 0 and not cex
    if cex:
        return _violated(search, cex, n, t0)
    seeds = torch.as_tensor(search.top_points, dtype=torch.float64, device="cpu")
    # the proof's boxes live and are bounded on the problem's device, in rounds of its size
    outcome = prove_mpdi(problem, max_boxes=settings.max_boxes, deadline=deadline,
                         progress=progress, seeds=seeds, executor=executor,
                         batch=proof_batch(problem.device),
                         forecast=lambda text: note(progress, "MPDI " + text))
    if figures is not None and getattr(outcome, "boxes", None):
        figures["proof_boxes"] = outcome.boxes
        figures["proof_history"] = outcome.stats.volume_history
    lower = max(search.best_value, outcome.lower if outcome.lower is not None else -np.inf)
    common["lower"] = lower
    if outcome.status == Status.VIOLATED and outcome.counterexample is not None:
        cex = outcome.counterexample
        common["worst"] = cex
        common["lower"] = max(lower, cex.value)
        return MpdiResult(status=Status.VIOLATED, upper=outcome.upper, counterexamples=[cex],
                          proof=outcome.stats, seconds=time.perf_counter() - t0,
                          message=(f"prover found lam_max(D) = {cex.value:.4g} > 0 at "
                                   f"xhat={_fmt(cex.xhat)}, y={_fmt(cex.y)} (sound lower "
                                   f"bound {lower_text(cex.sound_bound)})"), **common)
    if outcome.status == Status.PROVED and outcome.upper is not None and outcome.upper <= 0:
        return MpdiResult(status=Status.PROVED, upper=outcome.upper, proof=outcome.stats,
                          seconds=time.perf_counter() - t0,
                          message=(f"proved D <= 0 on all of X x Y: max lam_max(D) in "
                                   f"[{common['lower']:.4g}, {upper_text(outcome.upper, 4)}]"),
                          **common)
    best = "none" if outcome.upper is None else upper_text(outcome.upper, 4)
    if near_tie or common["lower"] > 0:
        return MpdiResult(
            status=Status.UNKNOWN, upper=outcome.upper, proof=outcome.stats,
            seconds=time.perf_counter() - t0,
            message=(f"near-tie: lam_max(D) evaluates to {common['lower']:.4g} > 0 in float64, "
                     "but no point has a sound lower bound > 0 (the value is within rounding "
                     f"error of 0); best proved upper bound {best}: neither proved nor "
                     "violated"), **common)
    st = outcome.stats
    found = (f"no counterexample (largest lam_max(D) found {common['lower']:.4g}), best "
             f"proved upper bound {best}")
    if st.stopped_by_cap:  # the registry names the cap in the message
        why = f"proof stopped after {st.boxes_processed:,} boxes; {found}"
    else:
        ahead = completion_text(st.estimated_boxes, st.estimate_rel_stderr,
                                st.boxes_processed)
        serial_cpu = (settings.workers <= 1 and not settings.scheduler
                      and torch.device(problem.device).type == "cpu")
        spread = ("; a GPU (--device cuda) or Dask workers (--workers, --scheduler) evaluate "
                  "more boxes in the same time" if serial_cpu else "")
        why = (f"proof budget spent (max_boxes={settings.max_boxes:,} boxes); {found}; "
               "raise max_boxes" + (f": {ahead}" if ahead else "") + spread)
    return MpdiResult(
        status=Status.UNKNOWN, upper=outcome.upper, proof=outcome.stats,
        seconds=time.perf_counter() - t0, message=why, **common)


def _fmt(values: list[float]) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"


# ----------------------------------------------------------------------------- check protocol

class MpdiCheck(Check):
    """The MPDI on X x Y: grid + ascent for counterexamples, then the prover."""

    name = "mpdi"
    title = "MPDI: D(x\u0302, y) \u2aaf 0"
    result_type = MpdiResult
    reads = ("grid_points", "float32_screen", "adversarial_starts", "adversarial_steps",
             "top_counterexamples", "max_boxes", "seed")

    def run(self, context: Context) -> MpdiResult:
        scratch: dict[str, Any] = {}
        result = check_mpdi(context.on_device(), context.settings, progress=context.progress,
                            figures=scratch, executor=context.executor,
                            deadline=context.deadline, coarse_first=context.fail_fast)
        boxes = scratch.get("proof_boxes")
        if boxes and boxes.get("lo"):
            context.figures.proof_boxes = ProofBoxes(
                lo=boxes["lo"], hi=boxes["hi"], status=boxes["status"],
                axes=list(context.problem.system.states[:2]))
        context.figures.proof_history = list(scratch.get("proof_history") or [])
        return result

    def present(self, r: MpdiResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        why_no_upper = ("not needed: counterexample found" if r.status == Status.VIOLATED
                        else "no proof attempted")
        upper = Quantity("sound upper bound on max \u03bb_max(D)", r.upper, why_no_upper,
                         signed=True, bound="upper")
        numbers = [Quantity("lower (sampled max lambda_max(D))", r.lower, sig=6, signed=True,
                            bound="lower"),
                   Quantity("upper (proved bound)", r.upper, why_no_upper, sig=6, signed=True,
                            bound="upper"),
                   Quantity("violating fraction of grid", r.violating_fraction),
                   Quantity("counterexamples", len(r.counterexamples))]
        facts = [Quantity("Status", r.status.value),
                 Quantity("Sampled max \u03bb_max(D)", r.lower, sig=6, signed=True,
                          bound="lower"),
                 Quantity("Proved upper bound", r.upper, why_no_upper, sig=6, signed=True,
                          bound="upper"),
                 Quantity("Violating fraction of the grid", 100 * r.violating_fraction,
                          suffix=" %"),
                 Quantity("Grid points", r.grid_points),
                 Quantity("Ascent starts", r.adversarial_starts)]
        if r.worst is not None:
            numbers.append(Quantity("worst xhat, y", [*r.worst.xhat, *r.worst.y]))
            facts += [Quantity("Worst point x\u0302", r.worst.xhat),
                      Quantity("Worst point y", r.worst.y),
                      Quantity("\u03bb_max(D) at the worst point", r.worst.value, sig=5,
                               signed=True)]
        if r.proof is not None:
            numbers += [Quantity("boxes processed", r.proof.boxes_processed),
                        Quantity("proved volume fraction", r.proof.proved_volume_fraction),
                        Quantity("budget exhausted", r.proof.budget_exhausted)]
            if r.proof.estimated_boxes is not None:  # an unfinished proof (tree_estimate)
                numbers += [Quantity("boxes a complete proof needs (estimate)",
                                     r.proof.estimated_boxes, sig=2),
                            Quantity("seconds more at this run's speed (estimate)",
                                     r.proof.seconds_to_finish(), sig=2,
                                     missing="no speed measured")]
        return Presentation(
            sampled=Quantity("max \u03bb_max(D) found (grid + ascent)", r.lower, signed=True,
                             bound="lower"),
            proved=upper,
            setting=(setting_quantity("grid_points", {"grid_points": r.grid_points
                                                      or s.get("grid_points")}),
                     setting_quantity("adversarial_starts",
                                      {"adversarial_starts": r.adversarial_starts}),
                     setting_quantity("max_boxes", s)),
            numbers=tuple(numbers), facts=tuple(facts))


CHECK = MpdiCheck()
