"""The stages of the box bound: each one a sound upper bound of max lam_max(A) over a box,
A = M D M^T, that says where it applies.

A stage (`Stage`) answers three questions: does it apply to this proof (`applies(options)`,
from the fields of `certify.enclose.options.BoxBoundOptions` alone), which of a call's
boxes does it bound (`select(options, state)`, from what the stages before it found), and
what are its bounds and split scores on them (`bound(boxes, options, state)` ->
`StageResult`). `select_stages(options)` is the ordered list `STAGES` filtered by
`applies`; the driver `certify.enclose.mpdi.mpdi_box_bounds` runs them in that order on
one `BoxState`, which keeps per box:

- `plain`: the bound of the screening stage (the plain interval bound; +inf where it does
  not run), which decides which boxes the later stages see (`BoxState.open`);
- `bound`: the later stages' bound: the first one that bounds a box sets it, each later one
  replaces it where its own bound is smaller (a NaN of the later stage counts as +inf; a NaN
  kept bound stays), with the split score alongside.

The box's bound is then nan_min(plain, bound): the smaller, or NaN (unknown) where either
is. A minimum of sound upper bounds is a sound upper bound, so the result is sound when
every stage is; each stage's docstring says why it is.

Which stages run (`select_stages`), by the options:

    technique  crown  mixed rows  plain screen | stages
    PLAIN        -        -           -        | plain interval
    MEAN_VALUE   -        -           -        | plain interval, mean-value form
    TAYLOR     False      -           -        | plain interval, Taylor models
    TAYLOR     True     False         -        | plain interval, Taylor models, linear bounds
    TAYLOR     True     True        True       | plain interval, mixed rows
    TAYLOR     True     True        False      | mixed rows

Rounding is each ingredient's (`certify.enclose.taylor`, `certify.enclose.crown`,
`certify.enclose.mixed`, `certify.arith.eigen`): directed rounding and gamma_k bounds,
documented there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch

from certify.arith.eigen import lam_max_upper_interval, taylor_upper
from certify.arith.interval_ops import bcast, iadd
from certify.arith.intervals import Interval, up
from certify.arith.taylor import TM
from certify.enclose.mixed import TopLayerRemainder, contraction_tm_mixed
from certify.enclose.network_interval import gain_enclosure
from certify.enclose.options import BoxBoundOptions, CrownGain, Technique
from certify.enclose.path import closed_loop_box, closed_loop_tm, jacobian_columns
from certify.enclose.preconditioner import Preconditioner, congruence
from certify.enclose.structured import entrywise, independent_upper
from certify.enclose.taylor import HERTZ_MAX_N, tm_congruence, tm_lam_upper
from certify.enclose.top_rank import rank_loewner_upper
from certify.model.problem import Problem

INF = float("inf")


@dataclass
class Boxes:
    """Boxes lo <= z <= hi [B, d] (float64), their centres zc and radii zr >= |z - zc|
    (rounded up) [B, d]."""

    lo: torch.Tensor
    hi: torch.Tensor
    zc: torch.Tensor
    zr: torch.Tensor

    @classmethod
    def of(cls, lo: torch.Tensor, hi: torch.Tensor) -> Boxes:
        lo = lo.to(torch.float64)
        hi = hi.to(torch.float64)
        zc = 0.5 * (lo + hi)
        return cls(lo, hi, zc, up(torch.maximum(hi - zc, zc - lo)))

    def __len__(self) -> int:
        return int(self.lo.shape[0])

    def take(self, mask: torch.Tensor) -> Boxes:
        """The boxes where mask [B] (bool) holds, in order (all of them: these boxes)."""
        if bool(mask.all()):
            return self
        return Boxes(self.lo[mask], self.hi[mask], self.zc[mask], self.zr[mask])


@dataclass
class StageResult:
    """A stage's answer for the boxes it bounds [b]: `bound` an upper bound of max
    lam_max(A) over each box (NaN: unknown), `score` [b, d] the split score, and `vertex`
    [b] the bound's affine (vertex) part alone where the stage forms one (what a tighter
    remainder could reach: `LinearBounds` reads it)."""

    bound: torch.Tensor
    score: torch.Tensor
    vertex: torch.Tensor | None = None


class BoxState:
    """One call of the box bound: the boxes, what the stages have found so far (module
    docstring: `plain`, `bound`, `score`, `bounded`, `vertex`, all per box) and the interval
    enclosures the interval stages share (`interval_enclosures`, computed once per call)."""

    def __init__(self, options: BoxBoundOptions, lo: torch.Tensor, hi: torch.Tensor) -> None:
        self.options = options
        self.boxes = Boxes.of(lo, hi)
        zr = self.boxes.zr
        B = len(self.boxes)
        f64 = dict(dtype=torch.float64, device=zr.device)
        self.plain = torch.full((B,), INF, **f64)
        self.bound = torch.full((B,), INF, **f64)
        #: the widest side relative to the box's own widest: the score of a box no later
        #: stage bounded
        self.score = zr * (1.0 / (zr.amax(-1, keepdim=True) + 1e-300))
        self.bounded = torch.zeros(B, dtype=torch.bool, device=zr.device)
        self.vertex = torch.full((B,), float("nan"), **f64)
        self._enclosures = None

    def open(self) -> torch.Tensor:
        """The boxes [B] (bool) the screen leaves to the later stages: those whose plain bound
        is not <= `options.screen` (every box with no screen; NaN stays open)."""
        if self.options.screen is None:
            return torch.ones_like(self.bounded)
        return ~(self.plain <= self.options.screen)

    def interval_enclosures(self):
        """(centre, box) interval enclosures of the gain terms and Jf (`gain_enclosure`): at
        the centres (thin intervals) and over the boxes, second order for the mean-value
        form; computed on first use."""
        if self._enclosures is None:
            opts, b = self.options, self.boxes
            system, net = opts.problem.system, opts.problem.network
            gc, nec = gain_enclosure(system, net, b.zc, b.zc, order=1)
            order = 2 if opts.technique is Technique.MEAN_VALUE else 1
            gb, _ = gain_enclosure(system, net, b.lo, b.hi, order=order, center_pre=nec.pre)
            self._enclosures = gc, gb
        return self._enclosures

    def keep(self, stage: Stage, mask: torch.Tensor, res: StageResult) -> None:
        """Record `stage`'s result on the boxes `mask` selected (module docstring)."""
        if stage.screens:
            self.plain[mask] = res.bound
            return
        first = ~self.bounded[mask]
        kept = self.bound[mask]
        take = first | (torch.nan_to_num(res.bound, nan=INF) < kept)
        self.bound[mask] = torch.where(take, res.bound, kept)
        self.score[mask] = torch.where(take[:, None], res.score, self.score[mask])
        if res.vertex is not None:
            self.vertex[mask] = torch.where(take, res.vertex, self.vertex[mask])
        self.bounded[mask] = True


