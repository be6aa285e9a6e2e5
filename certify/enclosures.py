"""Interval enclosures of the gain network, of D, and sound bounds on lam_max, over boxes.

Boxes live in z = (xhat, y) space: lo, hi of shape [B, d], d = n + p. Everything is batched
over boxes and sound under floating point (the rounding scheme is `certify.intervals.ROUNDING`).

Two enclosures of the (preconditioned) contraction matrix A(z) = M D(z) M^T are combined:

- plain interval: value, Jacobian (and second derivatives) of the MLP propagated layer by layer
  in interval arithmetic, pre-activations tightened by a mean-value form around the box centre;
- second-order (mean-value / Taylor) form: A(z) in A(c) + sum_m (z_m - c_m) [dA/dz_m](box).
  Writing [dA/dz_m] = G_m + [-R_m, R_m], lam_max(A(c) + sum_m d_m G_m) is convex in d, so its
  maximum over |d_m| <= r_m is attained at one of the 2^d vertices (small eigenproblems,
  vectorised); the remainder adds rho(sum_m r_m R_m + rad A(c)) (Weyl + Perron-Frobenius).

M is the identity for P = I; otherwise M ~ L^-1 (P = L L^T, computed in floating point and
then used as an exact matrix: by Sylvester's law of inertia D <= 0 iff M D M^T <= 0 for every
invertible M, so the float error of M costs tightness, never soundness).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from certify.intervals import (
    TINY,
    Interval,
    d2tanh_enclosure,
    down,
    dtanh_enclosure,
    gamma,
    h_enclosure,
    hessian_f_enclosure,
    hessian_h_enclosure,
    imatmul,
    imul,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    matmul_point_right,
    midrad_to_interval,
    tanh_enclosure,
    up,
    widen_up,
)
from certify.network import GainNetwork
from certify.problem import Problem
from certify.system import System

U = 2.0**-53
MAX_VERTEX_DIM = 8  # beyond 2^8 vertices per box, the first-order term joins the remainder


# ----- small interval helpers ------------------------------------------------------------
def isum(a: Interval, dim: int) -> Interval:
    """Sum along `dim`, with the floating-point summation error bounded by gamma_k sum|x|."""
    k = a.lo.shape[dim]
    g = gamma(k + 1)
    slo = a.lo.sum(dim)
    shi = a.hi.sum(dim)
    elo = g * a.lo.abs().sum(dim) + k * TINY
    ehi = g * a.hi.abs().sum(dim) + k * TINY
    return Interval(down(slo - elo), up(shi + ehi))


def iadd(a: Interval, b: Interval) -> Interval:
    return Interval(down(a.lo + b.lo), up(a.hi + b.hi))


def isym(a: Interval) -> Interval:
    """He{A} = (A + A^T)/2 for an interval matrix [..., n, n]."""
    s = iadd(a, Interval(a.lo.transpose(-1, -2), a.hi.transpose(-1, -2)))
    return Interval(down(0.5 * s.lo), up(0.5 * s.hi))


def intersect(a: Interval, b: Interval) -> Interval:
    """a cap b (both contain the true value, so the intersection does too)."""
    return Interval(torch.maximum(a.lo, b.lo), torch.minimum(a.hi, b.hi))


def point(x: torch.Tensor) -> Interval:
    return Interval(x, x)


# ----- MLP enclosure -------------------------------------------------------------------
@dataclass
class NetEnclosure:
    """Enclosures of N [B, out], dN/dz [B, out, d] and d2N/dz_j dz_m [B, out, J, d]."""

    value: Interval
    d1: Interval
    d2: Interval | None
    pre: list[Interval]  # pre-activation value enclosures per hidden layer [B, h]


def network_enclosure(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, order: int = 1,
                      second_cols: int | None = None,
                      center_pre: list[Interval] | None = None) -> NetEnclosure:
    """Forward-mode interval propagation of value, Jacobian and (order 2) second derivatives.

    lo, hi [B, d]. Rows travel together as one tensor [B, R, width]: row 0 the value, rows
    1..d the tangents, then J*d second-derivative rows (j < J = second_cols, m < d). With
    `center_pre` (from a pass on the degenerate boxes [c, c]), each pre-activation value
    is intersected with its mean-value form pre(c) + sum_m [dpre/dz_m] (z_m - c_m).
    """
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    J = d if second_cols is None else int(second_cols)
    weights = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
    W0, b0 = weights[0]
    zc = 0.5 * (lo + hi)
    zr = up(torch.maximum(hi - zc, zc - lo))
    zdev = Interval(-zr, zr)  # z - c
    c, r = matmul_point_right(zc, zr, W0.T)
    val = midrad_to_interval(c, r) + point(b0.expand_as(c))
    h0 = W0.shape[0]
    T = point(W0.T.unsqueeze(0).expand(B, d, h0))  # [B, d, h]
    S = None
    if order >= 2:
        zero = torch.zeros(B, J * d, h0, dtype=torch.float64)
        S = Interval(zero, zero)
    pres: list[Interval] = []
    for li, (W, b) in enumerate(weights[1:]):
        if center_pre is not None:
            mv = isum(imul(T, Interval(zdev.lo.unsqueeze(-1), zdev.hi.unsqueeze(-1))), 1)
            val = intersect(val, center_pre[li] + mv)
        pres.append(val)
        t = tanh_enclosure(val)
        s1 = dtanh_enclosure(val)
        s1e = Interval(s1.lo.unsqueeze(1), s1.hi.unsqueeze(1))
        Tn = imul(s1e, T)
        rows_lo = [t.lo.unsqueeze(1), Tn.lo]
        rows_hi = [t.hi.unsqueeze(1), Tn.hi]
        if S is not None:
            s2 = d2tanh_enclosure(val)
            hw = T.lo.shape[-1]
            Tj = Interval(T.lo[:, :J].unsqueeze(2), T.hi[:, :J].unsqueeze(2))  # [B, J, 1, h]
            Tm = Interval(T.lo.unsqueeze(1), T.hi.unsqueeze(1))  # [B, 1, d, h]
            TT = imul(Tj, Tm)  # [B, J, d, h]
            s2e = Interval(s2.lo[:, None, None, :], s2.hi[:, None, None, :])
            s1f = Interval(s1.lo[:, None, None, :], s1.hi[:, None, None, :])
            Sn = iadd(imul(s2e, TT), imul(s1f, Interval(S.lo.reshape(B, J, d, hw),
                                                        S.hi.reshape(B, J, d, hw))))
            rows_lo.append(Sn.lo.reshape(B, J * d, hw))
            rows_hi.append(Sn.hi.reshape(B, J * d, hw))
        rows = Interval(torch.cat(rows_lo, 1), torch.cat(rows_hi, 1))
        rc, rr = rows.midrad()
        oc, orr = matmul_point_right(rc, rr, W.T)
        out = midrad_to_interval(oc, orr)
        val = out[:, 0] + point(b.expand_as(oc[:, 0]))
        T = out[:, 1:1 + d]
        if S is not None:
            S = out[:, 1 + d:]
    out_dim = val.lo.shape[-1]
    d1 = Interval(T.lo.transpose(1, 2), T.hi.transpose(1, 2))  # [B, out, d]
    d2 = None
    if S is not None:
        d2 = Interval(S.lo.reshape(B, J, d, out_dim).permute(0, 3, 1, 2),
                      S.hi.reshape(B, J, d, out_dim).permute(0, 3, 1, 2))
    return NetEnclosure(value=val, d1=d1, d2=d2, pre=pres)


# ----- the gain k(xhat, y) and its derivatives ---------------------------------------------
@dataclass
class GainEnclosure:
    """Enclosures over boxes of k [B, n], dk/dxhat [B, n, n], dk/dy [B, n, p] and (order 2)
    d2k_i / dxhat_j dz_m [B, n, n, d]; plus Jf [B, n, n] and d Jf_ij / dz_m [B, n, n, d]."""

    k: Interval
    dk_dx: Interval
    dk_dy: Interval
    d2k: Interval | None
    jf: Interval
    djf: Interval | None


def gain_enclosure(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
                   order: int = 1, center_pre: list[Interval] | None = None
                   ) -> tuple[GainEnclosure, NetEnclosure]:
    """What `certify.kernels.gain_terms` computes, enclosed over boxes z in [lo, hi]."""
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    ne = network_enclosure(net, lo, hi, order=order, second_cols=n, center_pre=center_pre)
    xl, xh = lo[:, :n], hi[:, :n]
    yI = Interval(lo[:, n:], hi[:, n:])
    K = net.K.to(torch.float64)
    has_K = bool(torch.any(K != 0))
    structural = net.structure == "structural"
    jf = Interval(*jacobian_f_enclosure(system, xl, xh))
    djf = None
    if order >= 2:
        hf = Interval(*hessian_f_enclosure(system, xl, xh))  # [B, n, n, n]
        zpad = torch.zeros(B, n, n, p, dtype=torch.float64)
        djf = Interval(torch.cat([hf.lo, zpad], -1), torch.cat([hf.hi, zpad], -1))
    need_h = structural or has_K
    if need_h:
        hI = Interval(*h_enclosure(system, xl, xh))
        r = yI - hI  # [B, p]
        Hx = Interval(*jacobian_h_enclosure(system, xl, xh))  # [B, p, n]
        # dr/dz [B, p, d]: (-Hx | I)
        eye = torch.eye(p, dtype=torch.float64).expand(B, p, p)
        dr = Interval(torch.cat([-Hx.hi, eye], -1), torch.cat([-Hx.lo, eye], -1))
        d2r = None
        if order >= 2:
            hh = Interval(*hessian_h_enclosure(system, xl, xh))  # [B, p, n, n]
            zpad = torch.zeros(B, p, n, p, dtype=torch.float64)
            d2r = Interval(torch.cat([-hh.hi, zpad], -1), torch.cat([-hh.lo, zpad], -1))
    if not structural:
        k = ne.value
        dk = ne.d1  # [B, n, d]
        d2k = ne.d2  # [B, n, n, d]
    else:
        G = Interval(ne.value.lo.reshape(B, n, p), ne.value.hi.reshape(B, n, p))
        dG = Interval(ne.d1.lo.reshape(B, n, p, d), ne.d1.hi.reshape(B, n, p, d))
        rI = Interval(r.lo[:, None, :], r.hi[:, None, :])
        k = isum(imul(G, rI), 2)
        # dk_i/dz_j = sum_l dG_ilj r_l + G_il dr_lj
        t1 = isum(imul(dG, Interval(r.lo[:, None, :, None], r.hi[:, None, :, None])), 2)
        t2 = isum(imul(Interval(G.lo[..., None], G.hi[..., None]),
                       Interval(dr.lo[:, None], dr.hi[:, None])), 2)
        dk = iadd(t1, t2)
        d2k = None
        if order >= 2:
            d2G = Interval(ne.d2.lo.reshape(B, n, p, n, d), ne.d2.hi.reshape(B, n, p, n, d))
            rr = Interval(r.lo[:, None, :, None, None], r.hi[:, None, :, None, None])
            a1 = imul(d2G, rr)  # sum_l d2G_iljm r_l
            drj = Interval(dr.lo[:, None, :, :n, None], dr.hi[:, None, :, :n, None])
            drm = Interval(dr.lo[:, None, :, None, :], dr.hi[:, None, :, None, :])
            dGj = Interval(dG.lo[:, :, :, :n, None], dG.hi[:, :, :, :n, None])
            dGm = Interval(dG.lo[:, :, :, None, :], dG.hi[:, :, :, None, :])
            a2 = imul(dGj, drm)
            a3 = imul(dGm, drj)
            Ge = Interval(G.lo[..., None, None], G.hi[..., None, None])
            a4 = imul(Ge, Interval(d2r.lo[:, None, :, :n, :], d2r.hi[:, None, :, :n, :]))
            d2k = isum(iadd(iadd(a1, a2), iadd(a3, a4)), 2)
    if has_K:
        Kp = point(K)
        k = iadd(k, isum(imul(Interval(K.expand(B, n, p), K.expand(B, n, p)),
                              Interval(r.lo[:, None, :], r.hi[:, None, :])), 2))
        Kdr = isum(imul(Interval(K[None, :, :, None].expand(B, n, p, d),
                                 K[None, :, :, None].expand(B, n, p, d)),
                        Interval(dr.lo[:, None], dr.hi[:, None])), 2)  # [B, n, d]
        dk = iadd(dk, Kdr)
        if order >= 2:
            Kd2 = isum(imul(Interval(K[None, :, :, None, None].expand(B, n, p, n, d),
                                     K[None, :, :, None, None].expand(B, n, p, n, d)),
                            Interval(d2r.lo[:, None, :, :n, :], d2r.hi[:, None, :, :n, :])), 2)
            d2k = iadd(d2k, Kd2)
        del Kp
    dk_dx = dk[:, :, :n]
    dk_dy = dk[:, :, n:]
    return GainEnclosure(k=k, dk_dx=dk_dx, dk_dy=dk_dy, d2k=d2k, jf=jf, djf=djf), ne


# ----- sound eigenvalue bounds ---------------------------------------------------------
def lam_max_upper_point(S: torch.Tensor) -> torch.Tensor:
    """Sound upper bound of lam_max of point symmetric matrices [..., n, n] -> [...]."""
    n = S.shape[-1]
    if n == 1:
        return S[..., 0, 0]
    if n == 2:
        a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        return _lam2_upper(a, b.abs(), c)
    ev = torch.linalg.eigvalsh(S)[..., -1]
    norm = torch.linalg.matrix_norm(S)  # Frobenius
    margin = 8.0 * (n + 1) * U * up(norm * (1.0 + 4.0 * n * U)) + TINY
    bad = ~torch.isfinite(S).reshape(*S.shape[:-2], -1).all(-1)
    out = up(ev + margin)
    return torch.where(bad, torch.full_like(out, float("nan")), out)


def _lam2_upper(a: torch.Tensor, babs: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Upper bound of (a+c)/2 + sqrt(((a-c)/2)^2 + b^2), rounded up (increasing in a, c, |b|)."""
    m = up(0.5 * up(a + c))
    dlt = up((a - c).abs()) * 0.5
    hyp = widen_up(torch.hypot(dlt, babs))
    return up(m + hyp)


