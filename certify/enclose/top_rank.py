"""The top layer's product errors by their rank structure, for networks with at most two
hidden layers.

`certify.enclose.structured` bounds He{C eps} (C = R W_H [n, h], eps [h, n] the relaxation
errors of the last hidden layer's products Q_k^j = s_k t_k^j) with |eps_kj| <= w_kj taken
independent for every (k, j). They are not: with the averaged McCormick planes (slopes
tc_k^j on s_k, sc_k on t_k^j, intercept midpoint mq) and s_k = a_s pre_k + m_s + e_k (|e_k| <=
ws_k, the relaxation of f'),

    eps_kj = sigma_k tau_kj + tc_kj e_k + kappa_kj,  sigma_k = s_k - sc_k,
    tau_kj = t_k^j - tc_kj,  kappa_kj = -(sc_k tc_kj + mq_kj)

(exactly, in real arithmetic: s t - tc s - sc t = (s - sc)(t - tc) - sc tc). With two hidden
layers t_k^j = sum_l W1_kl s1_l W0_lj (s1 = f'(pre_0), W0 the first layer's weights), so
tau_k = sum_l W1_kl delta_l W0_l + o_k with delta_l = s1_l - s1c_l, |delta_l| <= rho1_l, and
o_k = W1 diag(s1c) W0 - tc_k a known vector (one hidden layer: t = W0 exactly, tau_k = o_k).
Every error term is a scalar times a fixed direction, so for every x

    x^T He{C eps} x = sum_k (c_k . x)(eps_k . x)
      <= sum_k |c_k . x| [sum_l beta_kl |W0_l . x| + rs_k |o_k . x| + ws_k |tc_k . x|] + entrywise
      <= x^T W x + entrywise,

beta_kl = rs_k |W1_kl| rho1_l (rs_k >= |sigma_k|), each |c . x||v . x| <= (a (c . x)^2 +
(v . x)^2 / a) / 2 (any a > 0), so W = 1/2 [C diag(A) C^T + W0^T diag(Bw) W0 + O^T diag(rs /
a_o) O + TC^T diag(ws / a_t) TC] with A_k = sum_l beta_kl a_kl + rs_k a_o,k + ws_k a_t,k and
Bw_l = sum_k beta_kl / a_kl: rank-one terms along the directions the errors really have,
where the independent form pays sum_j w_kj |x_j| in every direction. "entrywise" is kappa
and the rounding of o, |C| (rs |do| + |kappa|), joined to the remainder entry by entry. The
a's balance each pair against the room R = level I - sym(c) (a = sqrt(v^T R^-1 v /
c^T R^-1 c), which minimises the trace of R^-1/2 W R^-1/2); any a > 0 is sound.

On the chain families whole proofs take markedly fewer boxes than with the independent form
alone (`bench/prove_suite.py`, `bench/tree_size.py`).

The first layer's f' relaxation errors (two hidden layers, `LowerRank`): s1_l = a_s pre_0l +
m_s + e1_l enters the rows' Jacobian as sum_l e1_l U_l W0_l^T with U = C diag(sc) W1 (the
backward pass's coefficient on Q_0^j = s1 W0[:, j]), so x^T (.) x <= sum_l ws1_l |U_l . x|
|W0_l . x| <= 1/2 sum_l ws1_l (a_l (U_l . x)^2 + (W0_l . x)^2 / a_l): one more rank-one pair
per first-layer neuron, the W0_l half joining Bw. Entry by entry (as the backward pass
carried them before) they cost sum_l |U_il| |W0_lj| ws1_l in every entry; apart, more of the
boxes the chain families send to this bound are decided and whole proofs take fewer boxes
(`bench/remainder_gap.py`'s `decided_if_zero`, `bench/prove_suite.py`). The first layer's
value errors (through the top layer's f' slope a_s: entry (i, j) carries sum_l ea_l
G_l[i, j], G_l = C diag(a_s W1[:, l]) tc) stay in the pass: as rank-one pairs per top neuron
or as the Loewner majorant sum_l wa_l |sym(G_l)| (one small eigh per box and neuron) they
decided a few more boxes, but whole proofs took more time.

Rounding: rs, rho1, beta, A, Bw and the a-weighted sums are rounded up (sums of
non-negative terms, widened by gamma_K); W is formed in float and its error, at most
gamma_K times the same sums with |C|, |W0|, |O|, |TC|, joins the remainder; o's float error
is bounded by gamma_{h+3} (|W1| |s1c| |W0| + |tc|); kappa by the outward-rounded
|sc tc + mq| (two roundings).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.intervals import TINY, gamma, up
from certify.arith.linalg import eigh
from certify.arith.taylor import TM
from certify.enclose.crown_backward import midrad_icpt


@dataclass
class LowerRank:
    """The first layer's f' relaxation errors of a two-hidden-layer network, left out of the
    backward pass (`lower_apart`): with s1_l = a_s pre_0l + m_s + e1_l (|e1_l| <= ws1 [B,
    h1]) the backward pass's coefficient on Q_0^j = s1 W0[:, j] is U = C diag(sc) W1 (sc the
    top planes' slope on t), so the rows' Jacobian carries sum_l e1_l U_l W0_l^T: rank one
    per neuron, like the top layer's terms (module docstring). U [B, m, h1] is this module's
    float product; `entry` [B, m, J] bounds what the rank terms leave: the McCormick error of
    Q_0 (its intercept radius; t_0 = W0 is a point, so it is rounding only) and U's distance
    to the pass's own float coefficients; `full` [B, m, J] bounds all of these errors entry
    by entry (`certify.enclose.structured.entrywise`)."""

    U: torch.Tensor
    ws1: torch.Tensor
    entry: torch.Tensor
    full: torch.Tensor


def lower_apart_applies(layers: list) -> bool:
    """Whether the first layer's f' errors are left out of the backward pass and bounded by
    `LowerRank`: two hidden layers and no composed first layer."""
    return len(layers) == 2 and layers[0].bslack is None


def _lower_rank(layers: list, cols: torch.Tensor, C: torch.Tensor, sc: torch.Tensor
                ) -> LowerRank:
    """`LowerRank` for the two-layer network `layers` (C [m, h], sc [B, h])."""
    first, top = layers
    W1 = top.W.to(torch.float64)  # [h, h1]
    h = W1.shape[0]
    Csc = C[None] * sc[:, None, :]  # [B, m, h]
    U = Csc @ W1  # [B, m, h1]
    # the pass's coefficient and U are float sums of the same h products: each within
    # gamma_{h+1} |C| |sc| |W1| of the real one
    dU = up(2.0 * gamma(h + 2) * (Csc.abs() @ W1.abs()) * (1.0 + 4 * gamma(1)) + TINY)
    ws1 = first.w_s[:, 0, 0, :].to(torch.float64)  # [B, h1]
    # Q_0^j within slope_s s1 + sc t + mq +- wq (the planes, t_0 = W0[:, cols] a point: wq is
    # rounding only), s1 within its relaxation +- ws1: the error is slope_s e1 + (<= wq), and
    # slope_s (t's midpoint) is W0[:, cols]; any difference is carried entry by entry
    mc = first.planes(cols)
    wq = midrad_icpt(mc.lower_icpt, mc.upper_icpt)[1]  # [B, h1, J]
    W0 = first.W.to(torch.float64)[:, cols]  # [h1, J]
    off = up((mc.slope_s - W0[None]).abs() * ws1[:, :, None])  # [B, h1, J]: 0 in practice
    W0e = up(mc.slope_s.abs() * ws1[:, :, None])  # [B, h1, J]: |slope_s| ws1
    g = 1.0 + 2.0 * gamma(U.shape[-1] + 2)
    Um = up(U.abs() + dU)
    entry = up((Um @ up(wq + off) + dU @ W0e) * g + TINY)
    full = up(Um @ up(W0e + wq) * g + TINY)
    return LowerRank(U, ws1, entry, full)


@dataclass
class TopRank:
    """The rank structure of the top layer's product errors over each box (module
    docstring): eps_k = sigma_k tau_k + e_k tc_k + kappa_k with |sigma_k| <= rs [B, h],
    |e_k| <= ws [B, h], tau_k = sum_l W1_kl delta_l W0[l] + o_k, |delta_l| <= rho1 [B, h1]
    (beta [B, h, h1] = rs |W1| rho1, rounded up), directions W0 [h1, n], o [B, h, n] and
    tc [B, h, n], and `entry` [B, h, n]: the entrywise rest rs |do| + |kappa| of each
    eps_k."""

    rs: torch.Tensor
    ws: torch.Tensor
    beta: torch.Tensor
    W0: torch.Tensor
    o: torch.Tensor
    tc: torch.Tensor
    entry: torch.Tensor
    lower: LowerRank | None = None
    #: two hidden layers: W1 [h, h1] and rho1 [B, h1] apart, for the coupled form of the
    #: beta terms (`_coupled_beta`); None with one hidden layer
    W1: torch.Tensor | None = None
    rho1: torch.Tensor | None = None


def top_rank(layers: list, cols: torch.Tensor, C: torch.Tensor, lower: bool = False
             ) -> TopRank | None:
    """The structure for a network with one or two hidden layers (`certify.enclose.crown`'s
    `BackwardLayer`s, their ranges and relaxations) and C = R W_H [m, h]; None for deeper networks
    or a composed first layer (its tangent is not W0 exactly)."""
    if len(layers) > 2 or layers[0].bslack is not None:
        return None
    top = layers[-1]
    mc = top.planes(cols)  # the planes `col_consts` made (and the relaxation of f', w_s)
    tc, sc = mc.slope_s, mc.slope_t  # [B, h, J], [B, h, 1]
    mq = 0.5 * (mc.lower_icpt + mc.upper_icpt)
    rs = up(torch.maximum(top.s.hi - sc[..., 0], sc[..., 0] - top.s.lo))  # [B, h]
    ws = top.w_s[:, 0, 0, :].to(torch.float64)  # [B, h]
    # |sc tc + mq| in real arithmetic: the float value plus its two roundings
    kappa = up((sc * tc + mq).abs() + gamma(2) * ((sc * tc).abs() + mq.abs())
               * (1.0 + 4 * gamma(1)) + TINY)  # [B, h, J]
    W0 = layers[0].W.to(torch.float64)[:, cols]  # [h1, J]
    B, h, J = tc.shape
    W1 = rho1 = None
    if len(layers) == 1:  # t = W0[:, cols] exactly: tau = o = W0 - tc (one rounding)
        beta = torch.zeros(B, h, 0, dtype=torch.float64, device=tc.device)
        o = W0[None] - tc
        W0 = W0[:0]  # no lower layer: no delta directions
        do = up(gamma(2) * (o.abs() + tc.abs()))
    else:
        s1 = layers[0].s
        s1c = 0.5 * (s1.lo + s1.hi)
        rho1 = up(torch.maximum(s1.hi - s1c, s1c - s1.lo))  # [B, h1]
        W1 = top.W.to(torch.float64)  # [h, h1]
        h1 = W1.shape[1]
        beta = up(up(rs[:, :, None] * W1.abs()[None]) * rho1[:, None, :])  # [B, h, h1]
        o = torch.einsum("kl,bl,lj->bkj", W1, s1c, W0) - tc
        mag = torch.einsum("kl,bl,lj->bkj", W1.abs(), s1c.abs(), W0.abs()) + tc.abs()
        do = up(gamma(h1 + 3) * mag * (1.0 + 4 * gamma(1)))
    entry = up(rs[:, :, None] * do + kappa)  # [B, h, J]
    low = _lower_rank(layers, cols, C.to(torch.float64), sc[..., 0]) if lower else None
    return TopRank(rs, ws, beta, W0, o, tc, entry, low, W1, rho1)


def rank_loewner_upper(A: TM, C: torch.Tensor, w: torch.Tensor, rank: TopRank,
                       level: float = 0.0, force: str | None = None,
                       coupled: bool | None = None) -> TM:
    """The TM (c + W, g, e + entrywise rest + rounding) whose members bound every member of
    A + He{C eps} from above in the Loewner order, W balanced against the room level I -
    sym(c). Per neuron k the bound of |eps_k . x| is the rank form (module docstring) or
    the independent one of `certify.enclose.structured` (w [B, J, h]: |eps_kj| <= w_jk),
    whichever has the smaller trace against the room (neither dominates: the rank form wins
    on most boxes of the chain families, not on all); both are sound, so is any choice
    (`force`: "rank" or "independent" for every neuron, for the tests). With two hidden
    layers the beta terms of the rank neurons take the pair form or the coupled one
    (`_coupled_beta`), per box the one with the smaller trace (`coupled`: True or False
    forces it, for the tests)."""
    C = C.to(torch.float64)
    w = w.to(torch.float64)
    n, h = C.shape
    c0 = A.c
    Ri, _ = room_inverse(c0, level)  # [B, n, n]
    qc = torch.einsum("ik,bij,jk->bk", C, Ri, C)
    qw = torch.einsum("li,bij,lj->bl", rank.W0, Ri, rank.W0)
    qo = torch.einsum("bki,bij,bkj->bk", rank.o, Ri, rank.o)
    qt = torch.einsum("bki,bij,bkj->bk", rank.tc, Ri, rank.tc)
    # the independent form per k: (c_k . x)(w_k . |x|) <= (a (c_k . x)^2 + s_k/a w_k . x^2)/2
    s_ind = up(w.sum(1) * (1.0 + gamma(n + 1)))  # [B, h] >= sum_j w_jk
    q_ind = s_ind * torch.einsum("bjk,bj->bk", w, torch.diagonal(Ri, dim1=-2, dim2=-1))
    t_ind = (qc * q_ind).sqrt()
    t_rank = qc.sqrt() * ((rank.beta * qw.sqrt()[:, None, :]).sum(-1) + rank.rs * qo.sqrt()
                          + rank.ws * qt.sqrt())
    use = ~(t_ind < t_rank)  # NaN: the rank form (its own terms carry the NaN)
    if force is not None:
        use = torch.full_like(use, force == "rank")
    z = torch.zeros((), dtype=torch.float64, device=c0.device)
    a_kl = _ratio(qw[:, None, :], qc[:, :, None])
    a_o, a_t, a_i = _ratio(qo, qc), _ratio(qt, qc), _ratio(q_ind, qc)
    beta = torch.where(use[:, :, None], rank.beta, z)
    rs, ws = torch.where(use, rank.rs, z), torch.where(use, rank.ws, z)
    # independent neurons: a_i (c_k . x)^2 + (s_k / a_i) sum_j w_jk x_j^2
    ai = torch.where(use, z, a_i)
    si = torch.where(use, z, up(s_ind / a_i))
    K = rank.beta.shape[-1] + 4
    widen = 1.0 + 2.0 * gamma(K + 1)
    A_cp = F_cp = None
    if rank.W1 is not None and coupled is not False:
        beta, A_cp, F_cp = _coupled_beta(rank, use, qc, qw, beta, a_kl, coupled)
    Acoef = up(((beta * a_kl).sum(-1) + rs * a_o + ws * a_t + ai) * widen)  # [B, h]
    Bw = up(up(beta / a_kl).sum(1) * widen)  # [B, h1]
    if A_cp is not None:  # the coupled beta terms (zero where the pair form was kept)
        Acoef = up((Acoef + A_cp) * (1.0 + 2.0 * gamma(2)))
        Bw = up((Bw + F_cp) * (1.0 + 2.0 * gamma(2)))
    low = rank.lower
    if low is not None:  # ws1_l |U_l . x| |W0_l . x|, balanced like the top's pairs
        qu = torch.einsum("bil,bij,bjl->bl", low.U, Ri, low.U)
        a_u = _ratio(qw, qu)
        Bw = up((Bw + up(low.ws1 / a_u)) * (1.0 + 2.0 * gamma(2)))
        Fu = up(low.ws1 * a_u)  # [B, h1]
    fo, ft = up(rs / a_o), up(ws / a_t)  # [B, h]
    diag = up(torch.einsum("bk,bjk->bj", si, w) * (1.0 + 2.0 * gamma(h + 1)))
    W = 0.5 * (torch.einsum("ik,bk,jk->bij", C, Acoef, C)
               + torch.einsum("li,bl,lj->bij", rank.W0, Bw, rank.W0)
               + torch.einsum("bk,bki,bkj->bij", fo, rank.o, rank.o)
               + torch.einsum("bk,bki,bkj->bij", ft, rank.tc, rank.tc)
               + torch.diag_embed(diag))
    if low is not None:
        W = W + 0.5 * torch.einsum("bil,bl,bjl->bij", low.U, Fu, low.U)
    # float error of W: gamma_K' times the same sums of absolute values
    Wabs = 0.5 * (torch.einsum("ik,bk,jk->bij", C.abs(), Acoef, C.abs())
                  + torch.einsum("li,bl,lj->bij", rank.W0.abs(), Bw, rank.W0.abs())
                  + torch.einsum("bk,bki,bkj->bij", fo, rank.o.abs(), rank.o.abs())
                  + torch.einsum("bk,bki,bkj->bij", ft, rank.tc.abs(), rank.tc.abs())
                  + torch.diag_embed(diag))
    if low is not None:
        Wabs = Wabs + 0.5 * torch.einsum("bil,bl,bjl->bij", low.U.abs(), Fu, low.U.abs())
    gk = gamma(h + rank.beta.shape[-1] + 8)
    c = c0 + W
    entry = torch.einsum("ik,bkj->bij", C.abs(), torch.where(use[:, :, None], rank.entry, z))
    entry = up(entry * (1.0 + 2.0 * gamma(h + 2)) + TINY)
    if low is not None:
        entry = up(entry + low.entry)
    rest = 0.5 * (entry + entry.transpose(1, 2))
    e = up((A.e + rest + gk * Wabs + gamma(1) * c.abs()) * (1.0 + 2.0 * gk) + TINY)
    bad = ~(torch.isfinite(c).flatten(1).all(-1) & torch.isfinite(e).flatten(1).all(-1))
    e = torch.where(bad[:, None, None], torch.full_like(e, float("nan")), e)
    return TM(c, A.g, e)


def _coupled_beta(rank: TopRank, use: torch.Tensor, qc: torch.Tensor, qw: torch.Tensor,
                  beta: torch.Tensor, a_kl: torch.Tensor, force: bool | None,
                  iterations: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The beta terms of the rank neurons (`use`) in the coupled form, where its trace against
    the room is the smaller (or everywhere: `force`): (beta with those boxes' rows zeroed,
    A [B, h], F [B, h1]) such that, for every |sigma_k| <= rs_k, |delta_l| <= rho1_l and x,

        sum_k u_k sigma_k sum_l W1_kl delta_l v_l <= 1/2 [sum_k A_k u_k^2 + sum_l F_l v_l^2],

    u = C^T x, v = W0 x. Proof: for any y_k > 0 (G_k = 1 / y_k), 2 p q <= G p^2 + q^2 / G
    per k gives <= 1/2 [sum_k rs_k^2 u_k^2 / y_k + (delta o v)^T H (delta o v)], H = W1^T
    diag(y) W1, and (delta o v)^T H (delta o v) <= sum_lm |H_lm| rho1_l rho1_m |v_l| |v_m|
    <= sum_l v_l^2 rho1_l sum_m |H_lm| rho1_m (2 |v_l| |v_m| <= v_l^2 + v_m^2). So A_k =
    rs_k^2 / y_k and F_l = rho1_l sum_m |H_lm| rho1_m. The pair form bounds every (k, l)
    apart, sum_k |W1_kl| |W1_km| where this has |sum_k W1_kl y_k W1_km|: it keeps the
    cancellations between the top neurons. y: a few fixed-point steps towards the smallest
    trace sum_k A_k qc_k + sum_l F_l qw_l, then the best common scale (any y > 0 is sound).
    On the chain families the trees of whole proofs are smaller with it
    (`bench/tree_size.py`).

    Rounding: A and F are rounded up from real-number bounds: rs^2 / y by two upward
    roundings; |H_lm| <= |fl(H)_lm| + gamma_{h+2} (|W1|^T diag(y) |W1|)_lm (Higham, a sum of
    h products of three), the sums over m widened by gamma_{h1+2} and rounded up."""
    W1 = rank.W1
    rs = torch.where(use, rank.rs, torch.zeros_like(rank.rs))  # [B, h]
    rho = rank.rho1  # [B, h1]
    on = rs > 0
    zero = torch.zeros_like(rs)
    y = torch.where(on, rs * qc.sqrt(), zero)  # ~ 1 / G_k (first guess)

    def f_of(y: torch.Tensor) -> torch.Tensor:  # float F (for the choice of y only)
        return rho * (gram(W1, y).abs() @ rho[..., None])[..., 0]

    for _ in range(iterations):
        # d trace / d y_k = -rs_k^2 qc_k / y_k^2 + c_k, c_k = sum_lm qw_l rho_l rho_m
        # sgn(H_lm) W1_kl W1_km: halfway towards its zero
        G = (qw * rho)[:, :, None] * torch.sign(gram(W1, y)) * rho[:, None, :]
        ck = ((G @ W1.T) * W1.T).sum(1)  # sum_lm G_lm W1_km W1_kl
        step = rs * qc.sqrt() / ck.clamp_min(1e-300).sqrt()
        y = torch.where(on & (ck > 0), 0.5 * (y + step), y)
    T1 = torch.where(on, rs * rs * qc / y.clamp_min(1e-300), zero).sum(-1)
    T2 = (f_of(y) * qw).sum(-1)
    scale = (T2 / T1).sqrt()
    scale = torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))
    y = torch.where(on, (y / scale[:, None]).clamp(1e-150, 1e150), zero)
    pair = (beta * (a_kl * qc[:, :, None] + qw[:, None, :] / a_kl)).sum((1, 2))
    pick = 2.0 * (T1 * T2).sqrt() < pair
    if force is not None:
        pick = torch.full_like(pick, bool(force))
    pick = pick & on.any(-1)
    # sound A and F from the float y (module rounding note)
    h, h1 = W1.shape
    A = torch.where(on, up(up(rs * rs) / y.clamp_min(1e-300)), zero)
    H = gram(W1, y)
    Habs = gram(W1.abs(), y)
    Herr = up(gamma(h + 2) * Habs * (1.0 + 2.0 * gamma(h + 2)))  # >= |H - fl(H)|
    Hb = up(H.abs() + Herr)
    F = up(rho * up(torch.einsum("blm,bm->bl", Hb, rho) * (1.0 + 2.0 * gamma(h1 + 2))))
    if bool(pick.any()):
        F[pick] = _scaled_majorant(H[pick], Herr[pick], rho[pick], F[pick])
    beta = torch.where(pick[:, None, None], torch.zeros_like(beta), beta)
    A = torch.where(pick[:, None], A, torch.zeros_like(A))
    F = torch.where(pick[:, None], F, torch.zeros_like(F))
    return beta, A, F