class Stage(Protocol):
    """One way of bounding max lam_max(A) over boxes (module docstring). `screens`: the
    stage's bound is the screen (`BoxState.plain`) rather than one of the later bounds."""

    name: str
    screens: bool

    def applies(self, options: BoxBoundOptions) -> bool: ...

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor: ...

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState
              ) -> StageResult: ...


def _all(state: BoxState) -> torch.Tensor:
    return torch.ones_like(state.bounded)


class PlainInterval:
    """The plain interval bound: A over the box enclosed entrywise by interval arithmetic
    (`gain_enclosure`: Jf and dk/dxhat over the box, outward rounded; `congruence`: He{Q J
    M^T} as interval products; plus the constant term's enclosure), and lam_max of the
    interval matrix bounded by `certify.arith.eigen.lam_max_upper_interval`. Sound: every
    A(z), z in the box, is a member of the interval matrix, and the bound holds for every
    member. In a decision (`options.decide`) a box that cannot be decided may get the cheaper
    Gershgorin bound instead (still a bound). Runs on every box, except where the mixed rows
    apply and the prover found the screen does not pay (`options.plain_screen`)."""

    name = "plain interval"
    screens = True

    def applies(self, options: BoxBoundOptions) -> bool:
        return options.plain_screen or not MIXED_ROWS.applies(options)

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor:
        return _all(state)

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState) -> StageResult:
        _, gb = state.interval_enclosures()
        Ab = iadd(congruence(options.pc, closed_loop_box(options.problem, gb)),
                  bcast(options.constant, len(boxes)))
        plain = lam_max_upper_interval(Ab, level=options.decide_level)
        return StageResult(plain, state.score)


