"""Sound upper bounds of max lam_max(M D M^T) over boxes: plain interval and Taylor forms.

See `certify.enclosures` for the overview; each ingredient documents its own rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.eigen import lam_max_upper_interval, taylor_upper
from certify.arith.interval_ops import bcast, iadd, nan_min
from certify.arith.intervals import Interval, up
from certify.enclose.network_interval import gain_enclosure
from certify.enclose.preconditioner import (
    Preconditioner,
    candidate_preconditioners,
    congruence,
    constant_term,
    diagonal_preconditioner,
    make_preconditioner,
    to_lam_max_D,
    with_shift,
)
from certify.enclose.split import split_score
from certify.enclose.taylor import HERTZ_MAX_N, jcl_taylor, tm_congruence, tm_lam_upper
from certify.model.problem import Problem

DIRECT_MIXED = True  # with M = I and a direct network: skip the Taylor stage (see below)
#: the mixed stage keeps the last hidden layer's relaxation errors as a matrix
#: (`certify.enclose.structured`); False: entry by entry, as before (for comparisons)
STRUCTURED_TOP = True
CROWN_GAIN = 100.0  # remainder reduction assumed when choosing boxes for the linear bounds

#: boxes per stage since import (diagnostics for bench/prove_suite.py; never read by proofs)
STAGE_COUNTS = {"boxes": 0, "taylor": 0, "crown": 0, "crown_closed": 0}


@dataclass
class BoxBounds:
    """Per box: upper bounds of max lam_max(A) (A = M D M^T), plain and Taylor, and the
    per-dimension width contributions used to choose the split."""

    upper: torch.Tensor  # [B]  min of the two (NaN: unknown)
    plain: torch.Tensor  # [B]
    taylor: torch.Tensor  # [B]
    score: torch.Tensor  # [B, d] split score per dimension


def mpdi_box_bounds(problem: Problem, lo: torch.Tensor, hi: torch.Tensor, lam: float,
                    pc: Preconditioner | None = None, taylor: bool | str = True,
                    crown: bool = True, screen: float | None = None,
                    crown_gain: float | CrownGain = CROWN_GAIN,
                    root_width: torch.Tensor | None = None,
                    split_rule: str = "sensitivity", decide: bool = False,
                    plain_screen: bool = True) -> BoxBounds:
    """Sound upper bounds of max over each box of lam_max(M D M^T), D with rate lam.

    taylor: True (first-order Taylor models through the network, the default), "interval"
    (mean-value form with interval second derivatives) or False (plain interval only).
    crown (with taylor=True): the network's Taylor models are tightened entry by entry by
    backward linear bound propagation (`certify.enclose.crown`). screen: boxes whose plain
    interval bound is already <= screen skip the Taylor / linear-relaxation work; the linear
    bounds are tried where a remainder `crown_gain` times smaller would pass (see
    `estimate_crown_gain`). With the congruence M = I (pc.kind "none", chosen by
    `choose_preconditioner`) and a direct network, the boxes the plain bound leaves go straight
    to the linear bounds of P dN/dx with mixed rows (`certify.enclose.mixed`), which contain
    the Taylor models entry by entry. split_rule: how the split score is formed
    (`certify.enclose.split.split_score`). decide: the caller only asks whether each bound is
    <= the level (screen, else 0; a decision, not a maximisation): for n >= 4 the vertex
    matrices are tested by the certified Cholesky test (`tm_lam_upper(level=...)`) and a box
    it decides reports (just below) the level instead of its eigenvalue bound. plain_screen=False
    (with crown and the mixed rows; see `plain_screen_pays`): no plain interval stage, every
    box goes to the linear bounds and `plain` is +inf."""
    system, net = problem.system, problem.network
    if pc is None:
        pc = with_shift(make_preconditioner(problem.P_t), problem.shift_t)
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    zc = 0.5 * (lo + hi)
    zr = up(torch.maximum(hi - zc, zc - lo))
    wscore = zr * (1.0 / (zr.amax(-1, keepdim=True) + 1e-300))
    if not plain_screen and taylor is True and crown and direct_mixed(problem, pc):
        STAGE_COUNTS["boxes"] += B
        tay, s_w = _mixed_stage(problem, pc, lo, hi, zr, lam, screen, decide)
        return BoxBounds(tay, torch.full_like(tay, float("inf")), tay,
                         split_score(split_rule, s_w, zr, root_width, net))
    lamC = constant_term(pc, lam)
    # centre pass (thin intervals around A(c)) and box pass
    gc, nec = gain_enclosure(system, net, zc, zc, order=1)
    order = 2 if taylor == "interval" else 1
    gb, _ = gain_enclosure(system, net, lo, hi, order=order, center_pre=nec.pre)
    Ab = iadd(congruence(pc, iadd(gb.jf, gb.dk_dx)), bcast(lamC, B))
    plain = lam_max_upper_interval(Ab, level=(0.0 if screen is None else screen) if decide
                                   else None)
    if not taylor:
        return BoxBounds(plain, plain, torch.full_like(plain, float("inf")), wscore)
    if taylor == "interval":
        Ac = iadd(congruence(pc, iadd(gc.jf, gc.dk_dx)), bcast(lamC, B))
        dJ = iadd(gb.djf, gb.d2k)  # [B, n, n, d]
        dA = congruence(pc, Interval(dJ.lo.permute(0, 3, 1, 2), dJ.hi.permute(0, 3, 1, 2)))
        tay, score = taylor_upper(Ac, dA, zr)
        return BoxBounds(nan_min(plain, tay), plain, tay, score)
    # stage 1: plain intervals (screen); stage 2: forward Taylor models; stage 3 (crown): the
    # backward linear bounds, only where stage 2 failed while its affine (vertex) part alone
    # would pass, i.e. where a tighter remainder can decide the box
    work = (torch.ones(B, dtype=torch.bool, device=lo.device) if screen is None
            else ~(plain <= screen))
    decide_level = (0.0 if screen is None else screen) if decide else None
    STAGE_COUNTS["boxes"] += B
    tay = torch.full_like(plain, float("inf"))
    score = wscore.clone()
    if bool(work.any()):
        wl, wh, wr = lo[work], hi[work], zr[work]
        if crown and direct_mixed(problem, pc):
            # the mixed-row linear bounds contain the Taylor models entry by entry: no
            # Taylor stage first (measured on the 2x10 4-state chain: fewer boxes per CPU
            # second than screening with the Taylor models)
            t_w, s_w = _mixed_stage(problem, pc, wl, wh, wr, lam, screen, decide)
            tay[work] = t_w
            score[work] = split_score(split_rule, s_w, wr, root_width, net)
            return BoxBounds(nan_min(plain, tay), plain, tay, score)
        STAGE_COUNTS["taylor"] += int(work.sum())
        Jt = jcl_taylor(system, net, wl, wh)
        t_w, s_w, lv = tm_lam_upper(tm_congruence(pc, Jt, lam, wr), wr, parts=True,
                                    level=decide_level)
        if crown:
            level = 0.0 if screen is None else screen
            # the linear bounds cut the remainder by 10-1000x on small boxes: try them where
            # a 100x smaller remainder would decide the box
            gain = crown_gain
            if isinstance(crown_gain, CrownGain):
                # the box's radius relative to the root's width (no root: the smallest scale)
                rel = ((wr / root_width).amax(-1) if root_width is not None
                       else torch.zeros(len(wr), dtype=torch.float64, device=wr.device))
                gain = crown_gain.at(rel)
            again = ~(t_w <= level) & (lv + (t_w - lv) / gain <= level)
            if screen is None:
                again = torch.ones_like(again)
            if bool(again.any()):
                al, ah, ar = wl[again], wh[again], wr[again]
                Ac = crown_contraction_tm(problem, pc, al, ah, ar, lam)
                t_c, s_c = tm_lam_upper(Ac, ar, level=decide_level)
                STAGE_COUNTS["crown"] += int(again.sum())
                STAGE_COUNTS["crown_closed"] += int((t_c <= level).sum())
                better = torch.nan_to_num(t_c, nan=float("inf")) < t_w[again]
                idx = torch.nonzero(again).squeeze(-1)[better]
                t_w[idx] = t_c[better]
                s_w[idx] = s_c[better]
        tay[work] = t_w
        score[work] = split_score(split_rule, s_w, wr, root_width, net)
    return BoxBounds(nan_min(plain, tay), plain, tay, score)


def _mixed_stage(problem: Problem, pc: Preconditioner, lo: torch.Tensor, hi: torch.Tensor,
                 r: torch.Tensor, lam: float, screen: float | None, decide: bool
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """(bound, Taylor split score) of the boxes from the mixed-row linear bounds
    (`certify.enclose.mixed.contraction_tm_mixed`; the last hidden layer's errors as a matrix,
    `certify.enclose.structured`), decided against the level (screen, else 0) when
    `decide`."""
    from certify.enclose.mixed import contraction_tm_mixed
    from certify.enclose.structured import entrywise, loewner_upper

    level = 0.0 if screen is None else screen
    STAGE_COUNTS["crown"] += lo.shape[0]
    A, top = contraction_tm_mixed(problem, pc, lo, hi, r, lam, top_apart=STRUCTURED_TOP)
    dlevel = level if decide else None
    if top is None:
        bound, score = tm_lam_upper(A, r, level=dlevel)
    else:
        bound, score = tm_lam_upper(loewner_upper(A, top, level), r, level=dlevel)
        if problem.n <= HERTZ_MAX_N:
            # Hertz's bound (n <= 3) is exact for an entrywise remainder: there the entrywise
            # form can win (2x10 and 3x30 Van der Pol: 13-27% more boxes with the matrix form
            # alone); both come from the same backward pass, the smaller bound is kept
            b2, s2 = tm_lam_upper(entrywise(A, top), r, level=dlevel)
            use2 = torch.nan_to_num(b2, nan=float("inf")) < torch.nan_to_num(
                bound, nan=float("inf"))
            bound = torch.where(use2, b2, bound)
            score = torch.where(use2[:, None], s2, score)
    STAGE_COUNTS["crown_closed"] += int((bound <= level).sum())
    return bound, score


def crown_contraction_tm(problem: Problem, pc: Preconditioner, lo: torch.Tensor,
                         hi: torch.Tensor, r: torch.Tensor, lam: float):
    """The Taylor model of A = M D M^T over boxes (radii r, rounded up) from the backward
    linear bounds: the mixed-row form (`certify.enclose.mixed`) for M = I and a direct
    network, else the network's linear-bound Taylor models through `jcl_taylor`."""
    net = problem.network
    if pc.kind == "none" and net.structure == "direct":
        from certify.enclose.mixed import contraction_tm_mixed

        return contraction_tm_mixed(problem, pc, lo, hi, r, lam)[0]
    from certify.enclose.crown import network_crown_tms

    net_tms = network_crown_tms(net, lo, hi, list(range(problem.n)), value=problem.structural)
    return tm_congruence(pc, jcl_taylor(problem.system, net, lo, hi, net_tms=net_tms), lam, r)


