"""Plain interval enclosures of the gain network: value, Jacobian and second derivatives.

Boxes live in z = (xhat, y) space: lo, hi [B, d], d = n + p. Forward-mode interval propagation
layer by layer (`certify.model.gain.propagate` with
`certify.model.gain.interval.IntervalArithmetic`, the
one propagation of the gain), pre-activations tightened by a mean-value form around the box
centre. Rounding:
products with point weight matrices in midpoint-radius form with Higham's gamma_k bound added
(`certify.arith.intervals.matmul_point_right`), everything else outward by one ulp, the activation
and its derivatives by its own sound enclosures (`certify.model.activations`: `enclose_f`,
`enclose_d1`, `enclose_d2`, widened libm rules; for ELU, whose f'' jumps at 0, `enclose_d2`
holds both one-sided values, which is what the mean-value forms built on it need).

The gain k is the network composed with the injection by `certify.model.gain.compose` (value and
first derivatives) and `compose_second` (d2k / dxhat dz) in the same arithmetic: interval
products summed with `isum` (gamma_k sum|x| for the summation), K and the identity block of
dk/dy as exact point intervals; h, Jh, Jf and the second derivatives of f and h come from
`certify.spec.enclosures`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.interval_ops import intersect, isum
from certify.arith.intervals import Interval, imul, up
from certify.model.gain.interval import IntervalArithmetic
from certify.model.gain.propagate import NetOutput, compose, compose_second, propagate
from certify.model.network import GainNetwork
from certify.spec.enclosures import (
    h_enclosure,
    hessian_f_enclosure,
    hessian_h_enclosure,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    pad_y,
    residual_jacobian,
)
from certify.spec.system import System


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
    """What `certify.model.kernels.gain_terms` computes, enclosed over boxes z in [lo, hi]: the
    network's enclosure (`network_enclosure`) composed with the injection by
    `certify.model.gain.compose` (and `compose_second`) in `IntervalArithmetic`, plus Jf."""
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    spec = net.spec(torch.float64, detach=True)
    ne = network_enclosure(net, lo, hi, order=order, second_cols=n, center_pre=center_pre)
    xl, xh = lo[:, :n], hi[:, :n]
    jf = Interval(*jacobian_f_enclosure(system, xl, xh))
    djf = None
    if order >= 2:
        djf = pad_y(Interval(*hessian_f_enclosure(system, xl, xh)), p)  # [B, n, n, d]
    r = Hx = dr = d2r = None
    if spec.needs_h:
        r = Interval(lo[:, n:], hi[:, n:]) - Interval(*h_enclosure(system, xl, xh))  # [B, p]
        Hx = Interval(*jacobian_h_enclosure(system, xl, xh))  # [B, p, n]
        if order >= 2:
            dr = residual_jacobian(Hx)  # [B, p, d]
            hh = Interval(*hessian_h_enclosure(system, xl, xh))  # [B, p, n, n]
            d2r = pad_y(Interval(-hh.hi, -hh.lo), p)  # [B, p, n, d]
    arith = IntervalArithmetic(None, None)  # compose needs no box
    out = NetOutput(ne.value, ne.d1, ne.d2)
    g = compose(spec, arith, out, r, Hx)
    d2k = compose_second(spec, arith, out, r, dr, d2r) if order >= 2 else None
    return GainEnclosure(k=g.k, dk_dx=g.dk_dx, dk_dy=g.dk_dy, d2k=d2k, jf=jf, djf=djf), ne

