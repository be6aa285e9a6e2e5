"""Backward linear bound propagation (CROWN-style) through the network's Jacobian graph.

For a `direct` MLP N(z) with activation f (pre_0 = W_0 z + b_0, a_l = f(pre_l), pre_{l+1} =
W_{l+1} a_l + b_{l+1}) the Jacobian columns follow t_0^j = W_0[:, j], Q_l^j = s_l * t_l^j with
s_l = f'(pre_l), t_{l+1}^j = W_{l+1} Q_l^j and dN/dz_j = W_H Q_{H-1}^j. For every entry
(i, j) and both signs, one backward pass from the output to z composes

- McCormick planes for the products Q = s * t (`relax.mccormick`),
- linear relaxations of f' (derivative path) and f (value path) (`relax.relax_slope`,
  `relax.relax_value`: tanh's own, else the activation's generic parallel lines),
- the exact linear maps W_l,

picking each relaxation's lower or upper plane by the sign of its backward coefficient, and
ends with a linear function of z that bounds the entry on the whole box. Intermediate bounds
(ranges of pre_l and t_l) come from a forward pass that intersects plain interval propagation
with first-order Taylor models (`certify.bounds.taylor`).

Rounding: the backward coefficients are computed in float64 and used as the (exactly
representable) coefficients of the relaxation; what float evaluation changes is accounted for
by a slack added to each query: every matrix product contributes gamma_k (|Lambda| |W|) . mag(x),
every elementwise product u |Lambda a| . mag(x), every sum of bias terms gamma_k sum|terms|,
with mag(x) the magnitude bound of the node the coefficients multiply (from the forward
ranges). The slack is rounded up and subtracted; the resulting lines are then turned into a
Taylor model whose remainder is computed with upward rounding (`to_tm`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from certify.activations import Activation
from certify.bounds.relax import mccormick, relax_slope, relax_value
from certify.bounds.taylor import TM, tm_activation, tm_linear, tm_mul, tm_rho
from certify.intervals import (
    TINY,
    Interval,
    down,
    gamma,
    imul,
    matmul_point_right,
    midrad_to_interval,
    up,
)
from certify.network import GainNetwork

U = 2.0**-53


@dataclass
class ForwardBounds:
    """Per hidden layer l: ranges of pre_l [B, h] and of t_l = d pre_l / dz [B, h, d]; the
    Taylor models of the output value [B, out] and Jacobian [B, out, d]; box radii [B, d]."""

    pre: list[Interval]
    tan: list[Interval]
    value_tm: TM
    jac_tm: TM
    r: torch.Tensor
    layers: list = field(default_factory=list)  # _Layer per hidden layer (relaxations)


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


@dataclass
class LinearEnclosure:
    """For every z in the box: gl . (z - zc) + cl <= F(z) <= gu . (z - zc) + cu (real
    arithmetic; shapes [B, ...] for c, [B, ..., d] for g)."""

    gl: torch.Tensor
    cl: torch.Tensor
    gu: torch.Tensor
    cu: torch.Tensor


def _acc(coef_abs: torch.Tensor, mag: torch.Tensor | float, k: int) -> torch.Tensor:
    """gamma_k sum(coef_abs * mag) over the last dim (a float error bound), rounded up."""
    return up(gamma(k + 2) * (coef_abs * mag).sum(-1) * (1.0 + 4 * U) + TINY)


def _mag(iv: Interval) -> torch.Tensor:
    return torch.maximum(iv.lo.abs(), iv.hi.abs())


def _midrad_icpt(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """m, w with [lo, hi] inside [m - w, m + w] (w rounded up)."""
    m = 0.5 * (lo + hi)
    return m, up(torch.maximum(hi - m, m - lo))


class _Layer:
    """Hidden layer l: pre_l = W x + b (x = a_{l-1}, or z for l = 0), with parallel-line
    relaxations of f (value path) and f' (derivative path) on the range of pre_l, and
    the constants the backward passes need, shaped [B, 1, J, h] for broadcasting against
    coefficients [B, R, J, h] (R query rows, J Jacobian columns).

    A relaxation is stored as f(x) in a x + m + [-w, w]; the lines of `relax` are parallel
    (both sides share the chord slope), so a backward coefficient L picks its side with
    L m - |L| w. K_a, K_Q collect, per unit of |coefficient|, every magnitude whose product
    with a coefficient is rounded in the pass; the rounding slack gamma_{2h+8} |L| . K is
    folded into the intercept radius (w + gamma K), so the pass needs no separate sum."""

    def __init__(self, pre: Interval, tan: Interval, W: torch.Tensor, b: torch.Tensor,
                 prev: _Layer | None, zmag: torch.Tensor, act: Activation) -> None:
        self.pre, self.tan, self.W, self.b, self.prev = pre, tan, W, b, prev
        self.act = act
        self.s = act.enclose_d1(pre)
        ra = relax_value(act, pre.lo, pre.hi)
        if not torch.equal(ra.lower_slope, ra.upper_slope):
            raise ValueError("backward propagation needs parallel-line relaxations")
        e = lambda x: x[:, None, None, :]  # noqa: E731  [B, h] -> [B, 1, 1, h]
        self.a_s = self.m_s = self.w_s = None  # f' relaxation: on first use (col_consts)
        self.a_a = e(ra.lower_slope)
        ma, wa = _midrad_icpt(ra.lower_icpt, ra.upper_icpt)
        self.m_a, self.w_a = e(ma), e(wa)
        self.pmag = e(_mag(pre))
        self.amag = act.enclose_f(pre).mag()  # [B, h]
        xmag = zmag if prev is None else prev.amag  # |x| feeding this layer
        self.Wx = e(xmag @ W.abs().T)  # |W| |x|: rounding of L @ W
        babs = b.abs()[None, None, None]
        K_a = 2 * self.a_a.abs() * self.pmag + self.m_a.abs() + self.w_a \
            + self.a_a.abs() * (babs + self.Wx)
        h = pre.lo.shape[-1]
        self.gk = gamma(2 * h + 8)
        # intercept radius with the rounding slack folded in: L m - |L| (w + gamma K)
        self.wk_a = up(self.w_a + self.gk * up(K_a * (1 + 8 * U)))
        self._cols: dict[tuple[int, ...], tuple] = {}
        self.bslack: torch.Tensor | None = None  # |pre - (W x + b)| (composed first layers)

    def _smag(self) -> torch.Tensor | float:
        """1 for tanh (|tanh'| <= 1 and the slope |a_s| <= 1 of its relaxation); else the
        largest of 1, |f'| over the range of pre and |a_s| (what the 1 stands for, and 1)."""
        if self.act.name == "tanh":
            return 1
        return torch.maximum(self.s.mag()[:, None, None, :], self.a_s.abs()).clamp_min(1.0)

    def qmag(self, cols: torch.Tensor) -> torch.Tensor:
        """|Q_l^j| <= |s_l| |t_l^j|, [B, h, J]."""
        return self.s.mag().unsqueeze(-1) * _mag(self.tan)[..., cols]

    def col_consts(self, cols: torch.Tensor) -> tuple:
        """(st, SA, MQ, WKQ), each [B, 1, J, h], for the McCormick planes of s * t^j: the
        slope on t, the slope on pre through s, the intercept midpoint and its radius with the
        rounding slack gamma K_Q folded in."""
        key = tuple(int(c) for c in cols)
        if self.a_s is None:
            rs = relax_slope(self.act, self.pre.lo, self.pre.hi)
            if not torch.equal(rs.lower_slope, rs.upper_slope):
                raise ValueError("backward propagation needs parallel-line relaxations")
            self.a_s = rs.lower_slope[:, None, None, :]
            ms, ws = _midrad_icpt(rs.lower_icpt, rs.upper_icpt)
            self.m_s, self.w_s = ms[:, None, None, :], ws[:, None, None, :]
        if key not in self._cols:
            t = Interval(self.tan.lo[..., cols], self.tan.hi[..., cols])
            m = mccormick(Interval(self.s.lo.unsqueeze(-1), self.s.hi.unsqueeze(-1)), t)
            f = lambda x: x.transpose(1, 2).unsqueeze(1)  # noqa: E731  [B, h, J] -> [B,1,J,h]
            mq, wq = _midrad_icpt(m.lower_icpt, m.upper_icpt)
            ss = f(m.slope_s)
            st = f(m.slope_t.expand_as(m.slope_s))
            mq, wq, tmag = f(mq), f(wq), f(_mag(t))
            SA = ss * self.a_s
            MQ = mq + ss * self.m_s
            WQ = up(wq + ss.abs() * self.w_s)
            if self.prev is None:  # t_0^j = W_0[:, j], a constant: Lt . t_0 joins the bias
                Wq = self.W[:, cols].T.abs()[None, None]  # [1, 1, J, h]
            else:  # |W| |Q_{l-1}^j|: rounding of Lt @ W
                Wq = f(torch.einsum("kh,bhj->bkj", self.W.abs(), self.prev.qmag(cols)))
            KQ = ss.abs() * (self._smag() + self.m_s.abs() + self.w_s) + st.abs() * (tmag + Wq) \
                + mq.abs() + wq + SA.abs() * (2 * self.pmag + self.b.abs()[None, None, None]
                                              + self.Wx) + MQ.abs() + WQ
            WKQ = up(WQ + self.gk * up(KQ * (1 + 8 * U)))
            self._cols[key] = (st, SA, MQ, WKQ)
        return self._cols[key]


def _backward(layers: list[_Layer], top: int, La: torch.Tensor | None,
              LQ: torch.Tensor | None, bias: torch.Tensor, cols: torch.Tensor,
              lo: torch.Tensor, hi: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Backward pass from coefficients on a_{top-1} (La) and on Q_{top-1}^j (LQ; None for
    value-only queries), both [B, R, J, h], plus a constant `bias` [B, R, J], down to z:
    returns (Lz [B, R, J, d], cl, cu [B, R, J]) with
    Lz . (z - zc) + cl <= query <= Lz . (z - zc) + cu for every z in the box (real arithmetic).

    Both sides come from ONE pass: every relaxation is a pair of parallel lines
    a x + m +- w, so the coefficients of the query and of its negation are negatives of each
    other and only the intercepts differ: the signed part S = sum L m (+ biases) is shared and
    the radius part T = sum |L| w enters as S - T (lower) and S + T (upper).

    Slack: gamma_{2h+8} |L| . K per layer (folded into the intercept radii) covers every
    elementwise product, every sum of at most 2h bias terms and the products L @ W
    (gamma_{h+2} |L| |W| |x|); each update of the running sums adds gamma_4 (|S| + T)."""
    B, d = lo.shape
    zc = 0.5 * (lo + hi)
    # internal layout [B, J, R, h]: the intercept sums over h are then batched matrix-vector
    # products against the per-column constants (no [B, R, J, h] temporaries)
    sw = lambda x: x.transpose(1, 2)  # noqa: E731  [B, R, J, .] <-> [B, J, R, .]
    col = lambda x: x.transpose(1, 2).transpose(-1, -2)  # noqa: E731  [B,1,J,h] -> [B,J,h,1]
    dot = lambda L, c: (L @ c)[..., 0]  # noqa: E731  sum_h L c for c [B, J or 1, h, 1]
    La = sw(La) if La is not None else None
    LQ = sw(LQ) if LQ is not None else None
    S = sw(bias)
    T = torch.zeros_like(S)
    err = torch.zeros_like(S)
    Lz = None
    for li in range(top - 1, -1, -1):
        lay = layers[li]
        h = lay.pre.lo.shape[-1]
        if La is not None:
            Lpre = La * lay.a_a
            s_term = dot(La, col(lay.m_a))
            t_term = dot(La.abs(), col(lay.wk_a))
        if LQ is not None:
            st, SA, MQ, WKQ = lay.col_consts(cols)
            q_pre = LQ * sw(SA)
            Lpre = q_pre if La is None else Lpre + q_pre
            qs, qt = dot(LQ, col(MQ)), dot(LQ.abs(), col(WKQ))
            s_term = qs if La is None else s_term + qs
            t_term = qt if La is None else t_term + qt
            Lt = LQ * sw(st)
        S = S + s_term + Lpre @ lay.b
        T = T + t_term
        err = err + gamma(4) * (S.abs() + T)
        if lay.bslack is not None:
            err = err + up(dot(Lpre.abs(), col(lay.bslack)) * (1 + gamma(h + 2)))
        if li > 0:
            La = Lpre @ lay.W
            LQ = Lt @ lay.W if LQ is not None else None
        else:
            Lz = Lpre @ lay.W  # [B, J, R, d]
            if LQ is not None:
                S = S + dot(Lt, lay.W[:, cols].T[None, :, :, None])
                err = err + gamma(4) * (S.abs() + T)
    Lz, S, T, err = sw(Lz), sw(S), sw(T), sw(err)
    zcq = zc[:, None, None, :]
    cz = (Lz * zcq).sum(-1)
    S = cz + S
    err = err + gamma(d + 4) * ((Lz * zcq).abs().sum(-1) + S.abs() + T)
    E = up(up(err * (1.0 + 8 * U)) + TINY * (4 * d + 64))
    return Lz, down((S - T) - E), up((S + T) + E)


def _concretize(Lz: torch.Tensor, cl: torch.Tensor, cu: torch.Tensor, r: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """(min, max) over |dz| <= r of Lz . dz + cl and Lz . dz + cu, rounded outward."""
    d = Lz.shape[-1]
    rr = r.reshape(r.shape[0], *([1] * (Lz.ndim - 2)), d)
    rad = up((Lz.abs() * rr).sum(-1) * (1.0 + gamma(d + 2)))
    return down(cl - rad), up(cu + rad)


def _queries(Wrows: torch.Tensor, J: int, B: int) -> torch.Tensor:
    """Coefficients [B, out, J, h] for the queries (row i, column j); `_backward` bounds both
    signs at once."""
    out, h = Wrows.shape
    return Wrows[None, :, None, :].expand(B, out, J, h)


def forward_bounds(net: GainNetwork | AffineInputNetwork, lo: torch.Tensor, hi: torch.Tensor,
                   cols: list[int] | None = None, crown: bool = True,
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
    layers: list[_Layer] = []
    for L, (W, b) in enumerate(weights[1:], start=1):
        pres.append(pre_iv)
        tans.append(tan_iv)
        Win, bin_ = weights[L - 1]
        layers.append(_Layer(pre_iv, tan_iv, Win, bin_, layers[-1] if layers else None, zmag,
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
            La = _queries(W, 1, B)
            bias = b[None, :, None].expand(B, m, 1)
            lowv, highv = _concretize(*_backward(layers, L, La, None, bias, colt[:1], lo, hi),
                                      r)
            pre_iv = Interval(torch.maximum(pre_iv.lo, lowv[..., 0]),
                              torch.minimum(pre_iv.hi, highv[..., 0]))
            if not tangents:
                continue
            # tangent queries on t_L^j = W_L[i] Q_{L-1}^j
            LQ = _queries(W, len(colt), B)
            zero = torch.zeros(B, m, len(colt), dtype=torch.float64)
            lowt, hight = _concretize(*_backward(layers, L, None, LQ, zero, colt, lo, hi), r)
            tl, th = tan_iv.lo.clone(), tan_iv.hi.clone()
            tl[..., colt] = torch.maximum(tl[..., colt], lowt)
            th[..., colt] = torch.minimum(th[..., colt], hight)
            tan_iv = Interval(tl, th)
    jac = TM(T.c.transpose(1, 2), T.g.transpose(1, 2), T.e.transpose(1, 2))  # [B, out, d]
    return ForwardBounds(pres, tans, val, jac, r, layers)


def jacobian_crown(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, cols: list[int],
                   fb: ForwardBounds) -> LinearEnclosure:
    """Linear lower/upper bounds of dN_i/dz_j over each box, i < out, j in cols -> [B, out, J]."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    WH = net.weights()[-1][0].to(torch.float64)
    out = WH.shape[0]
    colt = torch.as_tensor(cols, dtype=torch.long)
    J = len(cols)
    LQ = _queries(WH, J, B)
    Lz, cl, cu = _backward(fb.layers, len(fb.layers), None, LQ,
                           torch.zeros(B, out, J, dtype=torch.float64), colt, lo, hi)
    return LinearEnclosure(gl=Lz, cl=cl, gu=Lz, cu=cu)


def value_crown(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, fb: ForwardBounds
                ) -> LinearEnclosure:
    """Linear lower/upper bounds of the network output N(z) over each box -> [B, out]."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    WH, bH = (x.to(torch.float64) for x in net.weights()[-1])
    out = WH.shape[0]
    La = _queries(WH, 1, B)
    bias = bH[None, :, None].expand(B, out, 1)
    Lz, cl, cu = _backward(fb.layers, len(fb.layers), La, None, bias,
                           torch.zeros(1, dtype=torch.long), lo, hi)
    return LinearEnclosure(gl=Lz[..., 0, :], cl=cl[..., 0], gu=Lz[..., 0, :], cu=cu[..., 0])


def network_crown_tms(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, cols: list[int],
                      value: bool = False, crown_intermediate: bool = True
                      ) -> tuple[TM, TM, torch.Tensor]:
    """(value TM [B, out], Jacobian TM [B, out, d], radii): the forward Taylor models with the
    Jacobian columns `cols` (and the value, when asked) replaced entry by entry by the linear
    bound propagation's, where that has the smaller remainder."""
    fb = forward_bounds(net, lo, hi, cols=cols, crown=crown_intermediate)
    jt = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r)  # [B, out, J]
    colt = torch.as_tensor(cols, dtype=torch.long)
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


__all__ = ["ForwardBounds", "forward_bounds", "LinearEnclosure", "jacobian_crown",
           "value_crown", "network_crown_tms", "to_tm", "tm_tighter"]