def direct_mixed(problem: Problem, pc: Preconditioner) -> bool:
    """Whether `mpdi_box_bounds` (with crown) sends the boxes the plain bound leaves straight
    to the mixed-row linear bounds: M = I (P != I) and a direct network."""
    return DIRECT_MIXED and pc.kind == "none" and problem.network.structure == "direct"


@dataclass
class CrownGain:
    """Remainder reduction of the linear bounds over the Taylor models, as a function of the
    box size: gains [K] measured at relative radii [K] (increasing), interpolated in log-log
    and clamped at the ends. Only decides where the linear bounds are tried."""

    rel_radii: torch.Tensor
    gains: torch.Tensor

    def at(self, rel_radius: torch.Tensor) -> torch.Tensor:
        x = torch.log(rel_radius.clamp(self.rel_radii[0], self.rel_radii[-1]))
        xs, ys = torch.log(self.rel_radii), torch.log(self.gains)
        i = torch.searchsorted(xs, x.contiguous()).clamp(1, len(xs) - 1)
        t = (x - xs[i - 1]) / (xs[i] - xs[i - 1])
        return torch.exp(ys[i - 1] + t * (ys[i] - ys[i - 1]))


def estimate_crown_gain(net, root_lo: torch.Tensor, root_hi: torch.Tensor,
                        probes: int = 12, scales: tuple[float, ...] = (1 / 256, 1 / 64, 1 / 16),
                        deadline: float | None = None) -> CrownGain:
    """How much the linear bounds shrink the Jacobian remainder for this network, at a few box
    sizes: at each relative radius, the median ratio of Taylor-model to linear-bound remainders
    over `probes` deterministic boxes inside the root box, clamped to [2, 1e6]. Deterministic
    in the problem, so every worker of a distributed proof chooses alike. `deadline`: a proof's
    budget, read before each size (`certify.budget.OutOfTime` once it has passed)."""
    from certify.budget import check_clock
    from certify.enclose.crown import forward_bounds, jacobian_crown, to_tm

    d = root_lo.shape[0]
    g = torch.Generator().manual_seed(1234)
    w = (root_hi - root_lo).to(torch.float64)
    u = torch.rand(probes, d, generator=g, dtype=torch.float64, device="cpu").to(w.device)
    cols = list(range(d))
    gains = []
    for s in scales:
        check_clock(deadline)
        c = root_lo + w * (s + (1 - 2 * s) * u)
        lo, hi = c - w * s, c + w * s
        fb = forward_bounds(net, lo, hi, cols=cols, crown=True)
        e_cr = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r).e
        ratio = (fb.jac_tm.e / e_cr.clamp_min(1e-300)).flatten()
        ratio = ratio[torch.isfinite(ratio)]
        gains.append(float(ratio.median().clamp(2.0, 1e6)) if len(ratio) else CROWN_GAIN)
    return CrownGain(torch.tensor(scales, dtype=torch.float64, device=w.device),
                     torch.tensor(gains, dtype=torch.float64, device=w.device))


