"""Certified contraction rate lam_cert (METHOD §3.2).

lam_cert = -max over X x Y of lam_max(He{P J_cl}, P) / 2. Sampling gives an upper bound on
lam_cert (a point where the rate is low); the prover gives a proved lower bound. "No
contraction" (VIOLATED) needs a point where a sound lower bound of lam_max(He{P J_cl}) is
>= 0 (`certify.search.witness`); a float64 rate <= 0 without one is a near-tie (UNKNOWN).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch

from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context, setting_quantity
from certify.checks.mpdi import counterexamples_from, joint_box
from certify.model.kernels import pointwise_rate
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.results import MpdiResult, ProofStats, RateResult, Status
from certify.search.falsify import maximize_over_box
from certify.search.grid import float32_rate_screen
from certify.search.witness import is_witness, rate_sign_lower
from certify.settings import VerifySettings

#: relative gap at which the rate proof stops: lam_cert is reported to 4 significant digits
RATE_REL_TOL = 1e-4
#: boxes after which the rate proof's tolerance relaxes to 1e-3 (the bound stays sound)
RATE_FINE_BOXES = 16_384
#: share of `rate_boxes` for the maximisation branch and bound; when it runs out before
#: closing, the rest of the budget goes to MPDI decisions above the proved rate
#: (`certify.prove.rate.raise_rate`). When the MPDI proof already proved the design rate
#: and the branch and bound has not proved more after RATE_FINE_BOXES boxes, it hands over
#: to the decisions then: on a flat D the maximisation can end below the design rate where
#: the decisions still climb (the reason: `bench/run.py --only vdp2_lmi`)
RATE_BNB_SHARE = 0.25
#: the decisions stop when the bracket [proved, sampled] is this narrow (relative): the
#: report prints lam_cert to 4 significant digits, and each halving costs about twice the
#: last
RATE_LADDER_REL_TOL = 1e-3


def check_rate(problem: Problem, settings: VerifySettings, *,
               progress: Progress | None = None, prove: bool = True,
               mpdi: MpdiResult | None = None,
               place: Callable[[Problem], Problem] | None = None,
               deadline: float | None = None) -> RateResult:
    """Bracket lam_cert: sampled upper value and, when `prove`, a proved lower bound (the
    grid on `problem`, the proofs on `place(problem)`: the problem on the run's device,
    `certify.checks.base.Context.on_device`; default `problem` itself).

    A PROVED MPDI at the design lam already proves lam_cert >= lam; the rate's own branch and
    bound (RATE_BNB_SHARE of `rate_boxes`) can only raise that, and when it runs out before
    closing, MPDI decisions at rates above the proved one use the rest of the budget
    (`certify.prove.rate.raise_rate`). No proof is attempted when sampling already shows a rate
    <= 0 (then no bound exists whatever the proof says). `deadline`: the run's wall-clock
    cap (None: none). The grid is swept with a float32 screen where `float32_screen` is on
    and the problem's numbers fit float32 (`certify.search.grid.float32_rate_screen`): it
    only selects the points evaluated again in float64, whose values are the check's.
    """
    progress = progress or NullProgress()
    t0 = time.perf_counter()
    n, P = problem.n, problem.P_t

    def neg_rate(z: torch.Tensor) -> torch.Tensor:
        return -pointwise_rate(problem.system, problem.network, P, z[:, :n], z[:, n:])

    lo, hi = joint_box(problem)
    grid = max(1000, settings.grid_points // 4)
    screen = float32_rate_screen(problem) if settings.float32_screen else None
    search = maximize_over_box(neg_rate, lo, hi, grid_points=grid, screen=screen,
                               starts=settings.adversarial_starts,
                               steps=settings.adversarial_steps, top_k=1, seed=settings.seed,
                               progress=progress, task="rate grid")
    sampled_upper = -search.best_value
    worst = counterexamples_from(search, n)[:1]
    worst_cex = worst[0] if worst else None
    witnessed = False
    if worst_cex is not None:
        worst_cex.value = sampled_upper  # the pointwise rate at that point
        z = torch.tensor([[*worst_cex.xhat, *worst_cex.y]], dtype=torch.float64)
        # sound: lam_max(He{P J}) >= this bound there; >= 0 proves rate <= 0 at the point
        sign_lower = float(rate_sign_lower(problem, z)[0])
        worst_cex.sound_bound = sign_lower
        witnessed = is_witness(sign_lower, strict=False)
    proved_lower = problem.lam if mpdi is not None and mpdi.status == Status.PROVED else None
    proofs: list[ProofStats] = []
    if prove and search.nonfinite == 0 and sampled_upper > 0:
        from certify.prove.mpdi import prove_rate

        # the grid's worst point seeds the closing level: with it the proof stops at the
        # precision the report prints (RATE_REL_TOL) in fewer boxes than an unseeded
        # proof needs for 1e-3 (`bench/run.py`); where that precision is dear (bounds of
        # first order), the tolerance relaxes to 1e-3 after RATE_FINE_BOXES boxes. On
        # the problem's device, in rounds of the CPU's size: the same boxes and bound on
        # every device (up to the last bits of rounding)
        seeds = [[*worst_cex.xhat, *worst_cex.y]] if worst_cex is not None else None
        on_device = problem if place is None else place(problem)
        outcome = prove_rate(on_device, max_boxes=max(1, int(settings.rate_boxes
                                                             * RATE_BNB_SHARE)),
                             deadline=deadline, progress=progress, seeds=seeds,
                             rel_tol=RATE_REL_TOL, coarse_after=(RATE_FINE_BOXES, 1e-3),
                             give_up=None if proved_lower is None
                             else (RATE_FINE_BOXES, proved_lower))
        proofs.append(outcome.stats)
        if outcome.lower is not None and outcome.lower == outcome.lower:
            proved_lower = outcome.lower if proved_lower is None else max(proved_lower,
                                                                          outcome.lower)
        left = settings.rate_boxes - outcome.stats.boxes_processed
        # from the proved rate, or from 0 when none is positive (0 is then only where the
        # ladder starts: a rate counts as proved only when a decision proved it)
        start = proved_lower if proved_lower is not None and proved_lower > 0 else 0.0
        if (outcome.stats.budget_exhausted and not outcome.stats.stopped_by_cap
                and sampled_upper > start and left > 0):
            from certify.prove.rate import raise_rate

            ladder = raise_rate(on_device, start, sampled_upper, max_boxes=left,
                                deadline=deadline, rel_tol=RATE_LADDER_REL_TOL,
                                progress=progress)
            proofs += ladder.stats
            if ladder.lower > start:
                proved_lower = ladder.lower
    proof = ProofStats.total(proofs)
    seconds = time.perf_counter() - t0
    if search.nonfinite:
        return RateResult(Status.UNKNOWN, "the rate is NaN/Inf at some grid points",
                          problem.lam, sampled_upper, None, worst_cex, seconds, proof)
    if sampled_upper <= 0 and witnessed:
        status, msg = Status.VIOLATED, (
            f"no contraction: at xhat={worst_cex.xhat}, y={worst_cex.y} the pointwise rate is "
            f"{sampled_upper:.4g} <= 0 (sound: lam_max(He{{P J}}) >= "
            f"{lower_text(worst_cex.sound_bound)}"
            f" >= 0 there), so lam_cert <= 0 and no error bound exists")
    elif sampled_upper <= 0:
        status, msg = Status.UNKNOWN, (
            f"near-tie: the pointwise rate evaluates to {sampled_upper:.4g} <= 0 in float64 at "
            f"xhat={worst_cex.xhat if worst_cex else None}, but within rounding error of 0 "
            "(no sound bound decides its sign); lam_cert is neither proved positive nor "
            "shown <= 0")
    elif proved_lower is not None and proved_lower > 0:
        status, msg = Status.PROVED, (
            f"lam_cert in [{lower_text(proved_lower, 4)}, {upper_text(sampled_upper, 4)}] "
            f"(design lam {problem.lam:g}; "
            "the error contracts at rate 2 lam_cert in the P-norm)")
    else:
        lower = ("not proved" if proved_lower is None
                 else f"proved lower bound {lower_text(proved_lower, 4)}")
        status, msg = Status.UNKNOWN, (
            f"lam_cert <= {upper_text(sampled_upper, 4)} (sampled); {lower}")
    return RateResult(status, msg, problem.lam, sampled_upper, proved_lower, worst_cex, seconds,
                      proof)


# ----------------------------------------------------------------------------- check protocol

class RateCheck(Check):
    """The certified contraction rate lam_cert, bracketed (a PROVED MPDI is a lower bound)."""

    name = "rate"
    title = "Contraction rate \u03bb_cert"
    result_type = RateResult
    reads = ("grid_points", "float32_screen", "adversarial_starts", "adversarial_steps", "seed",
             "rate_boxes")
    uses = ("mpdi",)

    def run(self, context: Context) -> RateResult:
        return check_rate(context.problem, context.settings, progress=context.progress,
                          mpdi=context.result("mpdi"), place=context.on_device,
                          deadline=context.deadline)

    def present(self, r: RateResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        lower = Quantity("\u03bb_cert \u2265 (proved)", r.proved_lower,
                         "MPDI not proved at any \u03bb > 0", signed=True, bound="lower")
        facts = [Quantity("Design \u03bb", r.lam_design),
                 Quantity("\u03bb_cert \u2264 (sampled)", r.sampled_upper, sig=6, signed=True,
                          bound="upper"),
                 Quantity("\u03bb_cert \u2265 (proved, branch and bound)", r.proved_lower,
                          "not proved", sig=6, signed=True, bound="lower")]
        if r.worst is not None:
            facts += [Quantity("Sampled side attained at x\u0302", r.worst.xhat),
                      Quantity("Sampled side attained at y", r.worst.y)]
        return Presentation(
            sampled=Quantity("\u03bb_cert \u2264 (sampled)", r.sampled_upper, signed=True,
                             bound="upper"),
            proved=lower,
            setting=(Quantity("design \u03bb =", r.lam_design),
                     setting_quantity("rate_boxes", s)),
            numbers=(Quantity("lam_design", r.lam_design, sig=6),
                     Quantity("sampled upper", r.sampled_upper, sig=6, bound="upper"),
                     Quantity("proved lower", r.proved_lower, sig=6, bound="lower")),
            facts=tuple(facts))


CHECK = RateCheck()
