"""`forward_bounds` as `propagate` over `PairedArithmetic`: bit-identical to the hand-written
layer walk it replaced (frozen below verbatim as `_reference_forward_bounds`), for every
activation, with and without tangent columns, CROWN on and off, with and without the
composed first layer's slack; and the paired arithmetic's ranges contain sampled values."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.intervals import Interval, down, imul, matmul_point_right, midrad_to_interval, up
from certify.arith.taylor import TM, tm_linear, tm_mul, tm_rho
from certify.enclose.crown import AffineInputNetwork, ForwardBounds, forward_bounds
from certify.enclose.crown_backward import BackwardLayer, backward_pass, concretize, queries
from certify.model import activations
from certify.model.gain.taylor import tm_activation
from certify.model.network import GainNetwork

from ..soak import examples
from .test_crown import _boxes, _net, _points

F64 = torch.float64


# ---- frozen reference: the hand-written forward pass before the port (verbatim) ----
def _intersect(a: Interval, b: Interval) -> Interval:
    return Interval(torch.maximum(a.lo, b.lo), torch.minimum(a.hi, b.hi))


def _tm_range(t: TM, r: torch.Tensor) -> Interval:
    rho = tm_rho(t, r)
    return Interval(down(t.c - rho), up(t.c + rho))


def _imatvec_point(x: Interval, W: torch.Tensor) -> Interval:
    """x @ W.T for x [..., k] an interval and W [m, k] a point matrix."""
    c, r = x.midrad()
    oc, orr = matmul_point_right(c, r, W.T)
    return midrad_to_interval(oc, orr)



def _reference_forward_bounds(net: GainNetwork | AffineInputNetwork, lo: torch.Tensor,
                              hi: torch.Tensor, cols: list[int] | None = None, crown: bool = True,
                   b0_slack: torch.Tensor | None = None) -> ForwardBounds:
    """Ranges of every pre-activation and tangent: interval propagation of the intersected
    ranges, intersected with the Taylor-model ranges and (crown) with backward linear bounds
    of pre_l and of the tangent columns `cols` (default all; [] for value-only), layer by
    layer. b0_slack [B, h0]: a bound on |pre_0 - (W_0 z + b_0)| (a composed first layer)."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    colt = torch.arange(d) if cols is None else torch.as_tensor(cols, dtype=torch.long)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    zmag = torch.maximum(lo.abs(), hi.abs())
    weights = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
    act = net.act
    W0, b0 = weights[0]
    eye = torch.eye(d, dtype=torch.float64).expand(B, d, d)
    val = tm_linear(TM(zc, eye, torch.zeros_like(zc)), W0.T, b0, r)  # [B, h]
    if b0_slack is not None:
        val = TM(val.c, val.g, up(val.e + b0_slack))
    h0 = W0.shape[0]
    T = TM(W0.T.expand(B, d, h0), torch.zeros(B, d, h0, d, dtype=torch.float64),
           torch.zeros(B, d, h0, dtype=torch.float64))
    pre_iv = _tm_range(val, r)
    tan_iv = Interval(W0.expand(B, h0, d), W0.expand(B, h0, d))  # [B, h, d]
    pres, tans = [], []
    layers: list[BackwardLayer] = []
    for L, (W, b) in enumerate(weights[1:], start=1):
        pres.append(pre_iv)
        tans.append(tan_iv)
        Win, bin_ = weights[L - 1]
        layers.append(BackwardLayer(pre_iv, tan_iv, Win, bin_, layers[-1] if layers else None, zmag,
                             act))
        if L == 1 and b0_slack is not None:
            layers[0].bslack = b0_slack[:, None, None, :]
        a, s = tm_activation(act, val, r)
        s_b = TM(s.c.unsqueeze(1), s.g.unsqueeze(1), s.e.unsqueeze(1))
        Tn = tm_mul(s_b, T, r)  # [B, d, h]
        val = tm_linear(a, W.T, b, r)
        T = tm_linear(Tn, W.T, None, r)
        if L == len(weights) - 1:
            break
        # interval step from the intersected ranges, then intersect with the TM ranges
        lay = layers[-1]
        a_iv = act.enclose_f(pre_iv)
        q_iv = imul(Interval(lay.s.lo.unsqueeze(-1), lay.s.hi.unsqueeze(-1)), tan_iv)
        nxt = _imatvec_point(a_iv, W)
        pre_iv = _intersect(Interval(down(nxt.lo + b), up(nxt.hi + b)), _tm_range(val, r))
        qt = Interval(q_iv.lo.transpose(1, 2), q_iv.hi.transpose(1, 2))  # [B, d, h]
        tcur = _intersect(_imatvec_point(qt, W), _tm_range(T, r))  # [B, d, m]
        tan_iv = Interval(tcur.lo.transpose(1, 2), tcur.hi.transpose(1, 2))
        if crown:
            m = W.shape[0]
            tangents = len(colt) > 0
            # value queries on pre_L = W_L[i] a_{L-1} + b_L[i] (both sides in one pass)
            La = queries(W, 1, B)
            bias = b[None, :, None].expand(B, m, 1)
            lowv, highv = concretize(*backward_pass(layers, L, La, None, bias, colt[:1], lo, hi),
                                      r)
            pre_iv = Interval(torch.maximum(pre_iv.lo, lowv[..., 0]),
                              torch.minimum(pre_iv.hi, highv[..., 0]))
            if not tangents:
                continue
            # tangent queries on t_L^j = W_L[i] Q_{L-1}^j
            LQ = queries(W, len(colt), B)
            zero = torch.zeros(B, m, len(colt), dtype=torch.float64)
            lowt, hight = concretize(*backward_pass(layers, L, None, LQ, zero, colt, lo, hi), r)
            tl, th = tan_iv.lo.clone(), tan_iv.hi.clone()
            tl[..., colt] = torch.maximum(tl[..., colt], lowt)
            th[..., colt] = torch.minimum(th[..., colt], hight)
            tan_iv = Interval(tl, th)
    jac = TM(T.c.transpose(1, 2), T.g.transpose(1, 2), T.e.transpose(1, 2))  # [B, out, d]
    return ForwardBounds(pres, tans, val, jac, r, layers)