def lam_max_upper_interval(A: Interval) -> torch.Tensor:
    """Sound upper bound of max lam_max over an interval symmetric matrix [..., n, n].

    n <= 2: exact (lam_max is increasing in the diagonal and in |b|). Otherwise the smaller of
    lam_max(centre) + rho(radius) and Gershgorin.
    """
    n = A.lo.shape[-1]
    if n == 1:
        return A.hi[..., 0, 0]
    if n == 2:
        bmag = torch.maximum(A.lo[..., 0, 1].abs(), A.hi[..., 0, 1].abs())
        bmag = torch.maximum(bmag, torch.maximum(A.lo[..., 1, 0].abs(), A.hi[..., 1, 0].abs()))
        return _lam2_upper(A.hi[..., 0, 0], bmag, A.hi[..., 1, 1])
    c, r = A.midrad()
    c = 0.5 * (c + c.transpose(-1, -2))  # exact symmetric centre (any point matrix works)
    r = up(torch.maximum(torch.maximum(A.hi - c, c - A.lo),
                         torch.maximum(A.hi - c, c - A.lo).transpose(-1, -2)))
    cr = up(lam_max_upper_point(c) + rho_upper(r))
    return _nan_min(cr, gershgorin_upper(A))


def gershgorin_upper(A: Interval) -> torch.Tensor:
    n = A.lo.shape[-1]
    mag = torch.maximum(A.lo.abs(), A.hi.abs())
    eye = torch.eye(n, dtype=torch.bool)
    off = torch.where(eye, torch.zeros_like(mag), mag).sum(-1)
    off = up(off * (1.0 + 2.0 * gamma(n)) + n * TINY)
    diag = torch.diagonal(A.hi, dim1=-2, dim2=-1)
    return up(diag + off).max(-1).values


