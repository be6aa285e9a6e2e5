"""CROWN-style bounds of the network's value and Jacobian: the forward ranges and the entry points.

`forward_bounds` computes the intermediate ranges the backward pass relaxes on (pre_l and
the tangents t_l = d pre_l / dz): `certify.model.gain.propagate` over `PairedArithmetic` (a
first-order Taylor model and an interval per value), whose `layer_hook` here, per hidden
layer, intersects the interval with the Taylor model's range, tightens pre_l and the
tangent columns by backward CROWN queries on the layers below (`certify.enclose.
crown_backward`), and records the layer's relaxations (`BackwardLayer`). `jacobian_crown` and
`value_crown` run the backward pass from the output; `network_crown_tms` turns their lines
into Taylor models (`to_tm`) and keeps the tighter one per entry.

Rounding: the ranges are `PairedArithmetic`'s (outward, see there) and the backward pass's
(slack folded in, see `crown_backward`); `to_tm` computes the remainder of the Taylor model
holding both lines with upward rounding; the composed first layer of `AffineInputNetwork`
carries its product's rounding as `first_layer_slack`, added to pre_0's remainder.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from certify.arith.intervals import TINY, Interval, down, gamma, up
from certify.arith.taylor import TM
from certify.enclose.crown_backward import BackwardLayer, U, backward_pass, concretize, queries
from certify.enclose.one_layer import second_layer_ranges
from certify.model.gain import GainSpec, propagate
from certify.model.gain.interval import IntervalArithmetic
from certify.model.gain.paired import Paired, PairedArithmetic
from certify.model.network import GainNetwork


@dataclass
class ForwardBounds:
    """Per hidden layer l: ranges of pre_l [B, h] and of t_l = d pre_l / dz [B, h, d]; the
    Taylor models of the output value [B, out] and Jacobian [B, out, d]; box radii [B, d]."""

    pre: list[Interval]
    tan: list[Interval]
    value_tm: TM | None  # None when no Taylor models were propagated (taylor=False)
    jac_tm: TM | None
    r: torch.Tensor
    layers: list = field(default_factory=list)  # BackwardLayer per hidden layer (relaxations)


@dataclass
class LinearEnclosure:
    """For every z in the box: gl . (z - zc) + cl <= F(z) <= gu . (z - zc) + cu (real
    arithmetic; shapes [B, ...] for c, [B, ..., d] for g)."""

    gl: torch.Tensor
    cl: torch.Tensor
    gu: torch.Tensor
    cu: torch.Tensor



class _ForwardRanges:
    """The `layer_hook` of `forward_bounds`: per hidden layer l, the ranges of pre_l and
    t_l (interval meet Taylor range, then the CROWN queries; without Taylor models the
    interval step meet the CROWN queries), recorded with their `BackwardLayer`. `closed_form`:
    the second layer's queries in closed form where `closed_form_applies`."""

    def __init__(self, arith: PairedArithmetic | IntervalArithmetic, spec: GainSpec,
                 lo: torch.Tensor, hi: torch.Tensor, colt: torch.Tensor, crown: bool,
                 b0_slack: torch.Tensor | None, closed_form: bool = True) -> None:
        self.arith, self.spec, self.lo, self.hi = arith, spec, lo, hi
        self.r = arith.r if isinstance(arith, PairedArithmetic) else arith.zr
        self.colt, self.crown, self.b0_slack = colt, crown, b0_slack
        self.closed_form = closed_form
        self.zmag = torch.maximum(lo.abs(), hi.abs())
        self.pres: list[Interval] = []
        self.tans: list[Interval] = []
        self.layers: list[BackwardLayer] = []

    def __call__(self, li: int, pre: Paired | Interval, T: Paired | Interval
                 ) -> tuple[Paired | Interval, Paired | Interval]:
        """Values are `Paired` (Taylor model + interval) or, without Taylor models
        (`forward_bounds(taylor=False)`), plain `Interval`s."""
        paired = isinstance(pre, Paired)
        if li == 0:
            if self.b0_slack is not None:  # the composed first layer's rounding
                if paired:
                    pre = Paired(TM(pre.tm.c, pre.tm.g, up(pre.tm.e + self.b0_slack)), None)
                else:
                    pre = Interval(down(pre.lo - self.b0_slack), up(pre.hi + self.b0_slack))
            if paired:  # pre_0 is affine: its TM range; t_0 = W_0 exact
                pre = self.arith.intersect(pre)
        else:
            if paired:
                pre, T = self.arith.intersect(pre), self.arith.intersect(T)
            if self.crown:
                pre, T = self._crown(li, pre, T)
        piv, tiv = (pre.iv, T.iv) if paired else (pre, T)
        tan = Interval(tiv.lo.transpose(1, 2), tiv.hi.transpose(1, 2))  # [B, h, d]
        self.pres.append(piv)
        self.tans.append(tan)
        W, b = self.spec.layers[li]
        self.layers.append(BackwardLayer(piv, tan, W, b, self.layers[-1] if self.layers else None,
                                  self.zmag, self.spec.activation))
        if li == 0 and self.b0_slack is not None:
            self.layers[0].bslack = self.b0_slack[:, None, None, :]
        return pre, T

    def _crown(self, li: int, pre: Paired | Interval, T: Paired | Interval
               ) -> tuple[Paired | Interval, Paired | Interval]:
        """pre_li and t_li[:, :, cols] narrowed by backward queries on the layers below."""
        W, b = self.spec.layers[li]
        lo, hi, colt, r = self.lo, self.hi, self.colt, self.r
        B, m = lo.shape[0], W.shape[0]
        paired = isinstance(pre, Paired)
        piv, tiv = (pre.iv, T.iv) if paired else (pre, T)
        if self.closed_form and closed_form_applies(li, self.layers):
            lowv, highv, lowt, hight = second_layer_ranges(self.layers[0], W, b, colt,
                                                           0.5 * (lo + hi), r)
        else:
            # value queries on pre_L = W_L[i] a_{L-1} + b_L[i] (both sides in one pass)
            bias = b[None, :, None].expand(B, m, 1)
            lowv, highv = concretize(*backward_pass(self.layers, li, queries(W, 1, B), None,
                                                 bias, colt[:1], lo, hi), r)
            lowv, highv = lowv[..., 0], highv[..., 0]
            lowt = hight = None
            if len(colt) > 0:
                # tangent queries on t_L^j = W_L[i] Q_{L-1}^j, rows [B, m, J] here
                zero = torch.zeros(B, m, len(colt), dtype=torch.float64, device=lo.device)
                lowt, hight = concretize(*backward_pass(self.layers, li, None,
                                                     queries(W, len(colt), B), zero, colt,
                                                     lo, hi), r)
        piv = Interval(torch.maximum(piv.lo, lowv), torch.minimum(piv.hi, highv))
        if len(colt) > 0:
            tl, th = tiv.lo.clone(), tiv.hi.clone()
            tl[:, colt] = torch.maximum(tl[:, colt], lowt.transpose(1, 2))
            th[:, colt] = torch.minimum(th[:, colt], hight.transpose(1, 2))
            tiv = Interval(tl, th)
        if paired:
            return Paired(pre.tm, piv), Paired(T.tm, tiv)
        return piv, tiv