def gram(W1: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """W1^T diag(y) W1 [B, h1, h1] for W1 [h, h1] and y [B, h] (a batched product)."""
    return (W1.T[None] * y[:, None, :]) @ W1


def _scaled_majorant(H: torch.Tensor, Herr: torch.Tensor, rho: torch.Tensor, F: torch.Tensor
                     ) -> torch.Tensor:
    """A smaller diagonal majorant of Delta H Delta over |delta| <= rho: lam F, lam >=
    lam_max(F^-1/2 R H R F^-1/2) (R = diag(rho)), capped at 1. diag(lam F) >= R H R suffices:
    with Delta = T R, |t_l| <= 1, x^T Delta H Delta x = (T x)^T R H R (T x) <= sum_l lam F_l
    t_l^2 x_l^2 <= x^T diag(lam F) x (H >= 0). F (the diagonal
    dominance bound, rho_l sum_m (|H| + Herr)_lm rho_m >= sum_m |(R H R)_lm|) gives lam <= 1
    (Perron); where cancellations in H leave R H R far from its absolute value, lam is well
    below 1. H is fl(W1^T diag(y) W1),
    within Herr of the real one.

    lam_max(N) is bounded by the certified Cholesky test (`certify.arith.eigen.
    lam_max_at_most`, far cheaper than an eigenvalue solver) at 1.02, then 1.15 times a
    power-iteration estimate; where both fail, lam stays 1.

    Rounding: with S = diag(rho / sqrt(F)) (float: within 3u relative of the real one), the
    real matrix differs from N = fl(S fl(H) S) entrywise by at most E = S Herr S (1 + gamma_8)
    + gamma_10 |N| (first order in u, with room), so lam_max <= (the level the test proved) +
    ||E||_F, rounded up."""
    from certify.arith.eigen import lam_max_at_most

    on = F > 0
    root = torch.where(on, F, torch.ones_like(F)).sqrt()
    scale = torch.where(on, rho / root, torch.zeros_like(rho))  # rho_l / sqrt(F_l)
    N = scale[:, :, None] * H * scale[:, None, :]
    err = up(scale[:, :, None] * Herr * scale[:, None, :] * (1.0 + gamma(8))
             + gamma(10) * N.abs() + TINY)
    err_f = up(torch.linalg.matrix_norm(err) * (1.0 + gamma(err.shape[-1] ** 2 + 2)))
    v = torch.ones_like(rho)
    for _ in range(12):  # N >= 0 (H >= 0): the power iteration tends to lam_max from below
        v = (N @ v[..., None])[..., 0]
        v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    est = (v * (N @ v[..., None])[..., 0]).sum(-1)
    lam = torch.ones_like(est)
    left = torch.ones_like(est, dtype=torch.bool)
    for slack in (1.02, 1.15):  # the estimate is from below: a little room, then more
        t = up(slack * est.clamp_min(0.0) + 1e-9)
        try_ = left & torch.isfinite(t) & (t < 1.0)
        ok = torch.zeros_like(try_)
        ok[try_] = lam_max_at_most(N[try_], t[try_])
        lam = torch.where(ok, up(t + err_f), lam)
        left = left & ~ok
    lam = lam.clamp(max=1.0)
    lam = torch.where(torch.isfinite(lam), lam, torch.ones_like(lam))
    return torch.minimum(up(lam[:, None] * F), F)  # F itself is a majorant too


def _ratio(qv: torch.Tensor, qc: torch.Tensor) -> torch.Tensor:
    """a = sqrt(qv / qc) clamped to [1e-150, 1e150] (1 where not finite): any a > 0 is sound."""
    a = (qv / qc).sqrt()
    a = torch.where(torch.isfinite(a), a, torch.ones_like(a))
    return a.clamp(1e-150, 1e150)


def room_inverse(c: torch.Tensor, level: float) -> tuple[torch.Tensor, torch.Tensor]:
    """((level I - sym(c))^-1 [B, n, n] with its eigenvalues clamped positive, done [B]):
    the identity where c is not finite or LAPACK fails (done False). Only the balance of
    the Loewner bounds' weights depends on it (here and in `certify.enclose.structured`)."""
    B, n, _ = c.shape
    eye = torch.eye(n, dtype=torch.float64, device=c.device)
    out = eye.expand(B, n, n).clone()
    ok = torch.isfinite(c).flatten(1).all(-1)
    if not bool(ok.any()):
        return out, ok
    try:
        ev, Q = eigh(level * eye - 0.5 * (c[ok] + c[ok].transpose(-1, -2)))
    except RuntimeError:
        return out, torch.zeros_like(ok)
    ev = torch.maximum(ev, ev[:, -1:].abs() * 1e-9 + 1e-300)
    out[ok] = (Q / ev[:, None, :]) @ Q.transpose(-1, -2)
    return out, ok
