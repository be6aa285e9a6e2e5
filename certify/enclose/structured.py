"""The last hidden layer's relaxation errors as a matrix, not entry by entry.

With the mixed rows (`certify.enclose.mixed`), P dN/dx = (linear bounds) + C eps with C =
P W_H [n, h] a point matrix and eps [h, n] the relaxation errors of the last layer's products
Q_k^j = f'(pre_k) t_k^j, |eps_kj| <= w_kj, the same for every row. In A = He{P J} + ... (He{X}
= (X + X^T) / 2 in this code), that term is He{C eps}, and for every x

    x^T He{C eps} x = sum_k (c_k . x)(eps_k . x) <= sum_k |c_k . x| (w_k . |x|)
                    <= 1/2 sum_k [a_k (c_k . x)^2 + (w_k . |x|)^2 / a_k]        (any a_k > 0)
                    <= x^T W x,   W = 1/2 sum_k [a_k c_k c_k^T + (s_k / a_k) diag(w_k)],

s_k >= sum_j w_kj (Cauchy-Schwarz: (w . |x|)^2 <= (sum_j w_j)(sum_j w_j x_j^2)). So every
member of the box's family is <= (Loewner order) c + W + sum_m v_m G_m + E_rest: the TM with
c + W as its centre is an upper model of A, which is all that upper bounds of lam_max and the
decisions lam_max <= level need (lam_max is monotone in the Loewner order).

Entrywise, the same errors cost sum_k |c_ik| w_kj in entry (i, j): the signs of C are lost, and
with P mixing the outputs every entry carries the whole sum (on the chain families the
remainder matrix is nearly rank one and far larger than the room below the level). Here c_k
enters through
(c_k . x)^2, which is small in the critical directions x where C's columns cancel.

a_k balances the two terms against the room the box's centre leaves below the level,
R = level I - sym(c) (clamped positive definite):
a_k = sqrt(s_k sum_j w_kj (R^-1)_jj / (c_k^T R^-1 c_k)) minimises the trace bound
1/2 [a_k c_k^T R^-1 c_k + (s_k / a_k) tr(R^-1/2 diag(w_k) R^-1/2) (on boxes the entrywise
form leaves undecided it decides many: `bench/remainder_gap.py`).
Any a_k > 0 is sound; only tightness depends on it.

Rounding: W is formed in float; its error, at most gamma_{h+4} (1/2 sum_k a_k |c_k| |c_k|^T +
1/2 diag(sum_k (s_k / a_k) w_k)) entrywise, and that of c + W (u |c + W|) join the remainder,
rounded up; s_k is rounded up.
"""

from __future__ import annotations

import torch

from certify.arith.intervals import TINY, gamma, up
from certify.arith.taylor import TM
from certify.enclose.mixed import TopLayerRemainder
from certify.enclose.top_rank import rank_loewner_upper, room_inverse


def loewner_upper(A: TM, top: TopLayerRemainder, level: float = 0.0) -> TM:
    """An upper model of A + He{C eps} in the Loewner order: the rank-structured one
    (`certify.enclose.top_rank.rank_loewner_upper`) where the errors' directions are known
    (`top.rank`), else `independent_upper`."""
    if top.rank is not None:
        return rank_loewner_upper(A, top.C, top.w, top.rank, level)
    return independent_upper(A, top, level)


def independent_upper(A: TM, top: TopLayerRemainder, level: float = 0.0) -> TM:
    """The TM (c + W, g, e + rounding) whose members bound every member of A + He{C eps}
    from above in the Loewner order, the errors |eps_kj| <= w_jk taken independent (module
    docstring): A [B, n, n] (coefficients [B, n, n, d]), `top` the last layer's relaxation
    errors (C [n, h], w [B, n, h]); W is balanced against the room level I - c (the level
    the bounds will be held to)."""
    C, w = top.C.to(torch.float64), top.w.to(torch.float64)
    n, h = C.shape
    s = up(w.sum(1) * (1.0 + gamma(n + 1)))  # [B, h] >= sum_j w_jk
    a = _balance(A.c, C, w, s, level)  # [B, h]
    Cs = C[None] * a.sqrt()[:, None, :]  # [B, n, h]
    rank_part = 0.5 * (Cs @ Cs.transpose(1, 2))  # 1/2 sum_k a_k c_k c_k^T
    diag_part = 0.5 * torch.einsum("bk,bjk->bj", s / a, w)  # 1/2 sum_k (s_k / a_k) w_k
    W = rank_part + torch.diag_embed(diag_part)
    gk = gamma(h + 4)
    err = gk * (0.5 * torch.einsum("bk,ik,jk->bij", a, C.abs(), C.abs())
                + torch.diag_embed(diag_part))
    c = A.c + W
    e = up((A.e + err + gamma(1) * c.abs()) * (1.0 + 2.0 * gk) + TINY)
    bad = ~(torch.isfinite(c).flatten(1).all(-1) & torch.isfinite(e).flatten(1).all(-1))
    e = torch.where(bad[:, None, None], torch.full_like(e, float("nan")), e)
    return TM(c, A.g, e)


def entrywise(A: TM, top: TopLayerRemainder) -> TM:
    """The same errors entry by entry: A's remainder plus He{|C| w^T}, (|C| w^T)_ij =
    sum_k |C_ik| w_jk, rounded up (an entrywise enclosure again; for n <= 3, where Hertz's
    vertex bound treats an entrywise remainder exactly, it can beat the matrix form)."""
    C, w = top.C.to(torch.float64), top.w.to(torch.float64)
    h = C.shape[1]
    E = torch.einsum("ik,bjk->bij", C.abs(), w)
    if top.rank is not None and top.rank.lower is not None:  # the first layer's, apart too
        E = up(up(E * (1.0 + gamma(h + 2))) + top.rank.lower.full)
    gk = gamma(h + 4)
    e = up((A.e + 0.5 * (E + E.transpose(1, 2))) * (1.0 + 2.0 * gk) + TINY)
    return TM(A.c, A.g, e)


def _balance(c: torch.Tensor, C: torch.Tensor, w: torch.Tensor, s: torch.Tensor,
             level: float) -> torch.Tensor:
    """a_k > 0 per box [B, h] (module docstring: the room R = level I - sym(c), clamped
    positive definite); 1 where it is not finite or LAPACK fails (any positive a is
    sound)."""
    ok = torch.isfinite(c).flatten(1).all(-1) & torch.isfinite(w).flatten(1).all(-1)
    Rinv, done = room_inverse(c, level)
    cRc = torch.einsum("ik,bij,jk->bk", C, Rinv, C)
    wR = torch.einsum("bjk,bj->bk", w, torch.diagonal(Rinv, dim1=-2, dim2=-1))
    a = (s * wR / cRc.clamp_min(1e-300)).sqrt()
    good = (ok & done)[:, None] & torch.isfinite(a) & (a > 1e-150) & (a < 1e150)
    return torch.where(good, a, torch.ones_like(a))