# ---- comparison ----
def _same_iv(a: Interval, b: Interval) -> bool:
    return torch.equal(a.lo, b.lo) and torch.equal(a.hi, b.hi)


def _same_tm(a: TM, b: TM) -> bool:
    return torch.equal(a.c, b.c) and torch.equal(a.g, b.g) and torch.equal(a.e, b.e)


def _assert_identical(new: ForwardBounds, ref: ForwardBounds) -> None:
    assert len(new.pre) == len(ref.pre) and len(new.tan) == len(ref.tan)
    assert all(_same_iv(a, b) for a, b in zip(new.pre, ref.pre))
    assert all(_same_iv(a, b) for a, b in zip(new.tan, ref.tan))
    assert _same_tm(new.value_tm, ref.value_tm)
    assert _same_tm(new.jac_tm, ref.jac_tm)
    assert torch.equal(new.r, ref.r)
    assert len(new.layers) == len(ref.layers)
    for a, b in zip(new.layers, ref.layers):
        assert _same_iv(a.pre, b.pre) and _same_iv(a.tan, b.tan) and _same_iv(a.s, b.s)
        assert torch.equal(a.W, b.W) and torch.equal(a.b, b.b)
        assert torch.equal(a.wk_a, b.wk_a) and torch.equal(a.Wx, b.Wx)
        assert (a.bslack is None) == (b.bslack is None)
        if a.bslack is not None:
            assert torch.equal(a.bslack, b.bslack)
        assert (a.prev is None) == (b.prev is None)


@pytest.mark.parametrize("act", activations.names())
@pytest.mark.parametrize("cols", [None, [1], []])
@pytest.mark.parametrize("crown", [True, False])
@pytest.mark.slow
def test_forward_bounds_bit_identical(act: str, cols: list[int] | None, crown: bool) -> None:
    net = _net(3, 4, 3, 6, 1.5, act)
    lo, hi = _boxes(5, 5, 4, 0.2)
    new = forward_bounds(net, lo, hi, cols=cols, crown=crown, closed_form=False)  # as ref
    ref = _reference_forward_bounds(net, lo, hi, cols=cols, crown=crown)
    _assert_identical(new, ref)
    if cols != []:  # the backward pass on the recorded layers gives the same Jacobian bounds
        c = [0, 1, 2, 3] if cols is None else cols
        WH = net.weights()[-1][0].to(F64)
        LQ = queries(WH, len(c), lo.shape[0])
        zero = torch.zeros(lo.shape[0], WH.shape[0], len(c), dtype=F64)
        ct = torch.as_tensor(c)
        a = concretize(*backward_pass(new.layers, len(new.layers), None, LQ, zero, ct, lo, hi),
                        new.r)
        b = concretize(*backward_pass(ref.layers, len(ref.layers), None, LQ, zero, ct, lo, hi),
                        ref.r)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


@pytest.mark.parametrize("act", ["tanh", "softplus", "gelu"])
@pytest.mark.parametrize("cols", [None, []])
def test_forward_bounds_bit_identical_composed_first_layer(act: str, cols: list[int] | None
                                                           ) -> None:
    """The composed network z -> N(A x + a) with the first layer's rounding slack b0_slack."""
    net = _net(7, 4, 2, 5, 1.2, act)
    gen = torch.Generator().manual_seed(11)
    A = torch.randn(4, 2, generator=gen, dtype=F64)
    a = torch.randn(4, generator=gen, dtype=F64)
    comp = AffineInputNetwork(net, A, a)
    lo, hi = _boxes(9, 4, 2, 0.3)
    slack = comp.first_layer_slack(lo, hi)
    for crown in (True, False):
        new = forward_bounds(comp, lo, hi, cols=cols, crown=crown, b0_slack=slack,
                             closed_form=False)
        ref = _reference_forward_bounds(comp, lo, hi, cols=cols, crown=crown, b0_slack=slack)
        _assert_identical(new, ref)
        assert new.layers[0].bslack is not None


