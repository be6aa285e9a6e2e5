"""Plain interval enclosures of the gain network: value, Jacobian and second derivatives.

Boxes live in z = (xhat, y) space: lo, hi [B, d], d = n + p. Forward-mode interval propagation
layer by layer (`certify.gain.propagate` with `certify.gain.interval.IntervalArithmetic`, the
one propagation of the gain), pre-activations tightened by a mean-value form around the box
centre. Rounding:
products with point weight matrices in midpoint-radius form with Higham's gamma_k bound added
(`certify.intervals.matmul_point_right`), everything else outward by one ulp, the activation
and its derivatives by its own sound enclosures (`certify.activations`: `enclose_f`,
`enclose_d1`, `enclose_d2`, widened libm rules; for ELU, whose f'' jumps at 0, `enclose_d2`
holds both one-sided values, which is what the mean-value forms built on it need).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.bounds.interval_ops import iadd, intersect, isum, point
from certify.gain.interval import IntervalArithmetic
from certify.gain.propagate import propagate
from certify.intervals import (
    Interval,
    h_enclosure,
    hessian_f_enclosure,
    hessian_h_enclosure,
    imul,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    up,
)
from certify.network import GainNetwork
from certify.system import System


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
    d = lo.shape[1]
    spec = net.spec(torch.float64, detach=True)
    zc = 0.5 * (lo + hi)
    zr = up(torch.maximum(hi - zc, zc - lo))
    zdev = Interval(-zr.unsqueeze(-1), zr.unsqueeze(-1))  # z - c, [B, d, 1]
    pres: list[Interval] = []

    def tighten(layer: int, pre: Interval, T: Interval) -> Interval:
        if center_pre is not None:
            pre = intersect(pre, center_pre[layer] + isum(imul(T, zdev), 1))
        pres.append(pre)
        return pre

    out = propagate(spec, IntervalArithmetic(zc, zr), None, d, order, second_cols, tighten)
    return NetEnclosure(value=out.value, d1=out.jac, d2=out.hess, pre=pres)


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

