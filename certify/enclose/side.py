"""Box bounds for the side proofs: the manifold quantity, the BC residual and ||dk/dy||.

Rounding as in `certify.arith.intervals.ROUNDING`; norms of entry magnitudes carry a gamma_k factor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.eigen import lam_max_upper_interval
from certify.arith.interval_ops import const_lam, iadd, intersect, isum, isym, point
from certify.arith.intervals import Interval, gamma, imatmul, imul, up
from certify.enclose.network_interval import gain_enclosure
from certify.model.network import GainNetwork
from certify.spec.enclosures import h_enclosure, jacobian_f_enclosure, jacobian_h_enclosure
from certify.spec.system import System


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


@dataclass
class IntervalDkDy:
    """The interval bound of ||dk/dy||_2 over z-boxes: `upper` [B], the float value at the
    centres `centre` [B], and the entry magnitudes `mag` [B, n, p] it came from (the
    tightened bounds reuse them instead of enclosing the gain again)."""

    upper: torch.Tensor
    centre: torch.Tensor
    mag: torch.Tensor

    def __getitem__(self, mask: torch.Tensor) -> IntervalDkDy:
        return IntervalDkDy(self.upper[mask], self.centre[mask], self.mag[mask])


def dk_dy_interval(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                   ) -> IntervalDkDy:
    """Upper bound of ||dk/dy||_2 (via Frobenius of the entry magnitudes) over z-boxes."""
    gb, _ = gain_enclosure(system, net, lo, hi)
    zc = 0.5 * (lo + hi).to(torch.float64)
    gc, _ = gain_enclosure(system, net, zc, zc)
    mag = torch.maximum(gb.dk_dy.lo.abs(), gb.dk_dy.hi.abs())
    nrm = up(torch.sqrt(up((mag * mag).sum((-1, -2)) * (1.0 + 2.0 * gamma(mag[0].numel() + 1)))))
    cen = torch.linalg.matrix_norm(gc.dk_dy.mid(), ord=2)
    return IntervalDkDy(nrm, cen, mag)


def dk_dy_box_upper(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(upper bound of ||dk/dy||_2, its centre value) over z-boxes (`dk_dy_interval`)."""
    iv = dk_dy_interval(system, net, lo, hi)
    return iv.upper, iv.centre



