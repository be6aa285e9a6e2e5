"""First-order Taylor models over boxes: q(z) in c + g . (z - zc) + [-e, e].

Linear maps act exactly on (c, g) and only the remainder wraps, so dependencies on the box
coordinates survive the layers. Rounding: the float errors of c and g are absorbed into e with
Higham's gamma_k |.| bounds, rounded up; the activation's Lagrange remainders use the
enclosure of its second derivative over the range and the bound `d3_bound` on the third
(tanh: 2). An activation without a third derivative (ELU, d3_bound = inf) gets a first-order
remainder for f' instead: f'(q) - f'(c) lies in f''(range) (q - c) (f' is Lipschitz).
tanh keeps its hand-written error terms (`tm_tanh_and_dtanh`); every other activation takes
the float errors of its centre values f(c), f'(c), f''(c) from the radii of its own point
enclosures (`certify.activations`: widened libm rules, outward-rounded arithmetic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from certify.activations import Activation
from certify.activations.tanh import d2tanh_enclosure
from certify.bounds.decide import decide_affine_family, vertex_matrices
from certify.bounds.eigen import (
    MAX_VERTEX_DIM,
    hertz_upper,
    lam_max_upper_point,
    rho_upper,
    vertex_max_upper,
)
from certify.bounds.interval_ops import const_lam
from certify.bounds.preconditioner import Preconditioner
from certify.gain.propagate import GainValues
from certify.intervals import TINY, Interval, down, gamma, imul, up
from certify.network import GainNetwork
from certify.system import System
from certify.system_enclosures import (
    h_enclosure,
    jacobian_h_enclosure,
    residual_jacobian,
)

U = 2.0**-53
#: up to this n, `tm_lam_upper` also takes Hertz's vertex bound (the remainder entrywise,
#: exactly: 2^(n-1) sign patterns per vertex)
HERTZ_MAX_N = 3


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


def tm_activation(act: Activation, t: TM, r: torch.Tensor) -> tuple[TM, TM]:
    """TMs of f(q) and f'(q) for a TM q and the activation `act` (tanh: `tm_tanh_and_dtanh`).

    f(q) = f(c) + f'(c) (q - c) + f''(xi) (q - c)^2 / 2 and, when f''' exists,
    f'(q) = f'(c) + f''(c) (q - c) + f'''(xi) (q - c)^2 / 2, |q - c| <= rho; else (ELU)
    f'(q) = f'(c) + f''(c) (q - c) + (mu - f''(c)) (q - c), mu in f''(range) (f' Lipschitz).
    The centre values are the midpoints of point enclosures; their radii (the float errors)
    go into the remainders, as does the error of the products g f'(c), g f''(c).
    """
    if act.name == "tanh":
        return tm_tanh_and_dtanh(t, r)
    rho = tm_rho(t, r)
    rng = Interval(down(t.c - rho), up(t.c + rho))
    d2r = act.enclose_d2(rng)
    M2 = d2r.mag()
    cI = Interval(t.c, t.c)
    t0, et0 = act.enclose_f(cI).midrad()
    s0, es0 = act.enclose_d1(cI).midrad()
    s2, es2 = act.enclose_d2(cI).midrad()
    gr = _gr(t.g, _rshape(r, t.g.ndim))
    ga = t.g * s0.unsqueeze(-1)
    e_a = ((s0.abs() + es0) * t.e + es0 * gr + 0.5 * M2 * rho * rho + et0
           + 4 * U * (t0.abs() + _gr(ga, _rshape(r, ga.ndim))))
    A = TM(t0, ga, up(e_a * (1.0 + 8 * U) + 4 * TINY))
    gs = t.g * s2.unsqueeze(-1)
    if math.isfinite(act.d3_bound):
        rem2 = 0.5 * act.d3_bound * rho * rho
    else:  # f'' bounded, not continuous: |mu - f''(c)| <= max(hi - s2, s2 - lo)
        rem2 = torch.maximum(up(d2r.hi - s2), up(s2 - d2r.lo)) * rho
    e_s = ((s2.abs() + es2) * t.e + es2 * gr + rem2 + es0
           + 4 * U * (s0.abs() + _gr(gs, _rshape(r, gs.ndim))))
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
    z = torch.zeros(*x.shape, d, dtype=x.dtype, device=x.device)
    return TM(x, z, torch.zeros_like(x))


def tm_index(t: TM, idx: tuple) -> TM:
    """Index the value dims (the coefficient dim stays last)."""
    return TM(t.c[idx], t.g[idx + (slice(None),)], t.e[idx])


def network_taylor(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                   ) -> tuple[TM, TM, torch.Tensor]:
    """First-order TMs over boxes of N(z) [B, out] and dN/dz [B, out, d]; returns radii r.

    `certify.gain.propagate` in `certify.gain.taylor.TaylorArithmetic` (the one propagation
    of the gain)."""
    from certify.gain.propagate import propagate  # certify.gain.taylor imports this module
    from certify.gain.taylor import TaylorArithmetic

    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    out = propagate(net.spec(torch.float64, detach=True), TaylorArithmetic(zc, r), None,
                    lo.shape[1])
    return out.value, out.jac, r


def gain_taylor(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
                net_tms: tuple[TM, TM, torch.Tensor] | None = None, with_k: bool = True,
                with_dy: bool = True) -> GainValues:
    """TMs over z-boxes of k [B, n], dk/dxhat [B, n, n] and (with_dy) dk/dy [B, n, p].

    `certify.gain.compose` in `TaylorArithmetic` on the network's models and the models of
    r = y - h(xhat) and dh/dxhat (mean-value forms from the centre values and the box
    enclosures of their derivatives). net_tms: (value [B, out], Jacobian [B, out, d], radii)
    of the network from elsewhere (e.g. tightened by linear bound propagation); default
    `network_taylor`."""
    from certify.bounds.system_taylor import jacobian_tm  # it imports this module
    from certify.gain.propagate import NetOutput, compose  # certify.gain.taylor imports us
    from certify.gain.taylor import TaylorArithmetic

    n = system.n
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    val, d1, r = network_taylor(net, lo, hi) if net_tms is None else net_tms
    spec = net.spec(torch.float64, detach=True)
    zc = 0.5 * (lo + hi)
    xc, xl, xh = zc[:, :n], lo[:, :n], hi[:, :n]
    rt = Jh = None
    if spec.needs_h:
        Jh = jacobian_tm(system, "h", lo, hi, r)  # [B, p, n]
    if spec.structural or (spec.has_K and with_k):  # what compose reads r for
        hc = Interval(*h_enclosure(system, xc, xc))
        jhb = Interval(*jacobian_h_enclosure(system, xl, xh))
        dr_box = residual_jacobian(jhb)
        yc = Interval(zc[:, n:], zc[:, n:])
        rt = tm_from_intervals(yc - hc, dr_box, r)  # r = y - h(x) [B, p]
    return compose(spec, TaylorArithmetic(zc, r), NetOutput(val, d1), rt, Jh,
                   with_dy=with_dy, with_k=with_k)


def jcl_taylor(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
               net_tms: tuple[TM, TM, torch.Tensor] | None = None) -> TM:
    """TM of the closed-loop Jacobian Jf(xhat) + dk/dxhat(xhat, y) over z-boxes -> [B, n, n]
    (dk/dxhat from `gain_taylor`; net_tms as there)."""
    from certify.bounds.system_taylor import jacobian_tm  # it imports this module

    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    net_tms = network_taylor(net, lo, hi) if net_tms is None else net_tms
    r = net_tms[2]
    dkdx = gain_taylor(system, net, lo, hi, net_tms, with_k=False, with_dy=False).dk_dx
    return tm_add(jacobian_tm(system, "f", lo, hi, r), dkdx, r)


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


def tm_lam_upper(A: TM, r: torch.Tensor, parts: bool = False, level: float | None = None):
    """max over the box of lam_max(A(z)) <= max_vertices lam_max(c + sum_m s_m r_m g_m)
    + rho(e + rounding) (convexity of lam_max in the affine part); for n <= 3 the smaller
    max_vertices hertz_upper(vertex matrix, e + rounding) (the remainder entrywise, not by its
    spectral radius).

    level (a decision: only "bound <= level" matters; n >= 4): the vertex matrices are first
    tested against t = down(level' - rho) by the certified Cholesky test
    (`certify.bounds.eigen.lam_max_at_most`), level' = level - 1e-12 (1 + |level|), unless
    (without `parts`) Weyl's bound of the affine part is already <= t; a box whose every vertex
    passes (or whose Weyl bound does) reports the bound level' (proved: vertex max <= t,
    t + rho <= level'), without vertex eigenvalues. The others (their bound then only ranks
    them in the branch and bound: a completed proof splits the same boxes whatever it is, a
    budgeted run's order depends on it) get Weyl's lam_max(c) + sum_m ||r_m g_m||_F (one
    eigenproblem per box, `_weyl_upper`); with `parts` (the vertex part is wanted), the
    vertices that fail are tested again at t + k s, s = rho + 1e-3 (1 + |level|), k = 1/4, 1,
    4 (their bound: the first level passed) and only the rest get eigenvalue bounds."""
    B, n, _, d = A.g.shape
    rG = (A.g * r[:, None, None, :]).permute(0, 3, 1, 2)  # [B, d, n, n]
    gk = gamma(d + 5)
    absum = A.c.abs() + rG.abs().sum(1)
    rem = up((A.e + gk * absum) * (1.0 + 2.0 * gk) + (d + 2) * TINY)
    rem = torch.maximum(rem, rem.transpose(1, 2))
    vertex = d <= MAX_VERTEX_DIM
    if not vertex:
        rem = up(rem + rG.abs().sum(1) * (1.0 + gk))
    decide_lower = vertex and level is not None and n >= 4 and not parts
    # the vertex matrices; the Cholesky decision reads their lower triangles only (as LAPACK),
    # which enclose D's like the whole matrices do, so there they are built unsymmetrised and
    # only for the boxes that need them (below)
    S = vertex_matrices(A.c, rG, sym=True) if vertex and not decide_lower else None
    rr = rho_upper(rem)
    decided = None
    if vertex and level is not None and n >= 4:
        lvl = float(level) - 1e-12 * (1.0 + abs(float(level)))
        t = down(lvl - rr)  # proved vertex max <= t  =>  lv + rr <= lvl
        if parts:  # the vertex part itself is wanted (where the linear bounds are tried)
            lv, decided = vertex_max_upper(S, t, step=rr + 1e-3 * (1.0 + abs(lvl)))
        else:
            # Weyl, the vertices, then the box's own congruence (`certify.bounds.decide`)
            decided, lv = decide_affine_family(A.c, rG, rem, rr, lvl)
            lv = torch.where(decided, t, lv)
    elif S is not None:
        lv = lam_max_upper_point(S).amax(-1)
    else:
        lv = lam_max_upper_point(A.c)
    bound = up(lv + rr)
    if decided is not None:
        bound = torch.where(decided, torch.full_like(bound, lvl), bound)
    if S is not None and n <= HERTZ_MAX_N:
        hz = hertz_upper(S, rem.unsqueeze(1).expand_as(S)).amax(-1)
        bound = torch.where(torch.isnan(bound) | torch.isnan(hz), bound + hz,
                            torch.minimum(bound, hz))
    # split score: first-order variation per dimension plus the remainder shared out in
    # proportion to the radii (the remainder grows with every radius)
    share = r / r.sum(-1, keepdim=True).clamp_min(1e-300)
    score = torch.linalg.matrix_norm(rG) + rr.unsqueeze(-1) * share  # [B, d]
    if parts:  # also the vertex (affine) part alone: a prediction of what tighter remainders
        return bound, score, lv  # could reach
    return bound, score
