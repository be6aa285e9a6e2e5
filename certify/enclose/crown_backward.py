"""The backward pass of the CROWN prover: per-layer relaxations (`BackwardLayer`) and the pass.

For a `direct` MLP N(z) with activation f (pre_0 = W_0 z + b_0, a_l = f(pre_l), pre_{l+1} =
W_{l+1} a_l + b_{l+1}) the Jacobian columns follow t_0^j = W_0[:, j], Q_l^j = s_l * t_l^j with
s_l = f'(pre_l), t_{l+1}^j = W_{l+1} Q_l^j and dN/dz_j = W_H Q_{H-1}^j. For every entry
(i, j) and both signs, one backward pass (`backward_pass`) from the output to z composes

- McCormick planes for the products Q = s * t (`relax.mccormick`),
- linear relaxations of f' (derivative path) and f (value path) (`relax.relax_slope`,
  `relax.relax_value`: tanh's own, else the activation's generic parallel lines),
- the exact linear maps W_l,

picking each relaxation's lower or upper plane by the sign of its backward coefficient, and
ends with a linear function of z that bounds the entry on the whole box (`concretize` takes
its extremes over the box). The relaxations sit on the ranges of pre_l and t_l that
`certify.enclose.crown.forward_bounds` computes.

Rounding: the backward coefficients are computed in float64 and used as the (exactly
representable) coefficients of the relaxation; what float evaluation changes is accounted for
by a slack added to each query: every matrix product contributes gamma_k (|Lambda| |W|) . mag(x),
every elementwise product u |Lambda a| . mag(x), every sum of bias terms gamma_k sum|terms|,
with mag(x) the magnitude bound of the node the coefficients multiply (from the forward
ranges). The slack is rounded up and subtracted (`backward_pass`); `concretize` rounds outward.
"""

from __future__ import annotations

import torch

from certify.arith.intervals import TINY, Interval, U, down, gamma, up
from certify.enclose.relax import BilinearBounds, mccormick, relax_slope, relax_value
from certify.model.activations import Activation


def _mag(iv: Interval) -> torch.Tensor:
    return torch.maximum(iv.lo.abs(), iv.hi.abs())


def midrad_icpt(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """m, w with [lo, hi] inside [m - w, m + w] (w rounded up)."""
    m = 0.5 * (lo + hi)
    return m, up(torch.maximum(hi - m, m - lo))


class BackwardLayer:
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
                 prev: BackwardLayer | None, zmag: torch.Tensor, act: Activation) -> None:
        self.pre, self.tan, self.W, self.b, self.prev = pre, tan, W, b, prev
        self.act = act
        self.s = act.enclose_d1(pre)
        ra = relax_value(act, pre.lo, pre.hi)
        if not torch.equal(ra.lower_slope, ra.upper_slope):
            raise ValueError("backward propagation needs parallel-line relaxations")
        e = lambda x: x[:, None, None, :]  # noqa: E731  [B, h] -> [B, 1, 1, h]
        self.a_s = self.m_s = self.w_s = None  # f' relaxation: on first use (col_consts)
        self.a_a = e(ra.lower_slope)
        ma, wa = midrad_icpt(ra.lower_icpt, ra.upper_icpt)
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
        self._planes: dict[tuple[int, ...], BilinearBounds] = {}  # per column set
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
        """(st, SA, MQ, WKQ, WQ), each [B, 1, J, h], for the McCormick planes of s * t^j: the
        slope on t, the slope on pre through s, the intercept midpoint, its radius with the
        rounding slack gamma K_Q folded in, and the radius alone: Q = s * t^j lies within WQ
        of MQ + SA pre + st t^j for every point of the box (the relaxation error, the same
        for every query)."""
        key = tuple(int(c) for c in cols)
        self.slope_lines()
        if key not in self._cols:
            t = Interval(self.tan.lo[..., cols], self.tan.hi[..., cols])
            m = mccormick(Interval(self.s.lo.unsqueeze(-1), self.s.hi.unsqueeze(-1)), t)
            self._planes[key] = m
            f = lambda x: x.transpose(1, 2).unsqueeze(1)  # noqa: E731  [B, h, J] -> [B,1,J,h]
            mq, wq = midrad_icpt(m.lower_icpt, m.upper_icpt)
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
            self._cols[key] = (st, SA, MQ, WKQ, WQ)
        return self._cols[key]

    def slope_lines(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(a_s, m_s, w_s) [B, 1, 1, h]: f'(pre) within a_s pre + m_s +- w_s on the range of
        pre (made on first use)."""
        if self.a_s is None:
            rs = relax_slope(self.act, self.pre.lo, self.pre.hi)
            if not torch.equal(rs.lower_slope, rs.upper_slope):
                raise ValueError("backward propagation needs parallel-line relaxations")
            self.a_s = rs.lower_slope[:, None, None, :]
            ms, ws = midrad_icpt(rs.lower_icpt, rs.upper_icpt)
            self.m_s, self.w_s = ms[:, None, None, :], ws[:, None, None, :]
        return self.a_s, self.m_s, self.w_s

    def planes(self, cols: torch.Tensor) -> BilinearBounds:
        """The McCormick planes of s * t^j behind `col_consts` (`relax.BilinearBounds`,
        [B, h, J]), for `certify.enclose.top_rank`."""
        self.col_consts(cols)
        return self._planes[tuple(int(c) for c in cols)]


def backward_pass(layers: list[BackwardLayer], top: int, La: torch.Tensor | None,
              LQ: torch.Tensor | None, bias: torch.Tensor, cols: torch.Tensor,
              lo: torch.Tensor, hi: torch.Tensor, top_apart: bool = False,
              lower_apart: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
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
    (gamma_{h+2} |L| |W| |x|); each update of the running sums adds gamma_4 (|S| + T).

    top_apart (derivative queries, La None): the relaxation errors of the products Q at layer
    top - 1, sum_k |LQ_k| WQ_k, are left out of the intercepts (their rounding slack stays
    in): the caller accounts for them as LQ . eps with |eps| <= WQ, one eps for all queries
    (`certify.enclose.mixed.TopLayerRemainder`). lower_apart (with top_apart, two hidden
    layers): the same for the products at layer 0, whose errors the caller bounds by
    `certify.enclose.top_rank.LowerRank`."""
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
            st, SA, MQ, WKQ, WQ = lay.col_consts(cols)
            q_pre = LQ * sw(SA)
            Lpre = q_pre if La is None else Lpre + q_pre
            if (top_apart and li == top - 1) or (lower_apart and li == 0):
                # only the rounding slack: the caller has WQ
                WKQ = up(WKQ - WQ)
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


def concretize(Lz: torch.Tensor, cl: torch.Tensor, cu: torch.Tensor, r: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """(min, max) over |dz| <= r of Lz . dz + cl and Lz . dz + cu, rounded outward."""
    d = Lz.shape[-1]
    rr = r.reshape(r.shape[0], *([1] * (Lz.ndim - 2)), d)
    rad = up((Lz.abs() * rr).sum(-1) * (1.0 + gamma(d + 2)))
    return down(cl - rad), up(cu + rad)


def queries(Wrows: torch.Tensor, J: int, B: int) -> torch.Tensor:
    """Coefficients [B, out, J, h] for the queries (row i, column j); `backward_pass` bounds both
    signs at once."""
    out, h = Wrows.shape
    return Wrows[None, :, None, :].expand(B, out, J, h)