@settings(max_examples=examples(16), deadline=None)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       scale=st.sampled_from([0.01, 0.1, 0.5]), crown=st.booleans(), taylor=st.booleans(),
       cols=st.sampled_from([None, [0, 1], [2]]))
@pytest.mark.slow
def test_forward_ranges_contain_sampled_values(seed: int, act: str, scale: float,
                                               crown: bool, taylor: bool,
                                               cols: list[int] | None) -> None:
    """Every recorded range of pre_l and t_l = d pre_l / dz contains the float64 values at
    sampled points of the box (`propagate` over `PairedArithmetic` alone, or with the CROWN
    queries of the layer hook; without Taylor models, over `IntervalArithmetic` with the
    queries), for all tangent columns, queried or not."""
    net = _net(seed, 3, 2, 5, 1.5, act)
    lo, hi = _boxes(seed, 3, 3, scale)
    fb = forward_bounds(net, lo, hi, cols=cols, crown=crown, taylor=taylor)
    assert (fb.jac_tm is None) == (crown and not taylor)
    B, S = lo.shape[0], 16
    x = _points(lo, hi, S, seed).reshape(B * S, 3)
    ws = [(W.to(F64), b.to(F64)) for W, b in net.weights()]
    f = net.act
    tang = ws[0][0].expand(B * S, *ws[0][0].shape)  # t_0 = W_0, [BS, h, d]
    for li, (pre_iv, tan_iv) in enumerate(zip(fb.pre, fb.tan)):
        W, b = ws[li]
        pre = x @ W.T + b
        if li > 0:
            tang = torch.einsum("kh,bhd->bkd", W, tang)
        pre_b = pre.reshape(B, S, -1)
        tan_b = tang.reshape(B, S, *tang.shape[1:])
        tol = 1e-12 * (1 + pre_b.abs())  # the float64 samples' own rounding
        assert bool(((pre_iv.lo[:, None] <= pre_b + tol)
                     & (pre_b - tol <= pre_iv.hi[:, None])).all())
        tt = 1e-12 * (1 + tan_b.abs())
        assert bool(((tan_iv.lo[:, None] <= tan_b + tt)
                     & (tan_b - tt <= tan_iv.hi[:, None])).all())
        assert bool((pre_iv.lo <= pre_iv.hi).all()) and bool((tan_iv.lo <= tan_iv.hi).all())
        x = f.f(pre)
        tang = f.d1(pre)[..., None] * tang


@pytest.mark.parametrize("act", activations.names())
def test_ranges_without_taylor_models_are_as_tight_as_with_them(act: str) -> None:
    """The ranges without Taylor models (the mixed-row prover's) lose almost nothing: on a
    g = 2 network and boxes of radius 0.05, each queried range is at most 5% wider than the
    paired (Taylor + interval + CROWN) one in the median, and pre_0 is identical."""
    net = _net(3, 3, 2, 8, 2.0, act)
    lo, hi = _boxes(3, 32, 3, 0.05)
    lo, hi = lo[1:], hi[1:]  # not the degenerate box
    both = forward_bounds(net, lo, hi, cols=[0, 1])
    ivl = forward_bounds(net, lo, hi, cols=[0, 1], taylor=False)
    for li in range(1, len(both.pre)):
        wb = both.pre[li].hi - both.pre[li].lo
        wi = ivl.pre[li].hi - ivl.pre[li].lo
        assert float((wi / wb).median()) <= 1.05
        tb = both.tan[li].hi[..., :2] - both.tan[li].lo[..., :2]
        ti = ivl.tan[li].hi[..., :2] - ivl.tan[li].lo[..., :2]
        assert float((ti / tb).median()) <= 1.05


@settings(max_examples=examples(12), deadline=None)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       scale=st.sampled_from([0.0, 1e-3, 0.1, 0.5]), depth=st.integers(2, 3),
       cols=st.sampled_from([None, [0, 2], []]))
@pytest.mark.slow
def test_second_layer_closed_form_matches_the_backward_pass(seed: int, act: str, scale: float,
                                                            depth: int,
                                                            cols: list[int] | None) -> None:
    """The second layer's ranges from `certify.enclose.one_layer` (the default) and from the
    general backward pass: the same linear functions, so equal up to their rounding slack
    (within 1e-9 of the width, plus 1e-12), for every activation and depth; that they contain
    sampled values is `test_forward_ranges_contain_sampled_values`'s."""
    net = _net(seed, 3, depth, 5, 2.0, act)
    lo, hi = _boxes(seed, 6, 3, scale)
    closed = forward_bounds(net, lo, hi, cols=cols, crown=True, taylor=False)
    general = forward_bounds(net, lo, hi, cols=cols, crown=True, taylor=False,
                             closed_form=False)
    for a, b in ((closed.pre[1], general.pre[1]), (closed.tan[1], general.tan[1])):
        tol = 1e-9 * (b.hi - b.lo) + 1e-12 * (1 + b.lo.abs() + b.hi.abs())
        assert bool(((a.lo - b.lo).abs() <= tol).all()), float((a.lo - b.lo).abs().max())
        assert bool(((a.hi - b.hi).abs() <= tol).all()), float((a.hi - b.hi).abs().max())
