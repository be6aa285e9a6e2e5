"""Sound upper bounds of max lam_max(M D M^T) over boxes, and the choices made once per proof.

`mpdi_box_bounds` runs the stages of `certify.enclose.stages` that the options select
(`certify.enclose.options.BoxBoundOptions`, made once per proof by `box_bound_options`) on
a batch of boxes, keeping per box the smallest sound bound, and says how many boxes each
stage bounded and closed. The probes below make the choices a proof's options hold:
the congruence M (`choose_preconditioner`), whether the plain interval stage screens the
boxes before the mixed rows (`plain_screen_pays`) and how much the linear bounds shrink the
remainders (`estimate_crown_gain`). Each probe is deterministic in the problem (every worker
of a distributed proof chooses alike) and only chooses, never bounds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from certify.arith.interval_ops import nan_min
from certify.enclose.options import (
    CROWN_GAIN,
    BoxBoundOptions,
    CrownGain,
    Technique,
    box_bound_options,
)
from certify.enclose.preconditioner import (
    Preconditioner,
    candidate_preconditioners,
    diagonal_preconditioner,
    to_lam_max_D,
    with_shift,
)
from certify.enclose.stages import BoxState, select_stages
from certify.model.problem import Problem


@dataclass
class BoxBounds:
    """Per box: upper bounds of max lam_max(A) (A = M D M^T), the screen's and the later
    stages', the split score, and per stage the boxes it bounded and closed."""

    upper: torch.Tensor  # [B]  nan_min(plain, taylor) (NaN: unknown)
    plain: torch.Tensor  # [B]  the plain interval bound (+inf where it did not run)
    taylor: torch.Tensor  # [B]  the later stages' bound (+inf where none ran)
    score: torch.Tensor  # [B, d] split score per dimension
    #: stage name -> {"boxes": bounded by it, "closed": of those, bound <= the level}
    counts: dict[str, dict[str, int]] = field(default_factory=dict)


def mpdi_box_bounds(options: BoxBoundOptions, lo: torch.Tensor, hi: torch.Tensor
                    ) -> BoxBounds:
    """Sound upper bounds of max over each box [lo, hi] [B, d] of lam_max(M D M^T), D at the
    options' rate and M their congruence: the stages `select_stages(options)` in order, each
    on the boxes it selects, the smallest sound bound kept per box
    (`certify.enclose.stages`). In a decision (`options.decide`) a box proved below the
    level may report (just below) the level instead of its eigenvalue bound. `counts`: per
    stage that applies, the boxes it bounded and, of those, the ones its bound put at or
    below `options.level` (statistics; nothing reads them to decide)."""
    state = BoxState(options, lo, hi)
    counts: dict[str, dict[str, int]] = {}
    for stage in select_stages(options):
        mask = stage.select(options, state)
        seen = int(mask.sum())
        closed = 0
        if seen:
            res = stage.bound(state.boxes.take(mask), options, state)
            closed = int((res.bound <= options.level).sum())
            state.keep(stage, mask, res)
        counts[stage.name] = {"boxes": seen, "closed": closed}
    return BoxBounds(nan_min(state.plain, state.bound), state.plain, state.bound, state.score,
                     counts)


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
    at the default batch; one plain-only evaluation of it). On the benchmark families it
    either closes a large share of that grid (and of a whole proof's boxes) or almost none,
    where in whole proofs it closed none and cost time (the stage counts of
    `bench/prove_suite.py`). (Random boxes of a given size do not predict this: a proof only
    refines boxes in the hard regions.) Only which bound is computed depends on it, never
    soundness; it is
    deterministic in the problem, so every worker of a distributed proof chooses alike.
    The boxes are bounded `chunk` at a time (the plain bound of a box does not depend on
    the others), the `deadline` of a proof's budget read before each chunk
    (`certify.budget.OutOfTime` once it has passed)."""
    from certify.arith.boxes import initial_grid
    from certify.budget import check_clock

    root = _root_box(problem)
    boxes = initial_grid(root[:, 0], root[:, 1], grid)
    plain = box_bound_options(problem, lam, pc=pc, technique=Technique.PLAIN)
    closed = 0
    for a in range(0, len(boxes), chunk):
        check_clock(deadline)
        bb = mpdi_box_bounds(plain, boxes.lo[a:a + chunk], boxes.hi[a:a + chunk])
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
    from certify.model.kernels import problem_matrix

    root = _root_box(problem)
    c = (0.5 * (root[:, 0] + root[:, 1]))[None]
    n = problem.n
    with torch.no_grad():
        D = problem_matrix(problem, lam, c[:, :n], c[:, n:])[0]
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
    The tie-break matters: on examples/vdp2_lmi.ckpt M ~ L^-1 and M = I both close every
    probe, and the whole proof takes far more boxes with the first than with the second,
    whose median bound is the smaller (`bench/same_numbers.py` records that proof's boxes;
    tests/enclose/test_preconditioner_choice.py holds it). Only tightness depends on the choice,
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
        bb = mpdi_box_bounds(box_bound_options(problem, lam, pc=pc), lo, hi)
        closed = int((bb.upper <= 0).sum())
        ub = torch.nan_to_num(to_lam_max_D(bb.upper, problem.P_t, pc), nan=float("inf"))
        key = (closed, -float(ub.median()))
        if best_key is None or key > best_key:
            best, best_key = pc, key
    return best