def _root_box(problem: Problem) -> torch.Tensor:
    """The root box X x Y as [d, 2] (lo, hi) float64."""
    import numpy as np

    s = problem.system
    return torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=torch.float64,
                           device=problem.device)


def plain_screen_pays(problem: Problem, lam: float, pc: Preconditioner, grid: int = 1024,
                      min_closed: float = 0.02, deadline: float | None = None,
                      chunk: int = 256) -> bool:
    """Whether the plain interval stage should screen the boxes before the linear bounds: it
    closes at least `min_closed` of the root split into `grid` boxes (the B&B's first round
    at the default batch; one plain-only evaluation of it). Measured on that grid: 55-79% on
    the 2x10 Van der Pol instances (seeds 0-2; in whole proofs the screen closed a third of
    the boxes there), at most 0.1% on the 2x10 chains with n = 3, 4, 6 and the 3x30 and 5x30
    Van der Pol instances, where in whole proofs it closed none and cost about an eighth of
    the time. (Random boxes of a given size do not predict this: a proof only refines boxes
    in the hard regions.) Only which bound is computed depends on it, never soundness; it is
    deterministic in the problem, so every worker of a distributed proof chooses alike.
    The boxes are bounded `chunk` at a time (the plain bound of a box does not depend on
    the others), the `deadline` of a proof's budget read before each chunk
    (`certify.budget.OutOfTime` once it has passed)."""
    from certify.arith.boxes import initial_grid
    from certify.budget import check_clock

    root = _root_box(problem)
    boxes = initial_grid(root[:, 0], root[:, 1], grid)
    closed = 0
    for a in range(0, len(boxes), chunk):
        check_clock(deadline)
        bb = mpdi_box_bounds(problem, boxes.lo[a:a + chunk], boxes.hi[a:a + chunk], lam,
                             pc=pc, taylor=False)
        closed += int((bb.plain <= 0).sum())
    return closed / len(boxes) >= min_closed