def closed_form_applies(li: int, layers: list) -> bool:
    """Whether hidden layer `li`'s queries have the closed form of `certify.enclose.one_layer`
    (the same linear functions as the general backward pass, from a few batched products):
    the second hidden layer, over a first layer that is not composed (no `bslack`)."""
    return li == 1 and layers[0].bslack is None


def forward_bounds(net: GainNetwork | AffineInputNetwork, lo: torch.Tensor, hi: torch.Tensor,
                   cols: list[int] | None = None, crown: bool = True,
                   b0_slack: torch.Tensor | None = None, taylor: bool = True,
                   closed_form: bool = True) -> ForwardBounds:
    """Ranges of every pre-activation and tangent: interval propagation of the intersected
    ranges, intersected with the Taylor-model ranges and (crown) with backward linear bounds
    of pre_l and of the tangent columns `cols` (default all; [] for value-only), layer by
    layer. b0_slack [B, h0]: a bound on |pre_0 - (W_0 z + b_0)| (a composed first layer).

    taylor=False (with crown): no Taylor models are propagated (value_tm and jac_tm are
    None); the ranges are the backward bounds met with the interval step from the layer
    below. On the benchmark families (`bench/instances.py`) the backward bounds alone were
    the tightest range of nearly every pre-activation and queried tangent column, and the
    Taylor models the forward pass's largest cost (whole proofs: `bench/prove_suite.py`).

    closed_form=False: the second layer's queries by the general backward pass too, where
    `closed_form_applies` would take the closed form (the two agree up to rounding; the
    tests compare them)."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    colt = (torch.arange(d, device=lo.device) if cols is None
            else torch.as_tensor(cols, dtype=torch.long, device=lo.device))
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    spec = net.spec(torch.float64)
    paired = taylor or not crown  # without the queries the Taylor ranges are needed
    arith = (PairedArithmetic(zc, r, len(spec.layers) - 1) if paired
             else IntervalArithmetic(zc, r))
    ranges = _ForwardRanges(arith, spec, lo, hi, colt, crown, b0_slack, closed_form)
    out = propagate(spec, arith, None, d, layer_hook=ranges)
    return ForwardBounds(ranges.pres, ranges.tans, out.value if paired else None,
                         out.jac if paired else None, r, ranges.layers)


def jacobian_crown(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, cols: list[int],
                   fb: ForwardBounds) -> LinearEnclosure:
    """Linear lower/upper bounds of dN_i/dz_j over each box, i < out, j in cols -> [B, out, J]."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    WH = net.weights()[-1][0].to(torch.float64)
    out = WH.shape[0]
    colt = torch.as_tensor(cols, dtype=torch.long, device=lo.device)
    J = len(cols)
    LQ = queries(WH, J, B)
    Lz, cl, cu = backward_pass(fb.layers, len(fb.layers), None, LQ,
                           torch.zeros(B, out, J, dtype=torch.float64, device=lo.device), colt,
                           lo, hi)
    return LinearEnclosure(gl=Lz, cl=cl, gu=Lz, cu=cu)