def rho_upper(R: torch.Tensor, iters: int = 8) -> torch.Tensor:
    """Spectral radius bound of non-negative matrices [..., n, n] (Collatz-Wielandt, rounded up).

    rho(R) <= max_i (R u)_i / u_i for any u > 0; u from a few power iterations.
    """
    n = R.shape[-1]
    if n <= 2 and torch.equal(R, R.transpose(-1, -2)):
        return lam_max_upper_point(R).clamp_min(0.0)
    u = torch.ones(*R.shape[:-1], 1, dtype=R.dtype)
    for _ in range(iters):
        u = R @ u
        u = u / u.amax(-2, keepdim=True).clamp_min(1e-300)
    u = u + 1e-6  # strictly positive
    Ru = (R @ u).squeeze(-1)
    Ru = up(Ru * (1.0 + 2.0 * gamma(n)) + n * TINY)
    q = up(Ru / u.squeeze(-1)).amax(-1)
    return q


def _nan_min(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    bad = torch.isnan(a) | torch.isnan(b)
    return torch.where(bad, torch.full_like(a, float("nan")), torch.minimum(a, b))


# ----- D and its bound on boxes --------------------------------------------------------
@dataclass
class Preconditioner:
    """M, Q = M P and C = M P M^T (as intervals) for the congruence A = M D M^T."""

    identity: bool
    M: torch.Tensor
    Q: Interval
    C: Interval
    c_min: float  # lower bound of lam_min(C)
    c_max: float  # upper bound of lam_max(C)


def make_preconditioner(P: torch.Tensor) -> Preconditioner:
    P = P.to(torch.float64)
    n = P.shape[0]
    eye = torch.eye(n, dtype=torch.float64)
    if torch.equal(P, eye):
        return Preconditioner(True, eye, point(eye), point(eye), 1.0, 1.0)
    L = torch.linalg.cholesky(P)
    M = torch.linalg.solve_triangular(L, eye, upper=False)
    Q = imatmul(point(M), point(P))
    C = imatmul(Q, point(M.T))
    dev = Interval(C.lo - eye, C.hi - eye)
    e = float(rho_upper(torch.maximum(dev.lo.abs(), dev.hi.abs())))
    return Preconditioner(False, M, Q, C, float(down(torch.tensor(1.0 - e))),
                          float(up(torch.tensor(1.0 + e))))


def _congruence(pc: Preconditioner, Jm: Interval) -> Interval:
    """He{Q J M^T} for interval J [B, n, n] (or [B, d, n, n] stacked)."""
    if pc.identity:
        return isym(Jm)
    QJ = imatmul(Interval(pc.Q.lo.expand_as(Jm.lo), pc.Q.hi.expand_as(Jm.hi)), Jm)
    MT = pc.M.T.expand_as(Jm.lo)
    return isym(imatmul(QJ, point(MT)))


@dataclass
class BoxBounds:
    """Per box: upper bounds of max lam_max(A) (A = M D M^T), plain and Taylor, and the
    per-dimension width contributions used to choose the split."""

    upper: torch.Tensor  # [B]  min of the two (NaN: unknown)
    plain: torch.Tensor  # [B]
    taylor: torch.Tensor  # [B]
    score: torch.Tensor  # [B, d] split score per dimension


def mpdi_box_bounds(problem: Problem, lo: torch.Tensor, hi: torch.Tensor, lam: float,
                    pc: Preconditioner | None = None, taylor: bool | str = True) -> BoxBounds:
    """Sound upper bounds of max over each box of lam_max(M D M^T), D with rate lam.

    taylor: True (first-order Taylor models through the network, the default), "interval"
    (mean-value form with interval second derivatives) or False (plain interval only)."""
    system, net = problem.system, problem.network
    if pc is None:
        pc = make_preconditioner(problem.P_t)
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    zc = 0.5 * (lo + hi)
    zr = up(torch.maximum(hi - zc, zc - lo))
    lamC = imul(pc.C, const_lam(2.0 * lam, pc.C))
    # centre pass (thin intervals around A(c)) and box pass
    gc, nec = gain_enclosure(system, net, zc, zc, order=1)
    order = 2 if taylor == "interval" else 1
    gb, _ = gain_enclosure(system, net, lo, hi, order=order, center_pre=nec.pre)
    Ab = iadd(_congruence(pc, iadd(gb.jf, gb.dk_dx)), _bcast(lamC, B))
    plain = lam_max_upper_interval(Ab)
    if not taylor:
        score = zr * (1.0 / (zr.amax(-1, keepdim=True) + 1e-300))
        return BoxBounds(plain, plain, torch.full_like(plain, float("inf")), score)
    if taylor == "interval":
        Ac = iadd(_congruence(pc, iadd(gc.jf, gc.dk_dx)), _bcast(lamC, B))
        dJ = iadd(gb.djf, gb.d2k)  # [B, n, n, d]
        dA = _congruence(pc, Interval(dJ.lo.permute(0, 3, 1, 2), dJ.hi.permute(0, 3, 1, 2)))
        tay, score = taylor_upper(Ac, dA, zr)
    else:
        Jt = jcl_taylor(system, net, lo, hi)
        tay, score = tm_lam_upper(tm_congruence(pc, Jt, lam, zr), zr)
    upper = _nan_min(plain, tay)
    return BoxBounds(upper, plain, tay, score)


def const_lam(v: float, like: Interval) -> Interval:
    t = torch.full_like(like.lo, v)
    return Interval(down(t), up(t))


def _bcast(a: Interval, B: int) -> Interval:
    return Interval(a.lo.expand(B, *a.lo.shape[-2:]), a.hi.expand(B, *a.hi.shape[-2:]))


_VERTEX_CACHE: dict[int, torch.Tensor] = {}


def _vertices(d: int) -> torch.Tensor:
    if d not in _VERTEX_CACHE:
        idx = torch.arange(2**d)
        bits = (idx[:, None] >> torch.arange(d)[None, :]) & 1
        _VERTEX_CACHE[d] = (2.0 * bits - 1.0).to(torch.float64)  # [V, d]
    return _VERTEX_CACHE[d]


def taylor_upper(Ac: Interval, dA: Interval, zr: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Second-order bound: max over vertices of lam_max(A(c) + sum d_m G_m) + rho(remainder).

    Ac [B, n, n] encloses A at the box centres; dA [B, d, n, n] encloses dA/dz_m over the
    boxes; zr [B, d] radii. Returns (bound [B], split score [B, d]).
    """
    B, d, n, _ = dA.lo.shape
    G, R = dA.midrad()
    G = 0.5 * (G + G.transpose(-1, -2))
    R = up(torch.maximum(torch.maximum(dA.hi - G, G - dA.lo),
                         torch.maximum(dA.hi - G, G - dA.lo).transpose(-1, -2)))
    C0, Cr = Ac.midrad()
    C0 = 0.5 * (C0 + C0.transpose(-1, -2))
    Cr = up(torch.maximum(torch.maximum(Ac.hi - C0, C0 - Ac.lo),
                          torch.maximum(Ac.hi - C0, C0 - Ac.lo).transpose(-1, -2)))
    zr4 = zr[:, :, None, None]
    rG = zr4 * G  # [B, d, n, n]
    g = gamma(d + 5)
    absum = C0.abs() + rG.abs().sum(1)
    rem = Cr + (zr4 * R).sum(1)
    rem = up(rem * (1.0 + g) + g * absum * (1.0 + g) + (d + 2) * TINY)
    if d <= MAX_VERTEX_DIM:
        V = _vertices(d)  # [V, d]
        S = C0[:, None] + torch.einsum("vd,bdij->bvij", V, rG)  # [B, V, n, n]
        S = 0.5 * (S + S.transpose(-1, -2))
        lv = lam_max_upper_point(S).amax(-1)
    else:
        rem = up(rem + rG.abs().sum(1) * (1.0 + g))
        lv = lam_max_upper_point(C0)
    bound = up(lv + rho_upper(rem))
    # split score: first-order variation plus remainder, per dimension
    gn = torch.linalg.matrix_norm(rG) + torch.linalg.matrix_norm(zr4 * R)  # [B, d]
    return bound, gn


def to_lam_max_D(upper_A: torch.Tensor, P: torch.Tensor, pc: Preconditioner) -> torch.Tensor:
    """Convert a bound on lam_max(M D M^T) to one on lam_max(D) (same sign; D = L A L^T)."""
    if pc.identity:
        return upper_A
    ev = torch.linalg.eigvalsh(P.to(torch.float64))
    smax = float(ev[-1]) * (1 + 1e-10)
    smin = float(ev[0]) * (1 - 1e-10)
    # ||L||^2 = lam_max(P), sigma_min(L)^2 = lam_min(P); M = L^-1 up to rounding (relative
    # 1e-10 slack covers it for any well-conditioned P)
    return torch.where(upper_A >= 0, up(upper_A * smax), up(upper_A * smin))


def manifold_enclosure(system: System, lo: torch.Tensor, hi: torch.Tensor, P: torch.Tensor,
                       lam: float, Z: torch.Tensor) -> torch.Tensor:
    """Upper bound of lam_max(Z^T (He{P Jf} + 2 lam P) Z) over x-boxes [B, n] (Z point)."""
    jf = Interval(*jacobian_f_enclosure(system, lo.to(torch.float64), hi.to(torch.float64)))
    B = lo.shape[0]
    Pi = point(P.to(torch.float64).expand(B, *P.shape))
    S = iadd(isym(imatmul(Pi, jf)), imul(Pi, const_lam(2.0 * lam, Pi)))
    Zt = point(Z.T.expand(B, *Z.T.shape))
    Zp = point(Z.expand(B, *Z.shape))
    Q = imatmul(imatmul(Zt, S), Zp)
    Q = isym(Q)
    return lam_max_upper_interval(Q)


def residual_box_upper(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Upper bound of ||k(x, h(x))||_2 over x-boxes [B, n] and its value at the centres.

    Mean-value form of g(x) = k(x, h(x)): g(x) in g(c) + [dk/dx + dk/dy Jh](box) (x - c),
    intersected with the plain enclosure of k over box x h(box).
    """
    n = system.n
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    xc = 0.5 * (lo + hi)
    xr = up(torch.maximum(hi - xc, xc - lo))
    hc = Interval(*h_enclosure(system, xc, xc))
    hb = Interval(*h_enclosure(system, lo, hi))
    gc, nec = gain_enclosure(system, net, torch.cat([xc, hc.lo], 1), torch.cat([xc, hc.hi], 1))
    gb, _ = gain_enclosure(system, net, torch.cat([lo, hb.lo], 1), torch.cat([hi, hb.hi], 1))
    Hx = Interval(*jacobian_h_enclosure(system, lo, hi))  # [B, p, n]
    dg = iadd(gb.dk_dx, isum(imul(Interval(gb.dk_dy.lo[..., None], gb.dk_dy.hi[..., None]),
                                  Interval(Hx.lo[:, None], Hx.hi[:, None])), 2))  # [B, n, n]
    mv = iadd(gc.k, isum(imul(dg, Interval(-xr[:, None, :], xr[:, None, :])), 2))
    kk = intersect(mv, gb.k)
    mag = torch.maximum(kk.lo.abs(), kk.hi.abs())
    norm = up(torch.sqrt(up((mag * mag).sum(-1) * (1.0 + 2.0 * gamma(n + 1)))))
    cen = torch.sqrt((gc.k.mid() ** 2).sum(-1))
    return norm, cen


def dk_dy_box_upper(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Upper bound of ||dk/dy||_2 (via Frobenius of the entry magnitudes) over z-boxes."""
    gb, _ = gain_enclosure(system, net, lo, hi)
    zc = 0.5 * (lo + hi).to(torch.float64)
    gc, _ = gain_enclosure(system, net, zc, zc)
    mag = torch.maximum(gb.dk_dy.lo.abs(), gb.dk_dy.hi.abs())
    nrm = up(torch.sqrt(up((mag * mag).sum((-1, -2)) * (1.0 + 2.0 * gamma(mag[0].numel() + 1)))))
    cen = torch.linalg.matrix_norm(gc.dk_dy.mid(), ord=2)
    return nrm, cen


__all__ = [
    "NetEnclosure", "network_enclosure", "GainEnclosure", "gain_enclosure",
    "lam_max_upper_point", "lam_max_upper_interval", "gershgorin_upper", "rho_upper",
    "Preconditioner", "make_preconditioner", "BoxBounds", "mpdi_box_bounds", "taylor_upper",
    "to_lam_max_D", "manifold_enclosure", "residual_box_upper", "dk_dy_box_upper",
    "isum", "iadd", "isym", "intersect", "math",
]


# ----- first-order Taylor models: q(z) in c + g . (z - zc) + [-e, e] ------------------------
@dataclass
class TM:
    """First-order Taylor model over boxes: value c [...], coefficients g [..., d] (point),
    remainder e [...] >= 0, valid for every z in the box with |z - zc| <= r.

    Linear maps act exactly on (c, g) and only the remainder wraps, so dependencies on the
    box coordinates survive the layers; float errors of c and g are absorbed into e."""

    c: torch.Tensor
    g: torch.Tensor
    e: torch.Tensor


def _gr(g: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Upper bound of sum_m |g_m| r_m, r broadcast over the leading dims of g."""
    d = g.shape[-1]
    return up((g.abs() * r).sum(-1) * (1.0 + 2.0 * gamma(d + 1)))


def _rshape(r: torch.Tensor, ndim: int) -> torch.Tensor:
    """Reshape radii [B, d] to broadcast against a coefficient tensor with `ndim` dims."""
    return r.reshape(r.shape[0], *([1] * (ndim - 2)), r.shape[1])


def tm_from_intervals(center: Interval, deriv: Interval, r: torch.Tensor) -> TM:
    """TM from a thin enclosure at the centre and an enclosure of the gradient over the box
    (mean-value theorem): center [B, ...], deriv [B, ..., d]."""
    c, cr = center.midrad()
    g, gr_ = deriv.midrad()
    rr = _rshape(r, g.ndim)
    e = up(cr + up((gr_ * rr).sum(-1) * (1.0 + 2.0 * gamma(g.shape[-1] + 1))))
    return TM(c, g, e)


def tm_absorb(c: torch.Tensor, g: torch.Tensor, e: torch.Tensor, r: torch.Tensor, k: int) -> TM:
    """Add gamma_k (|c| + sum |g| r) to the remainder (rounding of c and g), rounded up."""
    gk = gamma(k)
    rr = _rshape(r, g.ndim)
    e = up((e + gk * (c.abs() + _gr(g, rr))) * (1.0 + 2.0 * gk) + k * TINY)
    return TM(c, g, e)


def tm_linear(t: TM, W: torch.Tensor, b: torch.Tensor | None, r: torch.Tensor) -> TM:
    """x -> x @ W (+ b) on the last value dim: t.c [..., k], t.g [..., k, d]; W [k, m]."""
    k = W.shape[0]
    gk = gamma(k + 2)
    c = t.c @ W
    if b is not None:
        c = c + b
    g = (t.g.transpose(-1, -2) @ W).transpose(-1, -2)
    rr = _rshape(r, t.g.ndim)
    slack = t.e + gk * (t.c.abs() + _gr(t.g, rr))
    e = slack @ W.abs()
    if b is not None:
        e = e + gk * (b.abs() + c.abs())
    e = up(e * (1.0 + 2.0 * gk) + k * TINY)
    return TM(c, g, e)


def tm_rho(t: TM, r: torch.Tensor) -> torch.Tensor:
    """Radius of the range of t over the box: sum |g| r + e (rounded up)."""
    return up(_gr(t.g, _rshape(r, t.g.ndim)) + t.e)


_EPS = 2.0**-52


def tm_tanh_and_dtanh(t: TM, r: torch.Tensor) -> tuple[TM, TM]:
    """TMs of tanh(q) and tanh'(q) for a TM q (second-order Lagrange remainders, with the
    range of tanh'' from its interval rule and |tanh'''| <= 2)."""
    rho = tm_rho(t, r)
    rng = Interval(down(t.c - rho), up(t.c + rho))
    M2 = d2tanh_enclosure(rng).mag()
    t0 = torch.tanh(t.c)
    s0 = 1.0 - t0 * t0
    s2 = -2.0 * t0 * s0
    gr = _gr(t.g, _rshape(r, t.g.ndim))
    ga = t.g * s0.unsqueeze(-1)
    err_t0 = 4.0 * _EPS * t0.abs() + 4 * TINY
    e_a = (torch.clamp(s0 + 16 * _EPS, max=1.0) * t.e + 0.5 * M2 * rho * rho
           + 16 * _EPS * gr + err_t0 + 4 * U * (t0.abs() + _gr(ga, _rshape(r, ga.ndim))))
    A = TM(t0, ga, up(e_a * (1.0 + 8 * U) + 4 * TINY))
    gs = t.g * s2.unsqueeze(-1)
    e_s = ((s2.abs() + 64 * _EPS) * t.e + 1.0 * rho * rho  # 0.5 * max|tanh'''| (<= 2)
           + 64 * _EPS * gr + 32 * _EPS + 4 * U * (s0.abs() + _gr(gs, _rshape(r, gs.ndim))))
    S = TM(s0, gs, up(e_s * (1.0 + 8 * U) + 4 * TINY))
    return A, S


def tm_mul(a: TM, b: TM, r: torch.Tensor) -> TM:
    """Elementwise product (broadcasting)."""
    c = a.c * b.c
    g = a.c.unsqueeze(-1) * b.g + b.c.unsqueeze(-1) * a.g
    ra = tm_rho(a, r) if a.g.ndim else a.e
    rb = tm_rho(b, r)
    ga = _gr(a.g, _rshape(r, a.g.ndim))
    gb = _gr(b.g, _rshape(r, b.g.ndim))
    e = a.c.abs() * b.e + b.c.abs() * a.e + (ga + a.e) * (gb + b.e)
    del ra, rb
    e = up(e * (1.0 + 8 * U))
    return tm_absorb(c, g, e, r, 4)


def tm_sum(t: TM, dim: int, r: torch.Tensor) -> TM:
    """Sum over value dim `dim` (non-negative index into c's dims)."""
    k = t.c.shape[dim]
    c = t.c.sum(dim)
    g = t.g.sum(dim)
    e = t.e.sum(dim)
    extra = gamma(k + 1) * (t.c.abs().sum(dim) + _gr(t.g, _rshape(r, t.g.ndim)).sum(dim))
    e = up((e + extra) * (1.0 + 2.0 * gamma(k + 1)) + k * TINY)
    return TM(c, g, e)


def tm_add(a: TM, b: TM, r: torch.Tensor) -> TM:
    c = a.c + b.c
    g = a.g + b.g
    e = up(a.e + b.e)
    return tm_absorb(c, g, e, r, 2)


def tm_point(x: torch.Tensor, d: int) -> TM:
    z = torch.zeros(*x.shape, d, dtype=x.dtype)
    return TM(x, z, torch.zeros_like(x))


def tm_index(t: TM, idx: tuple) -> TM:
    """Index the value dims (the coefficient dim stays last)."""
    return TM(t.c[idx], t.g[idx + (slice(None),)], t.e[idx])


def network_taylor(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                   ) -> tuple[TM, TM, torch.Tensor]:
    """First-order TMs over boxes of N(z) [B, out] and dN/dz [B, out, d]; returns radii r."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    weights = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
    W0, b0 = weights[0]
    eye = torch.eye(d, dtype=torch.float64).expand(B, d, d)
    ztm = TM(zc, eye, torch.zeros_like(zc))
    val = tm_linear(ztm, W0.T, b0, r)  # [B, h]
    h0 = W0.shape[0]
    T = TM(W0.T.expand(B, d, h0), torch.zeros(B, d, h0, d, dtype=torch.float64),
           torch.zeros(B, d, h0, dtype=torch.float64))
    for W, b in weights[1:]:
        a, s = tm_tanh_and_dtanh(val, r)
        s_b = TM(s.c.unsqueeze(1), s.g.unsqueeze(1), s.e.unsqueeze(1))
        Tn = tm_mul(s_b, T, r)  # [B, d, h]
        val = tm_linear(a, W.T, b, r)
        T = tm_linear(Tn, W.T, None, r)
    d1 = TM(T.c.transpose(1, 2), T.g.transpose(1, 2), T.e.transpose(1, 2))  # [B, out, d]
    return val, d1, r


def jcl_taylor(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor) -> TM:
    """TM of the closed-loop Jacobian Jf(xhat) + dk/dxhat(xhat, y) over z-boxes -> [B, n, n]."""
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    val, d1, r = network_taylor(net, lo, hi)
    zc = 0.5 * (lo + hi)
    xc = zc[:, :n]
    xl, xh = lo[:, :n], hi[:, :n]
    rx = r[:, :n]
    zpad = torch.zeros(B, n, n, p, dtype=torch.float64)

    def pad(iv: Interval) -> Interval:  # derivative w.r.t. x only -> pad y columns with 0
        z = torch.zeros(*iv.lo.shape[:-1], p, dtype=torch.float64)
        return Interval(torch.cat([iv.lo, z], -1), torch.cat([iv.hi, z], -1))

    jf = tm_from_intervals(Interval(*jacobian_f_enclosure(system, xc, xc)),
                           pad(Interval(*hessian_f_enclosure(system, xl, xh))), r)
    del zpad, rx
    K = net.K.to(torch.float64)
    has_K = bool(torch.any(K != 0))
    structural = net.structure == "structural"
    if structural or has_K:
        Jh = tm_from_intervals(Interval(*jacobian_h_enclosure(system, xc, xc)),
                               pad(Interval(*hessian_h_enclosure(system, xl, xh))), r)  # [B,p,n]
    if not structural:
        dkdx = tm_index(d1, (slice(None), slice(None), slice(0, n)))
    else:
        hc = Interval(*h_enclosure(system, xc, xc))
        jhb = Interval(*jacobian_h_enclosure(system, xl, xh))
        eye_p = torch.eye(p, dtype=torch.float64).expand(B, p, p)
        dr_box = Interval(torch.cat([-jhb.hi, eye_p], -1), torch.cat([-jhb.lo, eye_p], -1))
        yc = Interval(zc[:, n:], zc[:, n:])
        rt = tm_from_intervals(yc - hc, dr_box, r)  # r = y - h(x) [B, p]
        G = TM(val.c.reshape(B, n, p), val.g.reshape(B, n, p, d), val.e.reshape(B, n, p))
        dG = TM(d1.c.reshape(B, n, p, d)[..., :n], d1.g.reshape(B, n, p, d, d)[..., :n, :],
                d1.e.reshape(B, n, p, d)[..., :n])  # [B, n, p, n]
        # dk_i/dx_j = sum_l dG_ilj r_l - G_il Jh_lj
        r_b = TM(rt.c[:, None, :, None], rt.g[:, None, :, None, :], rt.e[:, None, :, None])
        t1 = tm_sum(tm_mul(dG, r_b, r), 2, r)
        G_b = TM(G.c[..., None], G.g[:, :, :, None, :], G.e[..., None])
        Jh_b = TM(Jh.c[:, None], Jh.g[:, None], Jh.e[:, None])
        t2 = tm_sum(tm_mul(G_b, Jh_b, r), 2, r)
        dkdx = tm_add(t1, TM(-t2.c, -t2.g, t2.e), r)
    if has_K:
        # - K Jh: point matrix K [n, p] times the TM Jh [B, p, n]
        KJ = TM(K @ Jh.c, torch.einsum("ip,bpjd->bijd", K, Jh.g), K.abs() @ Jh.e)
        KJ = tm_absorb(KJ.c, KJ.g, up(KJ.e * (1 + 2 * gamma(p + 1))), r, p + 2)
        dkdx = tm_add(dkdx, TM(-KJ.c, -KJ.g, KJ.e), r)
    return tm_add(jf, dkdx, r)


def tm_congruence(pc: Preconditioner, J: TM, lam: float, r: torch.Tensor) -> TM:
    """TM of A = He{Q J M^T} + 2 lam C (exact congruence when P = I)."""
    n = J.c.shape[-1]
    if pc.identity:
        A = J
    else:
        Qc, Qr = pc.Q.midrad()
        M = pc.M
        # Q J M^T with Q = Qc + [-Qr, Qr]: the Qr part goes into the remainder
        QJ_c = Qc @ J.c @ M.T
        QJ_g = torch.einsum("ik,bkld,jl->bijd", Qc, J.g, M)
        Jmag = up(J.c.abs() + tm_rho(J, r))
        e = Qc.abs() @ J.e @ M.T.abs() + Qr @ Jmag @ M.T.abs()
        e = up(e * (1.0 + 2.0 * gamma(2 * n + 2)))
        A = tm_absorb(QJ_c, QJ_g, e, r, 2 * n + 2)
    # He{.}
    c = 0.5 * (A.c + A.c.transpose(1, 2))
    g = 0.5 * (A.g + A.g.transpose(1, 2))
    e = 0.5 * up(A.e + A.e.transpose(1, 2))
    A = tm_absorb(c, g, up(e), r, 2)
    lamC = imul(pc.C, const_lam(2.0 * lam, pc.C))
    lc, lr = lamC.midrad()
    A = tm_absorb(A.c + lc, A.g, up(A.e + lr), r, 2)
    return A


def tm_lam_upper(A: TM, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """max over the box of lam_max(A(z)) <= max_vertices lam_max(c + sum_m s_m r_m g_m)
    + rho(e + rounding) (convexity of lam_max in the affine part)."""
    B, n, _, d = A.g.shape
    rG = (A.g * r[:, None, None, :]).permute(0, 3, 1, 2)  # [B, d, n, n]
    gk = gamma(d + 5)
    absum = A.c.abs() + rG.abs().sum(1)
    rem = up((A.e + gk * absum) * (1.0 + 2.0 * gk) + (d + 2) * TINY)
    rem = torch.maximum(rem, rem.transpose(1, 2))
    if d <= MAX_VERTEX_DIM:
        V = _vertices(d)
        S = A.c[:, None] + torch.einsum("vd,bdij->bvij", V, rG)
        S = 0.5 * (S + S.transpose(-1, -2))
        lv = lam_max_upper_point(S).amax(-1)
    else:
        rem = up(rem + rG.abs().sum(1) * (1.0 + gk))
        lv = lam_max_upper_point(A.c)
    rr = rho_upper(rem)
    bound = up(lv + rr)
    # split score: first-order variation per dimension plus the remainder shared out in
    # proportion to the radii (the remainder grows with every radius)
    share = r / r.sum(-1, keepdim=True).clamp_min(1e-300)
    score = torch.linalg.matrix_norm(rG) + rr.unsqueeze(-1) * share  # [B, d]
    return bound, score