#: where the magnitudes of D's diagonal at the root's centre span more than this ratio, the
#: congruence M = diag(|D_ii|^-1/2), which brings that diagonal to -1 or 1, is a candidate too:
#: float64 keeps about 2^-53 of the largest entry, so a bound on D itself loses the small
#: ones (a spec with a term -1e39 x1 beside -x2: D's eigenvalue -0.5 is below the rounding
#: of -1e39). Never the case on the shipped examples, whose candidates stay those of P.
SCALE_SPREAD = 2.0**26


def diagonal_scaling(problem: Problem, lam: float) -> torch.Tensor | None:
    """|D_ii|^-1/2 [n] at the centre of X x Y (float64 point values; any positive M serves,
    `certify.enclose.preconditioner`) where those magnitudes span more than SCALE_SPREAD, else
    None (also where one is 0 or not finite)."""
    from certify.model.kernels import contraction_matrix, gain_terms

    root = _root_box(problem)
    c = (0.5 * (root[:, 0] + root[:, 1]))[None]
    n = problem.n
    with torch.no_grad():
        dk = gain_terms(problem.system, problem.network, c[:, :n], c[:, n:],
                        with_dy=False).dk_dx
        D = contraction_matrix(problem.system.jac_f(c[:, :n]), dk, problem.P_t, lam,
                               problem.shift_t)[0]
    mag = D.diagonal().abs()
    if not bool(torch.isfinite(mag).all()) or not bool((mag > 0).all()):
        return None
    if float(mag.max()) <= SCALE_SPREAD * float(mag.min()):
        return None
    return mag.rsqrt()