def value_crown(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, fb: ForwardBounds
                ) -> LinearEnclosure:
    """Linear lower/upper bounds of the network output N(z) over each box -> [B, out]."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    WH, bH = (x.to(torch.float64) for x in net.weights()[-1])
    out = WH.shape[0]
    La = queries(WH, 1, B)
    bias = bH[None, :, None].expand(B, out, 1)
    Lz, cl, cu = backward_pass(fb.layers, len(fb.layers), La, None, bias,
                           torch.zeros(1, dtype=torch.long, device=lo.device), lo, hi)
    return LinearEnclosure(gl=Lz[..., 0, :], cl=cl[..., 0], gu=Lz[..., 0, :], cu=cu[..., 0])


def network_crown_tms(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, cols: list[int],
                      value: bool = False, crown_intermediate: bool = True
                      ) -> tuple[TM | None, TM, torch.Tensor]:
    """(value TM [B, out] or None, Jacobian TM [B, out, d], radii) from the linear bound
    propagation: the Jacobian columns `cols` (and the value, when asked) as the linear
    bounds' Taylor models.

    With `crown_intermediate` (the default) no forward Taylor models are propagated
    (`forward_bounds(taylor=False)`): met with the linear bounds they changed the MPDI
    bounds only in the last bits and cost a noticeable share of the proofs
    (`bench/prove_suite.py`, `bench/run.py`). The columns
    outside `cols` then carry NaN remainders: a bound that reads them is NaN and closes no
    box. Without it the forward Taylor models are the ranges, kept where they are tighter."""
    if crown_intermediate:
        fb = forward_bounds(net, lo, hi, cols=cols, crown=True, taylor=False)
        jt = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r)  # [B, out, J]
        B, out, _ = jt.c.shape
        d = lo.shape[1]
        colt = torch.as_tensor(cols, dtype=torch.long, device=lo.device)
        c = torch.zeros(B, out, d, dtype=torch.float64, device=lo.device)
        g = torch.zeros(B, out, d, d, dtype=torch.float64, device=lo.device)
        e = torch.full((B, out, d), float("nan"), dtype=torch.float64, device=lo.device)
        c[..., colt], g[..., colt, :], e[..., colt] = jt.c, jt.g, jt.e
        val = to_tm(value_crown(net, lo, hi, fb), fb.r) if value else None
        return val, TM(c, g, e), fb.r
    fb = forward_bounds(net, lo, hi, cols=cols, crown=False)
    jt = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r)  # [B, out, J]
    colt = torch.as_tensor(cols, dtype=torch.long, device=lo.device)
    base = fb.jac_tm
    sub = TM(base.c[..., colt], base.g[..., colt, :], base.e[..., colt])
    best = tm_tighter(sub, jt)
    c, g, e = base.c.clone(), base.g.clone(), base.e.clone()
    c[..., colt], g[..., colt, :], e[..., colt] = best.c, best.g, best.e
    val = fb.value_tm
    if value:
        val = tm_tighter(val, to_tm(value_crown(net, lo, hi, fb), fb.r))
    return val, TM(c, g, e), fb.r


class AffineInputNetwork:
    """The network z -> N(A x + a) as a network in x (first layer W_0 A, b_0 + W_0 a), for
    the bounds of k(x, h(x)) with linear h: z = (x, C x). Weights in float64; W_0 A is a
    float product, so the composed network differs from the exact one by rounding: callers
    add `input_rounding_slack` (see there)."""

    def __init__(self, net: GainNetwork, A: torch.Tensor, a: torch.Tensor) -> None:
        ws = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
        self.act = net.act
        W0, b0 = ws[0]
        self.W0_exact, self.A, self.a = W0, A.to(torch.float64), a.to(torch.float64)
        self._weights = [(W0 @ self.A, b0 + W0 @ self.a)] + ws[1:]

    def weights(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return self._weights

    def first_layer_slack(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """Bound on |(W0 A) x + (b0 + W0 a) - (W0 (A x + a) + b0)| over the boxes [B, h0]:
        gamma_k (|W0| |A| |x| + |W0| |a| + |b0|) with k the inner dimensions."""
        xm = torch.maximum(lo.abs(), hi.abs()).to(torch.float64)
        k = self.A.shape[0] + 2
        W0a = self.W0_exact.abs()
        inner = xm @ (W0a @ self.A.abs()).T + (W0a @ self.a.abs())
        return up(gamma(k + 2) * 2.0 * (inner + self._weights[0][1].abs()) * (1 + 4 * U) + TINY)

    def spec(self, dtype: torch.dtype | None = None) -> GainSpec:
        """The composed MLP for `propagate` (float64; `dtype` is accepted for the
        `GainNetwork.spec` signature): its output as a `direct` gain with n = out, p = 0."""
        W_out = self._weights[-1][0]
        return GainSpec(W_out.shape[0], 0, tuple(self._weights), self.act, "direct",
                        torch.zeros(W_out.shape[0], 0, dtype=torch.float64, device=W_out.device))


def to_tm(le: LinearEnclosure, r: torch.Tensor) -> TM:
    """The Taylor model c + g . dz + [-e, e] containing both lines over |dz| <= r."""
    c = 0.5 * (le.cl + le.cu)
    g = 0.5 * (le.gl + le.gu)
    rr = r.reshape(r.shape[0], *([1] * (g.ndim - 2)), r.shape[1])
    d = g.shape[-1]
    k = gamma(d + 4)
    e_up = up(up(le.cu - c) + up((le.gu - g).abs() * rr).sum(-1) * (1.0 + k))
    e_lo = up(up(c - le.cl) + up((g - le.gl).abs() * rr).sum(-1) * (1.0 + k))
    e = up(torch.maximum(e_up, e_lo) * (1.0 + k) + d * TINY)
    bad = ~(torch.isfinite(e) & torch.isfinite(c))
    e = torch.where(bad, torch.full_like(e, float("nan")), e)
    return TM(c, g, e)


def tm_tighter(a: TM, b: TM) -> TM:
    """Per entry, the Taylor model with the smaller remainder (both contain the function)."""
    use_b = torch.nan_to_num(b.e, nan=float("inf")) < a.e
    return TM(torch.where(use_b, b.c, a.c), torch.where(use_b[..., None], b.g, a.g),
              torch.where(use_b, b.e, a.e))


# backward_pass, queries: the backward pass, re-exported for `certify.enclose.mixed`
__all__ = ["AffineInputNetwork", "ForwardBounds", "LinearEnclosure", "backward_pass", "queries",
           "forward_bounds", "jacobian_crown", "network_crown_tms", "tm_tighter", "to_tm",
           "value_crown"]
