"""Enclosures over boxes for a state-dependent metric M(x): the metric itself, its rate along
the observer's flow, and the matrix of the Riemannian path certificate.

Over a box of z = (x, w) (a state x in R^n, an output w in R^p; coordinates d = n + p), with
F(x, w) = f(x) + k(x, w), J_F = Jf + dk/dx and B = dk/dw, the path certificate's matrix is

    N(x, w) = [[Mdot + He{M J_F} + (alpha/2) M,   M B / 2],
               [B^T M / 2,                       -(mu/2) I]],    Mdot = (1/2) sum_i dM/dx_i F_i,

half the matrix [[dM/dt + 2 He{M J_F} + alpha M, M B], [B^T M, -mu I]] of
`certify.prove.metric`. Everything is a first-order Taylor model over the box
(`certify.arith.taylor`): the monomials of M as products of the coordinates' exact linear
models, the network's value and Jacobians from the gain's own Taylor arithmetic
(`certify.enclose.taylor.gain_taylor`), f and Jf from the spec's enclosures (mean-value forms),
products of models by `tm_mul` (whose remainder covers the second-order terms). So every N(z),
z in the box, is a member of the model's family, and `tm_lam_upper` (convexity of lam_max in
the affine part, Weyl for the remainder) bounds lam_max over the box. A constant congruence
T N T^T (T invertible: Sylvester's law keeps the sign) only conditions the bound.

`tube_outside` tells the boxes that hold no point of the domain's tube ||w - h(x)|| <= tau
(a sound lower bound of the distance above tau): the certificate is claimed on the tube only,
so those boxes are closed without a bound.

**Tube coordinates.** A tube is a thin band around the output manifold; in z = (x, w) its edge
cuts every box it crosses, and the boxes there must shrink until they fall inside or outside.
In u = (x, t) with w = h(x) + t the tube ||t|| <= tau is a box for one output (and inscribed in
the box [-tau, tau]^p otherwise): `tube_flow_terms` builds the same models over u-boxes. The
network's input z(u) = (x, h(x) + t) enters as a Taylor model over u (h by its mean-value
form, exact for a linear h up to rounding), r = w - h(x) = t is exact, and every derivative is
still the partial derivative in z (the models' coefficients run over u). So every N(z(u)), u in
the box, is a member of the model's family, as in z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from certify.arith.intervals import Interval, down, gamma, up
from certify.arith.taylor import (
    TM,
    tm_absorb,
    tm_add,
    tm_from_intervals,
    tm_linear,
    tm_mul,
    tm_sum,
)
from certify.enclose.system_taylor import jacobian_tm
from certify.enclose.taylor import gain_taylor, network_taylor, tm_lam_upper
from certify.model.gain.propagate import NetOutput, compose, propagate
from certify.model.gain.taylor import TaylorArithmetic
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.spec.enclosures import (
    f_enclosure,
    h_enclosure,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    pad_y,
)
from certify.spec.system import System

_F64 = torch.float64


def _radii(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    zc = 0.5 * (lo + hi)
    return zc, up(torch.maximum(hi - zc, zc - lo))


def coordinate_tms(lo: torch.Tensor, hi: torch.Tensor, n: int) -> TM:
    """The exact linear models of the first n coordinates over boxes [B, d] -> [B, n]."""
    zc, _ = _radii(lo, hi)
    B, d = lo.shape
    g = torch.zeros(B, n, d, dtype=_F64, device=lo.device)
    g[:, torch.arange(n), torch.arange(n)] = 1.0
    return TM(zc[:, :n].clone(), g, torch.zeros(B, n, dtype=_F64, device=lo.device))


def _monomial_tms(metric: PolyMetric, x: TM, r: torch.Tensor) -> TM:
    """The monomials x^(a_k) over the boxes -> [B, K] (products of the coordinates' models)."""
    B, n, d = x.g.shape
    K = len(metric.exponents)
    c = torch.ones(B, K, dtype=_F64, device=x.c.device)
    out = TM(c, torch.zeros(B, K, d, dtype=_F64, device=x.c.device), torch.zeros_like(c))
    for i in range(n):
        for power in range(1, int(metric.exponents[:, i].max()) + 1):
            rows = torch.as_tensor(metric.exponents[:, i] >= power, device=x.c.device)
            if not bool(rows.any()):
                continue
            xi = TM(x.c[:, i:i + 1].expand(B, K), x.g[:, i:i + 1].expand(B, K, d),
                    x.e[:, i:i + 1].expand(B, K))
            prod = tm_mul(out, xi, r)
            keep = rows[None]
            out = TM(torch.where(keep, prod.c, out.c), torch.where(keep[..., None], prod.g, out.g),
                     torch.where(keep, prod.e, out.e))
    return out


def tm_combine(weights: TM, mats: torch.Tensor, r: torch.Tensor) -> TM:
    """sum_k weights_k mats_k over boxes: weights [B, K], mats [K, a, b] (points) -> [B, a, b]."""
    M = mats.to(_F64)
    c = torch.einsum("bk,kij->bij", weights.c, M)
    g = torch.einsum("bkd,kij->bijd", weights.g, M)
    e = torch.einsum("bk,kij->bij", weights.e, M.abs())
    return tm_absorb(c, g, up(e), r, weights.c.shape[1] + 2)


def metric_tm(metric: PolyMetric, lo: torch.Tensor, hi: torch.Tensor) -> TM:
    """M(x) over boxes of z [B, d] (x the first n coordinates) -> [B, n, n]."""
    _, r = _radii(lo, hi)
    x = coordinate_tms(lo, hi, metric.n)
    return tm_combine(_monomial_tms(metric, x, r),
                      torch.as_tensor(metric.coefficients, device=lo.device), r)


def tm_matmul(a: TM, b: TM, r: torch.Tensor) -> TM:
    """Matrix product over boxes: a [B, i, k], b [B, k, j] -> [B, i, j]."""
    A = TM(a.c[:, :, :, None], a.g[:, :, :, None, :], a.e[:, :, :, None])
    Bm = TM(b.c[:, None, :, :], b.g[:, None, :, :, :], b.e[:, None, :, :])
    return tm_sum(tm_mul(A, Bm, r), 2, r)


def tm_transpose(a: TM) -> TM:
    return TM(a.c.transpose(1, 2), a.g.transpose(1, 2), a.e.transpose(1, 2))


def tm_scale(a: TM, s: float, r: torch.Tensor) -> TM:
    return tm_absorb(a.c * s, a.g * s, up(a.e * abs(s)), r, 1)


def tm_sym(a: TM, r: torch.Tensor) -> TM:
    """He{a} = (a + a^T) / 2 over boxes [B, n, n]."""
    t = tm_transpose(a)
    return tm_absorb(0.5 * (a.c + t.c), 0.5 * (a.g + t.g), up(0.5 * up(a.e + t.e)), r, 2)


def tm_congruent(T: torch.Tensor, a: TM, r: torch.Tensor) -> TM:
    """T a T^T for a point matrix T [m, m] and a model a [B, m, m]."""
    T = T.to(_F64)
    m = T.shape[0]
    c = T @ a.c @ T.T
    g = torch.einsum("ik,bkld,jl->bijd", T, a.g, T)
    e = T.abs() @ a.e @ T.abs().T
    return tm_absorb(c, g, up(e * (1.0 + 2.0 * gamma(2 * m + 2))), r, 2 * m + 2)


def tm_blocks(top_left: TM, top_right: TM, bottom_right: TM) -> TM:
    """[[A, C], [C^T, D]] over boxes from A [B, n, n], C [B, n, p], D [B, p, p]."""
    bl = tm_transpose(top_right)

    def cat(f):
        return torch.cat([torch.cat([f(top_left), f(top_right)], 2),
                          torch.cat([f(bl), f(bottom_right)], 2)], 1)
    return TM(cat(lambda t: t.c), cat(lambda t: t.g), cat(lambda t: t.e))


@dataclass
class FlowTerms:
    """Over boxes: F = f + k [B, n], J_F = Jf + dk/dx [B, n, n], B = dk/dw [B, n, p], the
    radii r [B, d]."""

    F: TM
    J: TM
    B: TM
    r: torch.Tensor


def flow_terms(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
               ) -> FlowTerms:
    """The observer's vector field and its Jacobians over boxes of z = (x, w)."""
    lo, hi = lo.to(_F64), hi.to(_F64)
    n, p = system.n, system.p
    net_tms = network_taylor(net, lo, hi)
    r = net_tms[2]
    gv = gain_taylor(system, net, lo, hi, net_tms, with_k=True, with_dy=True)
    zc = 0.5 * (lo + hi)
    xc, xl, xh = zc[:, :n], lo[:, :n], hi[:, :n]
    f_centre = Interval(*f_enclosure(system, xc, xc))
    jf_box = pad_y(Interval(*jacobian_f_enclosure(system, xl, xh)), p)
    f_tm = tm_from_intervals(f_centre, jf_box, r)
    F = tm_add(f_tm, gv.k, r)
    J = tm_add(jacobian_tm(system, "f", lo, hi, r), gv.dk_dx, r)
    return FlowTerms(F=F, J=J, B=gv.dk_dy, r=r)


class _InputModel(TaylorArithmetic):
    """The gain's Taylor arithmetic with the network's input a given model z(u) [B, d] over
    the u-boxes (instead of the box's own coordinates)."""

    def __init__(self, uc: torch.Tensor, r: torch.Tensor, z: TM) -> None:
        super().__init__(uc, r)
        self.z = z

    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[TM, TM | None]:
        _, T = super().input_layer(None, W, b, m)  # the constant rows of dN/dz
        return tm_linear(self.z, W.T, b, self.r), T


def tube_point(system: System, u: torch.Tensor) -> torch.Tensor:
    """z = (x, h(x) + t) at points u = (x, t) [B, n + p] (differentiable)."""
    n = system.n
    return torch.cat([u[:, :n], system.h(u[:, :n]) + u[:, n:]], 1)


def tube_flow_terms(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                    ) -> FlowTerms:
    """`flow_terms` over boxes of u = (x, t), the point z = (x, h(x) + t) (module docstring,
    tube coordinates)."""
    lo, hi = lo.to(_F64), hi.to(_F64)
    n, p = system.n, system.p
    uc, r = _radii(lo, hi)
    xc, xl, xh = uc[:, :n], lo[:, :n], hi[:, :n]
    x = coordinate_tms(lo, hi, n)
    h_tm = tm_from_intervals(Interval(*h_enclosure(system, xc, xc)),
                             pad_y(Interval(*jacobian_h_enclosure(system, xl, xh)), p), r)
    B_, d = lo.shape
    tg = torch.zeros(B_, p, d, dtype=_F64, device=lo.device)
    tg[:, torch.arange(p), n + torch.arange(p)] = 1.0
    t = TM(uc[:, n:].clone(), tg, torch.zeros(B_, p, dtype=_F64, device=lo.device))
    w = tm_add(h_tm, t, r)
    z = TM(torch.cat([x.c, w.c], 1), torch.cat([x.g, w.g], 1), torch.cat([x.e, w.e], 1))
    spec = net.spec(_F64, detach=True)
    arith = _InputModel(uc, r, z)
    out = propagate(spec, arith, None, d)
    Jh = jacobian_tm(system, "h", lo, hi, r)
    gv = compose(spec, arith, NetOutput(out.value, out.jac), t, Jh, with_dy=True, with_k=True)
    f_centre = Interval(*f_enclosure(system, xc, xc))
    jf_box = pad_y(Interval(*jacobian_f_enclosure(system, xl, xh)), p)
    F = tm_add(tm_from_intervals(f_centre, jf_box, r), gv.k, r)
    J = tm_add(jacobian_tm(system, "f", lo, hi, r), gv.dk_dx, r)
    return FlowTerms(F=F, J=J, B=gv.dk_dy, r=r)


def path_metric_tm(system: System, net: GainNetwork, metric: PolyMetric, alpha: float,
                   mu: float, lo: torch.Tensor, hi: torch.Tensor,
                   congruence: torch.Tensor | None = None, tube: bool = False) -> TM:
    """N (module docstring) over boxes [B, d] of z = (x, w), or of u = (x, t) with `tube`
    -> [B, n + p, n + p] (T N T^T with a point `congruence` T [n + p, n + p] when given)."""
    lo, hi = lo.to(_F64), hi.to(_F64)
    n, p = system.n, system.p
    ft = (tube_flow_terms if tube else flow_terms)(system, net, lo, hi)
    r = ft.r
    x = coordinate_tms(lo, hi, n)
    mono = _monomial_tms(metric, x, r)
    coeffs = torch.as_tensor(metric.coefficients, device=lo.device)
    M = tm_combine(mono, coeffs, r)
    # Mdot / 2 = (1/2) sum_i dM/dx_i F_i
    half_mdot = None
    for i in range(n):
        d = metric.derivative(i)
        if d is None:
            continue
        dM = tm_combine(_monomial_tms(d, x, r), torch.as_tensor(d.coefficients,
                                                                 device=lo.device), r)
        Fi = TM(ft.F.c[:, i, None, None], ft.F.g[:, i, None, None, :], ft.F.e[:, i, None, None])
        term = tm_mul(dM, Fi, r)
        half_mdot = term if half_mdot is None else tm_add(half_mdot, term, r)
    top = tm_add(tm_sym(tm_matmul(M, ft.J, r), r), tm_scale(M, 0.5 * alpha, r), r)
    if half_mdot is not None:
        top = tm_add(top, tm_scale(half_mdot, 0.5, r), r)
    MB = tm_scale(tm_matmul(M, ft.B, r), 0.5, r)
    B_ = lo.shape[0]
    D = torch.zeros(B_, p, p, dtype=_F64, device=lo.device)
    D[:, torch.arange(p), torch.arange(p)] = -0.5 * mu
    low = TM(D, torch.zeros(B_, p, p, lo.shape[1], dtype=_F64, device=lo.device),
             torch.zeros_like(D))
    N = tm_blocks(top, MB, low)
    return N if congruence is None else tm_congruent(congruence, N, r)


def lam_max_upper(A: TM, lo: torch.Tensor, hi: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sound upper bounds of max lam_max(A(z)) over each box [B] and a split score [B, d]."""
    _, r = _radii(lo.to(_F64), hi.to(_F64))
    c = 0.5 * (A.c + A.c.transpose(1, 2))
    g = 0.5 * (A.g + A.g.transpose(1, 2))
    # the members are symmetric, so the symmetric parts serve (He of a member is itself);
    # one more rounding of the centre's symmetric part, absorbed here
    e = up(torch.maximum(A.e, A.e.transpose(1, 2)) + 2.0 ** -52 * c.abs())
    return tm_lam_upper(TM(c, g, e), r)


def tube_outside(system: System, lo: torch.Tensor, hi: torch.Tensor, tau: float
                 ) -> torch.Tensor:
    """Boxes [B] (bool) in which every point has ||w - h(x)||_2 > tau (so none is in the
    tube): a sound lower bound of the norm over the box (interval mignitudes, rounded down)
    above tau. False where the enclosure is not finite."""
    n = system.n
    lo, hi = lo.to(_F64), hi.to(_F64)
    hl, hh = h_enclosure(system, lo[:, :n], hi[:, :n])
    dlo = down(lo[:, n:] - hh)  # w - h(x) >= dlo
    dhi = up(hi[:, n:] - hl)
    mig = torch.where(dlo > 0, dlo, torch.where(dhi < 0, -dhi, torch.zeros_like(dlo)))
    ok = torch.isfinite(dlo).all(-1) & torch.isfinite(dhi).all(-1)
    low = down(torch.sqrt(down((mig * mig).sum(-1)) * (1.0 - 4 * 2.0 ** -52)))
    return ok & (low > tau)


def tube_box_outside(system: System, lo: torch.Tensor, hi: torch.Tensor, tau: float
                     ) -> torch.Tensor:
    """Boxes [B] (bool) of u = (x, t) in which every point has ||t||_2 > tau (tube
    coordinates; never for one output, whose tube is the box): interval mignitudes, the norm
    rounded down."""
    n = system.n
    lo, hi = lo.to(_F64), hi.to(_F64)
    tl, th = lo[:, n:], hi[:, n:]
    mig = torch.where(tl > 0, tl, torch.where(th < 0, -th, torch.zeros_like(tl)))
    low = down(torch.sqrt(down((mig * mig).sum(-1)) * (1.0 - 4 * 2.0 ** -52)))
    return low > tau


def point_matrix(system: System, net: GainNetwork, metric: PolyMetric, alpha: float,
                 mu: float, z: torch.Tensor) -> torch.Tensor:
    """N at points z [B, d] (float64, differentiable) -> [B, n + p, n + p]."""
    from certify.model.kernels import gain_terms

    n = system.n
    x, w = z[:, :n], z[:, n:]
    t = gain_terms(system, net, x, w, with_dy=True)
    F = system.f(x) + t.k
    J = system.jac_f(x) + t.dk_dx
    M = metric.value(x)
    Mdot = metric.rate_along(x, F)
    MJ = M @ J
    top = 0.5 * Mdot + 0.5 * (MJ + MJ.transpose(1, 2)) + 0.5 * alpha * M
    MB = 0.5 * M @ t.dk_dy
    p = system.p
    low = -0.5 * mu * torch.eye(p, dtype=z.dtype, device=z.device).expand(z.shape[0], p, p)
    return torch.cat([torch.cat([top, MB], 2), torch.cat([MB.transpose(1, 2), low], 2)], 1)


def metric_congruence(metric: PolyMetric, centre: np.ndarray, mu: float, p: int
                      ) -> torch.Tensor:
    """T = diag(L^-1, (2/mu)^(1/2) I) with M(centre) = L L^T: the matrix at the centre of the
    domain brought near the identity scale (conditioning only; identity where M(centre) is
    not positive definite)."""
    n = metric.n
    Mc = metric.value(torch.as_tensor(centre[None, :n], dtype=_F64))[0].numpy()
    try:
        Li = np.linalg.inv(np.linalg.cholesky(Mc))
    except np.linalg.LinAlgError:
        Li = np.eye(n)
    T = np.zeros((n + p, n + p))
    T[:n, :n] = Li
    T[n:, n:] = np.sqrt(2.0 / mu) * np.eye(p)
    return torch.as_tensor(T)
