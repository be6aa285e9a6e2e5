"""First-order Taylor models over boxes: q(z) in c + g . (z - zc) + [-e, e].

Linear maps act exactly on (c, g) and only the remainder wraps, so dependencies on the box
coordinates survive the layers. Rounding: the float errors of c and g are absorbed into e with
Higham's gamma_k |.| bounds, rounded up; the activation's Lagrange remainders use the
enclosure of its second derivative over the range and the bound `d3_bound` on the third
(tanh: 2). An activation without a third derivative (ELU, d3_bound = inf) gets a first-order
remainder for f' instead: f'(q) - f'(c) lies in f''(range) (q - c) (f' is Lipschitz).
tanh keeps its hand-written error terms (`tm_tanh_and_dtanh`); every other activation takes
the float errors of its centre values f(c), f'(c), f''(c) from the radii of its own point
enclosures (`certify.model.activations`: widened libm rules, outward-rounded arithmetic).
"""

from __future__ import annotations

import torch

from certify.arith.eigen import (
    MAX_VERTEX_DIM,
    hertz_upper,
    lam_max_upper_point,
    rho_upper,
    vertex_max_upper,
)
from certify.arith.intervals import TINY, Interval, down, gamma, up
from certify.arith.taylor import TM, tm_absorb, tm_add, tm_from_intervals, tm_rho
from certify.enclose.decide import decide_affine_family, vertex_matrices
from certify.enclose.preconditioner import Preconditioner
from certify.enclose.system_taylor import jacobian_tm
from certify.enclose.whole_box import decide_whole_box
from certify.model.gain.propagate import GainValues, NetOutput, compose, propagate
from certify.model.gain.taylor import TaylorArithmetic
from certify.model.network import GainNetwork
from certify.spec.enclosures import (
    h_enclosure,
    jacobian_h_enclosure,
    residual_jacobian,
)
from certify.spec.system import System

#: up to this n, `tm_lam_upper` also takes Hertz's vertex bound (the remainder entrywise,
#: exactly: 2^(n-1) sign patterns per vertex)
HERTZ_MAX_N = 3


def network_taylor(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                   ) -> tuple[TM, TM, torch.Tensor]:
    """First-order TMs over boxes of N(z) [B, out] and dN/dz [B, out, d]; returns radii r.

    `certify.model.gain.propagate` in `certify.model.gain.taylor.TaylorArithmetic` (the one
    propagation of the gain)."""
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

    `certify.model.gain.compose` in `TaylorArithmetic` on the network's models and the models of
    r = y - h(xhat) and dh/dxhat (mean-value forms from the centre values and the box
    enclosures of their derivatives). net_tms: (value [B, out], Jacobian [B, out, d], radii)
    of the network from elsewhere (e.g. tightened by linear bound propagation); default
    `network_taylor`."""

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

    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    net_tms = network_taylor(net, lo, hi) if net_tms is None else net_tms
    r = net_tms[2]
    dkdx = gain_taylor(system, net, lo, hi, net_tms, with_k=False, with_dy=False).dk_dx
    return tm_add(jacobian_tm(system, "f", lo, hi, r), dkdx, r)


def tm_congruence(pc: Preconditioner, J: TM, constant: Interval, r: torch.Tensor) -> TM:
    """TM of A = He{Q J M^T} + `constant` (exact congruence when P = I); `constant` is the
    enclosure of M (2 lam P + Q) M^T, `certify.enclose.preconditioner.constant_term`."""
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
    lc, lr = constant.midrad()
    A = tm_absorb(A.c + lc, A.g, up(A.e + lr), r, 2)
    return A


def _decision_level(level: float) -> float:
    """The level a decision proves, a hair below the caller's: level - 1e-12 (1 + |level|)."""
    return float(level) - 1e-12 * (1.0 + abs(float(level)))


def tm_lam_upper(A: TM, r: torch.Tensor, parts: bool = False, level: float | None = None):
    """max over the box of lam_max(A(z)) <= max_vertices lam_max(c + sum_m s_m r_m g_m)
    + rho(e + rounding) (convexity of lam_max in the affine part); for n <= 3 the smaller
    max_vertices hertz_upper(vertex matrix, e + rounding) (the remainder entrywise, not by its
    spectral radius).

    level (a decision: only "bound <= level" matters; n >= 4): the vertex matrices are first
    tested against t = down(level' - rho) by the certified Cholesky test
    (`certify.arith.eigen.lam_max_at_most`), level' = level - 1e-12 (1 + |level|), unless
    (without `parts`) Weyl's bound of the affine part is already <= t; a box whose every vertex
    passes (or whose Weyl bound does) reports the bound level' (proved: vertex max <= t,
    t + rho <= level'), without vertex eigenvalues. The others (their bound then only ranks
    them in the branch and bound: a completed proof splits the same boxes whatever it is, a
    budgeted run's order depends on it) get Weyl's lam_max(c) + sum_m ||r_m g_m||_F (one
    eigenproblem per box, `_weyl_upper`); with `parts` (the vertex part is wanted), the
    vertices that fail are tested again at t + k s, s = rho + 1e-3 (1 + |level|), k = 1/4, 1,
    4 (their bound: the first level passed) and only the rest get eigenvalue bounds.
    Beyond MAX_VERTEX_DIM coordinates (level given, n >= 2), where the first-order part joins
    the remainder for the bound, a box is first decided as a whole
    (`certify.enclose.whole_box.decide_whole_box`: the room's congruence, the strongest
    coordinates as vertices, the rest by Weyl); decided boxes report level'."""
    B, n, _, d = A.g.shape
    rG = (A.g * r[:, None, None, :]).permute(0, 3, 1, 2)  # [B, d, n, n]
    gk = gamma(d + 5)
    absum = A.c.abs() + rG.abs().sum(1)
    rem = up((A.e + gk * absum) * (1.0 + 2.0 * gk) + (d + 2) * TINY)
    rem = torch.maximum(rem, rem.transpose(1, 2))
    vertex = d <= MAX_VERTEX_DIM
    whole = None
    if not vertex:
        if level is not None and n >= 2:  # too many vertices: the box decided as a whole
            whole = decide_whole_box(A.c, rG, rem, _decision_level(level))
        rem = up(rem + rG.abs().sum(1) * (1.0 + gk))
    decide_lower = vertex and level is not None and n >= 4 and not parts
    # the vertex matrices; the Cholesky decision reads their lower triangles only (as LAPACK),
    # which enclose D's like the whole matrices do, so there they are built unsymmetrised and
    # only for the boxes that need them (below)
    S = vertex_matrices(A.c, rG, sym=True) if vertex and not decide_lower else None
    rr = rho_upper(rem)
    decided = None
    if vertex and level is not None and n >= 4:
        lvl = _decision_level(level)
        t = down(lvl - rr)  # proved vertex max <= t  =>  lv + rr <= lvl
        if parts:  # the vertex part itself is wanted (where the linear bounds are tried)
            lv, decided = vertex_max_upper(S, t, step=rr + 1e-3 * (1.0 + abs(lvl)))
        else:
            # Weyl, the vertices, then the box's own congruence (`certify.enclose.decide`)
            decided, lv = decide_affine_family(A.c, rG, rem, rr, lvl)
            lv = torch.where(decided, t, lv)
    elif S is not None:
        lv = lam_max_upper_point(S).amax(-1)
    else:
        lv = lam_max_upper_point(A.c)
    bound = up(lv + rr)
    if decided is not None:
        bound = torch.where(decided, torch.full_like(bound, lvl), bound)
    if whole is not None:
        bound = torch.where(whole, torch.full_like(bound, _decision_level(level)), bound)
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