class MeanValue:
    """The mean-value form (the comparison prover of `Technique.MEAN_VALUE`): A(z) = A(zc) +
    sum_m dA/dz_m(xi) (z_m - zc_m) with A(zc) enclosed by thin intervals and dA/dz_m by the
    interval second derivatives over the box (`gain_enclosure(order=2)`), bounded by
    `certify.arith.eigen.taylor_upper`. Sound by the mean-value theorem entry by entry:
    every A(z) lies in the interval family that bound covers. Every box; its own split
    score (the split rule is not applied)."""

    name = "mean-value form"
    screens = False

    def applies(self, options: BoxBoundOptions) -> bool:
        if options.technique is Technique.MEAN_VALUE and options.problem.noise is not None:
            raise ValueError("the mean-value form bounds the MPDI's matrix only (no noise "
                             "input)")
        return options.technique is Technique.MEAN_VALUE

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor:
        return _all(state)

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState) -> StageResult:
        gc, gb = state.interval_enclosures()
        pc = options.pc
        Ac = iadd(congruence(pc, iadd(gc.jf, gc.dk_dx)), bcast(options.constant, len(boxes)))
        dJ = iadd(gb.djf, gb.d2k)  # [B, n, n, d]
        dA = congruence(pc, Interval(dJ.lo.permute(0, 3, 1, 2), dJ.hi.permute(0, 3, 1, 2)))
        tay, score = taylor_upper(Ac, dA, boxes.zr)
        return StageResult(tay, score)


class TaylorModels:
    """First-order Taylor models through the network (`jcl_taylor`: J_cl(z) in c + g . (z -
    zc) + [-e, e] entrywise for every z in the box, remainders rounded up), congruence and
    constant term added exactly on (c, g) with the rest in the remainder (`tm_congruence`),
    bounded by `tm_lam_upper`: lam_max is convex, so over the box the affine part is
    largest at a vertex, and the remainder adds at most its spectral radius (Weyl). Also
    returns that vertex part alone (`StageResult.vertex`), for `LinearBounds`. On the
    boxes the screen leaves; not where the mixed rows take its place."""

    name = "Taylor models"
    screens = False

    def applies(self, options: BoxBoundOptions) -> bool:
        return (options.technique is Technique.TAYLOR
                and not (options.crown and options.mixed_rows))

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor:
        return state.open()

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState) -> StageResult:
        Jt = closed_loop_tm(options.problem, boxes.lo, boxes.hi)
        A = tm_congruence(options.pc, Jt, options.constant, boxes.zr)
        t, s, lv = tm_lam_upper(A, boxes.zr, parts=True, level=options.decide_level)
        return StageResult(t, options.split(s, boxes.zr), vertex=lv)


def linear_contraction_tm(problem: Problem, pc: Preconditioner, lo: torch.Tensor,
                          hi: torch.Tensor, r: torch.Tensor, constant: Interval) -> TM:
    """The Taylor model of A = M D M^T over boxes (radii r, rounded up) with the network's
    Jacobian (and, for a structural network, its value) from the backward linear bounds
    (`certify.enclose.crown.network_crown_tms`) in place of the forward Taylor models;
    `constant` = M (2 lam P + Q) M^T."""
    from certify.enclose.crown import network_crown_tms

    net_tms = network_crown_tms(problem.network, lo, hi, jacobian_columns(problem),
                                value=problem.structural)
    return tm_congruence(pc, closed_loop_tm(problem, lo, hi, net_tms=net_tms), constant, r)


class LinearBounds:
    """The Taylor models again with the network's parts from the backward linear bounds
    (`linear_contraction_tm`): the linear relaxations hold for every z in the box, so their
    Taylor models contain the network's value and Jacobian there, and the rest is the
    Taylor-model bound's argument. Tried only where the Taylor models left the box above
    the level while their vertex part alone would pass with a remainder `options.crown_gain`
    times smaller (every box the Taylor models bounded when there is no screen): only the
    choice of boxes depends on the gain, never a bound. Where M = I and the network is
    direct, `MixedRows` takes the place of both."""

    name = "linear bounds"
    screens = False

    def applies(self, options: BoxBoundOptions) -> bool:
        return (options.technique is Technique.TAYLOR and options.crown
                and not options.mixed_rows)

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor:
        if options.screen is None:
            return state.bounded.clone()
        idx = torch.nonzero(state.bounded).squeeze(-1)
        t, lv, wr = state.bound[idx], state.vertex[idx], state.boxes.zr[idx]
        gain = options.crown_gain
        if isinstance(gain, CrownGain):
            # the box's radius relative to the root's width (no root: the smallest scale)
            rw = options.root_width
            rel = ((wr / rw).amax(-1) if rw is not None
                   else torch.zeros(len(wr), dtype=torch.float64, device=wr.device))
            gain = gain.at(rel)
        level = options.level
        again = ~(t <= level) & (lv + (t - lv) / gain <= level)
        mask = torch.zeros_like(state.bounded)
        mask[idx[again]] = True
        return mask

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState) -> StageResult:
        A = linear_contraction_tm(options.problem, options.pc, boxes.lo, boxes.hi, boxes.zr,
                                  options.constant)
        t, s = tm_lam_upper(A, boxes.zr, level=options.decide_level)
        return StageResult(t, options.split(s, boxes.zr))