def _tm_mag(c: torch.Tensor, g: torch.Tensor, e: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Upper bound of |c + g . dz + [-e, e]| over |dz| <= r (r broadcast on g's last dim)."""
    d = g.shape[-1]
    gr = up((g.abs() * r).sum(-1) * (1.0 + gamma(d + 2)))
    return up(up(c.abs() + gr) + e)


def residual_box_upper_crown(system: System, net: GainNetwork, lo: torch.Tensor,
                             hi: torch.Tensor,
                             interval: tuple[torch.Tensor, torch.Tensor] | None = None
                             ) -> tuple[torch.Tensor, torch.Tensor]:
    """`residual_box_upper` tightened by linear bound propagation (direct network, linear h):
    g(x) = k(x, h(x)) = N(A x + a) with A = [I; C], a = [0; h(0)] (the K term vanishes), the
    composition done on the first layer with its rounding carried as a slack; per component
    the smaller of the two magnitude bounds. The forward pass keeps no Taylor models
    (`forward_bounds(taylor=False)`): with them the bound changed only in its last bits on
    examples/vdp.ckpt and the benchmark instances, at a cost in the residual proof.
    `interval`: the
    `residual_box_upper` of these boxes when the caller has it (not computed again)."""
    from certify.enclose.crown import AffineInputNetwork, forward_bounds, to_tm, value_crown

    norm, cen = residual_box_upper(system, net, lo, hi) if interval is None else interval
    if net.structure != "direct" or not system.h_is_linear:
        return norm, cen
    n = system.n
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    zero = torch.zeros(1, n, dtype=torch.float64, device=lo.device)
    C = system.jac_h(zero)[0].to(torch.float64)  # [p, n], constant for linear h
    h0 = system.h(zero)[0].to(torch.float64)
    A = torch.cat([torch.eye(n, dtype=torch.float64, device=lo.device), C], 0)
    a = torch.cat([torch.zeros(n, dtype=torch.float64, device=lo.device), h0])
    if bool(h0.abs().max() > 0) or not bool(torch.equal(C, C.round())):
        # a non-integer C or an offset: the exact composition needs the sympy values; keep
        # the interval bound (the built-ins and benchmarks have y = x1)
        return norm, cen
    vnet = AffineInputNetwork(net, A, a)
    fb = forward_bounds(vnet, lo, hi, cols=[], crown=True,
                        b0_slack=vnet.first_layer_slack(lo, hi), taylor=False)
    vt = to_tm(value_crown(vnet, lo, hi, fb), fb.r)
    mag = _tm_mag(vt.c, vt.g, vt.e, fb.r.unsqueeze(1))
    entrywise = up(torch.sqrt(up((mag * mag).sum(-1) * (1.0 + 2.0 * gamma(n + 1)))))
    # the norm's maximum over the vertices of the linear part (an excess quadratic in the box
    # size, where the entrywise bound's is linear): k as an [n, 1] matrix
    joint = _tm_frobenius_upper(vt.c[..., None], vt.g[:, :, None, :], vt.e[..., None], fb.r)
    tight = torch.minimum(entrywise, joint)
    return torch.where(torch.isnan(tight), norm, torch.minimum(norm, tight)), cen


def dk_dy_box_upper_crown(system: System, net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
                          interval: IntervalDkDy | None = None
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """`dk_dy_box_upper` tightened by linear bound propagation of dN/dy (direct network):
    dk/dy = dN/dy + K, its norm bounded by `_tm_frobenius_upper` and by the entrywise
    smaller of the linear and interval magnitudes; the smallest per box. A structural
    network (no linear bounds here) gets `dk_dy_box_upper_taylor`. The forward pass keeps no
    Taylor models (`forward_bounds(taylor=False)`): with them the bound changed only in its
    last bits (the instances of `residual_box_upper_crown`), at a cost in the proof.
    `interval`: the `dk_dy_interval` of these boxes when the caller has it (the gain is then
    not enclosed again: a large share of examples/vdp.ckpt's dk/dy proof, `bench/run.py`)."""
    from certify.enclose.crown import forward_bounds, jacobian_crown, to_tm

    if net.structure != "direct":
        return dk_dy_box_upper_taylor(system, net, lo, hi, interval)
    iv = dk_dy_interval(system, net, lo, hi) if interval is None else interval
    nrm, cen = iv.upper, iv.centre
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    cols = list(range(n, n + p))
    fb = forward_bounds(net, lo, hi, cols=cols, crown=True, taylor=False)
    jt = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r)  # [B, n, p]
    K = net.K.to(torch.float64)
    ck = jt.c + K  # float sum: its error is at most u |c + K|, added to e
    e = up(jt.e + 2.0 * 2.0**-53 * ck.abs())
    mag = _tm_mag(ck, jt.g, e, fb.r[:, None, None, :])
    mag = torch.minimum(mag, iv.mag)
    entrywise = up(torch.sqrt(up((mag * mag).sum((-1, -2))
                                 * (1.0 + 2.0 * gamma(mag[0].numel() + 1)))))
    tight = torch.minimum(entrywise, _tm_frobenius_upper(ck, jt.g, e, fb.r))
    return torch.where(torch.isnan(tight), nrm, torch.minimum(nrm, tight)), cen


def dk_dy_box_upper_taylor(system: System, net: GainNetwork, lo: torch.Tensor,
                           hi: torch.Tensor, interval: IntervalDkDy | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """`dk_dy_box_upper` tightened by first-order Taylor models of dk/dy (any structure):
    `certify.enclose.taylor.gain_taylor`'s model (float errors already in its remainder)
    bounded by `_tm_frobenius_upper`; the smaller of that and the interval bound per box
    (`interval`: as in `dk_dy_box_upper_crown`)."""
    from certify.enclose.taylor import gain_taylor

    iv = dk_dy_interval(system, net, lo, hi) if interval is None else interval
    nrm, cen = iv.upper, iv.centre
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))  # the radii gain_taylor's models are over
    t = gain_taylor(system, net, lo, hi, with_k=False, with_dy=True).dk_dy  # [B, n, p]
    tight = _tm_frobenius_upper(t.c, t.g, t.e, r)
    return torch.where(torch.isnan(tight), nrm, torch.minimum(nrm, tight)), cen


#: most float64 entries the vertex maximum of `_tm_frobenius_upper` builds at once
MAX_VERTEX_ENTRIES = 2**23


def _tm_frobenius_upper(c: torch.Tensor, g: torch.Tensor, e: torch.Tensor, r: torch.Tensor
                        ) -> torch.Tensor:
    """Upper bound of max ||c + G dz + E||_F over |dz| <= r, |E| <= e (entrywise), per box.

    c, e [B, n, p], g [B, n, p, d], r [B, d]. ||.||_F of the linear part is convex in dz, so
    its max over the box is at a vertex: max_v ||c + G (v * r)||_F exactly, plus ||e||_F
    (triangle inequality). Bounding each entry at its own worst vertex instead leaves an
    excess linear in the box size; the vertex maximum leaves one quadratic in it, which is
    what lets a maximisation close near its maximum. The vertex values are computed in float
    with the error of each entry bounded by gamma_(d+2) (|c| + |G| r), added to its
    magnitude; sums and square roots are rounded up. Where the 2^d vertices would not fit
    (`MAX_VERTEX_ENTRIES`), each entry's magnitude is bounded on its own (`_tm_mag`).
    """
    from certify.arith.eigen import cube_vertices

    B, d = r.shape
    rr = r[:, None, None, :]
    size = c[0].numel()
    if B * 2**d * size > MAX_VERTEX_ENTRIES:
        mag = _tm_mag(c, g, e, rr)
        return up(torch.sqrt(up((mag * mag).sum((-1, -2)) * (1.0 + 2.0 * gamma(size + 1)))))
    gr = g * rr  # one rounding per product, covered by the gamma below
    err = up((c.abs() + gr.abs().sum(-1)) * gamma(d + 2))  # [B, n, p]
    corners = cube_vertices(d, gr.device)
    lin = c[:, None] + torch.einsum("bijd,vd->bvij", gr, corners)  # [B, V, n, p]
    mag = lin.abs() + err[:, None]
    sq = up((mag * mag).sum((-1, -2)) * (1.0 + 2.0 * gamma(size + 1)))
    lin_norm = up(torch.sqrt(sq.amax(1)))
    e_norm = up(torch.sqrt(up((e * e).sum((-1, -2)) * (1.0 + 2.0 * gamma(size + 1)))))
    return up(lin_norm + e_norm)
