"""Box bounds for the side proofs: the manifold quantity, the BC residual and ||dk/dy||.

Rounding as in `certify.intervals.ROUNDING`; norms of entry magnitudes carry a gamma_k factor.
"""

from __future__ import annotations

import torch

from certify.bounds.eigen import lam_max_upper_interval
from certify.bounds.interval_ops import const_lam, iadd, intersect, isum, isym, point
from certify.bounds.network_interval import gain_enclosure
from certify.intervals import (
    Interval,
    gamma,
    h_enclosure,
    imatmul,
    imul,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    up,
)
from certify.network import GainNetwork
from certify.system import System


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