def choose_preconditioner(problem: Problem, lam: float, probes: int = 24,
                          scales: tuple[float, ...] = (1 / 16, 1 / 32),
                          deadline: float | None = None) -> Preconditioner:
    """The congruence M (`candidate_preconditioners`) under which the box bounds close the most
    of `probes` deterministic boxes per relative radius in `scales`; ties go to the smaller
    median bound on lam_max(D) over the probes (then the earlier candidate, M ~ L^-1 first).
    A badly scaled D adds the candidate `diagonal_scaling`.
    The tie-break matters: on examples/vdp2_lmi.ckpt M ~ L^-1 and M = I both close all 48
    probes, and the whole proof takes 88,768 boxes with the first against 256 with the second
    (median bounds -0.24 and -0.76 at radius 1/16). Only tightness depends on the choice,
    never soundness; it is deterministic in the problem, so every worker of a distributed
    proof chooses alike. `deadline`: a proof's budget, read before each candidate
    (`certify.budget.OutOfTime` once it has passed)."""
    from certify.budget import check_clock

    cands = candidate_preconditioners(problem.P_t)
    scaling = diagonal_scaling(problem, lam)
    if scaling is not None:  # a badly scaled D (SCALE_SPREAD)
        cands = [*cands, diagonal_preconditioner(problem.P_t, scaling, "scaled")]
    cands = [with_shift(pc, problem.shift_t) for pc in cands]
    if len(cands) == 1:
        return cands[0]
    root = _root_box(problem)
    rlo, rhi = root[:, 0], root[:, 1]
    w = rhi - rlo
    g = torch.Generator().manual_seed(4321)
    # drawn on the CPU (the same probes, so the same choice, on every device)
    u = torch.rand(probes, len(w), generator=g, dtype=torch.float64, device="cpu").to(w.device)
    los, his = [], []
    for sc in scales:
        c = rlo + w * (sc + (1 - 2 * sc) * u)
        los.append(c - w * sc)
        his.append(c + w * sc)
    lo, hi = torch.cat(los), torch.cat(his)
    best, best_key = cands[0], None
    for pc in cands:
        check_clock(deadline)
        bb = mpdi_box_bounds(problem, lo, hi, lam, pc=pc, screen=None)
        closed = int((bb.upper <= 0).sum())
        ub = torch.nan_to_num(to_lam_max_D(bb.upper, problem.P_t, pc), nan=float("inf"))
        key = (closed, -float(ub.median()))
        if best_key is None or key > best_key:
            best, best_key = pc, key
    return best