@dataclass(frozen=True)
class UpperModel:
    """A Taylor model whose members bound, in the Loewner order, every member of A + He{C
    eps} (`certify.enclose.mixed.TopLayerRemainder`: the last hidden layer's relaxation
    errors apart): `model(A, top, level)`, the weights balanced against the room below
    `level`. lam_max is monotone in the Loewner order, so an upper bound of lam_max over
    the model's family bounds A's. `applies(options, top)`: where it is used."""

    name: str
    applies: Callable[[BoxBoundOptions, TopLayerRemainder], bool]
    model: Callable[[TM, TopLayerRemainder, float], TM]


def _rank_model(A: TM, top: TopLayerRemainder, level: float) -> TM:
    return rank_loewner_upper(A, top.C, top.w, top.rank, level)


def _entrywise_model(A: TM, top: TopLayerRemainder, level: float) -> TM:
    return entrywise(A, top)


#: the errors' rank structure, known for networks with at most two hidden layers
#: (`certify.enclose.top_rank`)
RANK_STRUCTURED = UpperModel("rank structure", lambda options, top: top.rank is not None,
                             _rank_model)
#: the errors taken independent, entry by entry of eps (`certify.enclose.structured`)
INDEPENDENT = UpperModel("independent errors", lambda options, top: top.rank is None,
                         independent_upper)
#: the errors entrywise in the remainder: for n <= HERTZ_MAX_N, where Hertz's vertex bound
#: treats an entrywise remainder exactly, it can beat the matrix forms
ENTRYWISE = UpperModel("entrywise",
                       lambda options, top: options.problem.m <= HERTZ_MAX_N,
                       _entrywise_model)


class MixedRows:
    """The mixed-row linear bounds (`certify.enclose.mixed.contraction_tm_mixed`): with M = I
    and a direct network, A = He{P J} + 2 lam P (+ Q) and P dN/dx is bounded with the rows
    P mixes, the last hidden layer's relaxation errors kept apart as a matrix; the Taylor
    model holds for every z in the box (linear relaxations, rounded outward). Each upper
    model of `models` that applies gives a bound (`tm_lam_upper` on the model, as for the
    Taylor models), the smallest kept (NaN as +inf; ties to the earlier). On the boxes the
    screen leaves, or every box where the prover dropped the screen."""

    name = "mixed rows"
    screens = False
    models: tuple[UpperModel, ...] = (RANK_STRUCTURED, INDEPENDENT, ENTRYWISE)

    def applies(self, options: BoxBoundOptions) -> bool:
        return options.technique is Technique.TAYLOR and options.crown and options.mixed_rows

    def select(self, options: BoxBoundOptions, state: BoxState) -> torch.Tensor:
        return state.open()

    def bound(self, boxes: Boxes, options: BoxBoundOptions, state: BoxState) -> StageResult:
        A, top = contraction_tm_mixed(options.problem, options.pc, boxes.lo, boxes.hi,
                                      boxes.zr, options.lam, top_apart=True,
                                      constant=options.constant)
        bound = score = None
        for m in self.models:
            if not m.applies(options, top):
                continue
            b, s = tm_lam_upper(m.model(A, top, options.level), boxes.zr,
                                level=options.decide_level)
            if bound is None:
                bound, score = b, s
                continue
            use = torch.nan_to_num(b, nan=INF) < torch.nan_to_num(bound, nan=INF)
            bound = torch.where(use, b, bound)
            score = torch.where(use[:, None], s, score)
        return StageResult(bound, options.split(score, boxes.zr))


PLAIN_INTERVAL = PlainInterval()
MEAN_VALUE = MeanValue()
TAYLOR_MODELS = TaylorModels()
LINEAR_BOUNDS = LinearBounds()
MIXED_ROWS = MixedRows()

#: every stage, in the order they run
STAGES: tuple[Stage, ...] = (PLAIN_INTERVAL, MEAN_VALUE, TAYLOR_MODELS, LINEAR_BOUNDS,
                             MIXED_ROWS)


def select_stages(options: BoxBoundOptions) -> tuple[Stage, ...]:
    """The stages that apply to `options`, in the order they run (module docstring)."""
    return tuple(s for s in STAGES if s.applies(options))
