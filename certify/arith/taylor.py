"""First-order Taylor models over boxes: q(z) in c + g . (z - zc) + [-e, e].

`TM` holds, per box, the value c [...], the coefficients g [..., d] (point values) and the
remainder e [...] >= 0, valid for every z with |z - zc| <= r (r [..., d], the box's radii).
Linear maps act exactly on (c, g) and only the remainder wraps, so dependencies on the box
coordinates survive the layers. Rounding: the float errors of c and g are absorbed into e
with Higham's gamma_k |.| bounds, rounded up (`certify.arith.intervals.gamma`, `up`).
The activations' rules over Taylor models live with the gain's Taylor arithmetic
(`certify.model.gain.taylor`); the enclosures built from them in `certify.enclose.taylor`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.intervals import TINY, Interval, U, gamma, up

__all__ = ["TM", "tm_from_intervals", "tm_absorb", "tm_linear", "tm_rho", "tm_mul", "tm_sum",
           "tm_add", "tm_point", "tm_index", "reach", "as_radii"]


@dataclass
class TM:
    """First-order Taylor model over boxes: value c [...], coefficients g [..., d] (point),
    remainder e [...] >= 0, valid for every z in the box with |z - zc| <= r.

    Linear maps act exactly on (c, g) and only the remainder wraps, so dependencies on the
    box coordinates survive the layers; float errors of c and g are absorbed into e."""

    c: torch.Tensor
    g: torch.Tensor
    e: torch.Tensor


def reach(g: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Upper bound of sum_m |g_m| r_m, r broadcast over the leading dims of g."""
    d = g.shape[-1]
    return up((g.abs() * r).sum(-1) * (1.0 + 2.0 * gamma(d + 1)))


def as_radii(r: torch.Tensor, ndim: int) -> torch.Tensor:
    """Reshape radii [B, d] to broadcast against a coefficient tensor with `ndim` dims."""
    return r.reshape(r.shape[0], *([1] * (ndim - 2)), r.shape[1])


def tm_from_intervals(center: Interval, deriv: Interval, r: torch.Tensor) -> TM:
    """TM from a thin enclosure at the centre and an enclosure of the gradient over the box
    (mean-value theorem): center [B, ...], deriv [B, ..., d]."""
    c, cr = center.midrad()
    g, gr_ = deriv.midrad()
    rr = as_radii(r, g.ndim)
    e = up(cr + up((gr_ * rr).sum(-1) * (1.0 + 2.0 * gamma(g.shape[-1] + 1))))
    return TM(c, g, e)


def tm_absorb(c: torch.Tensor, g: torch.Tensor, e: torch.Tensor, r: torch.Tensor, k: int) -> TM:
    """Add gamma_k (|c| + sum |g| r) to the remainder (rounding of c and g), rounded up."""
    gk = gamma(k)
    rr = as_radii(r, g.ndim)
    e = up((e + gk * (c.abs() + reach(g, rr))) * (1.0 + 2.0 * gk) + k * TINY)
    return TM(c, g, e)


def tm_linear(t: TM, W: torch.Tensor, b: torch.Tensor | None, r: torch.Tensor) -> TM:
    """x -> x @ W (+ b) on the last value dim: t.c [..., k], t.g [..., k, d]; W [k, m]."""
    k = W.shape[0]
    gk = gamma(k + 2)
    c = t.c @ W
    if b is not None:
        c = c + b
    g = (t.g.transpose(-1, -2) @ W).transpose(-1, -2)
    rr = as_radii(r, t.g.ndim)
    slack = t.e + gk * (t.c.abs() + reach(t.g, rr))
    e = slack @ W.abs()
    if b is not None:
        e = e + gk * (b.abs() + c.abs())
    e = up(e * (1.0 + 2.0 * gk) + k * TINY)
    return TM(c, g, e)


def tm_rho(t: TM, r: torch.Tensor) -> torch.Tensor:
    """Radius of the range of t over the box: sum |g| r + e (rounded up)."""
    return up(reach(t.g, as_radii(r, t.g.ndim)) + t.e)


def tm_mul(a: TM, b: TM, r: torch.Tensor) -> TM:
    """Elementwise product (broadcasting)."""
    c = a.c * b.c
    g = a.c.unsqueeze(-1) * b.g + b.c.unsqueeze(-1) * a.g
    ra = tm_rho(a, r) if a.g.ndim else a.e
    rb = tm_rho(b, r)
    ga = reach(a.g, as_radii(r, a.g.ndim))
    gb = reach(b.g, as_radii(r, b.g.ndim))
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
    extra = gamma(k + 1) * (t.c.abs().sum(dim) + reach(t.g, as_radii(r, t.g.ndim)).sum(dim))
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


