"""Taylor models of the system's Jacobians Jf and dh/dx over boxes: the mean-value form and a
second-order form, the smaller remainder taken entry by entry.

For one entry q(x) = d g_i / dx_a (g = f or h) over a box with centre xc and radii r:

- mean-value form: q(x) in q(xc) + grad q(box) . (x - xc), so the remainder is the radius of
  the gradient's enclosure over the box times r: about sum_{k,l} |T_kl| r_k r_l for the third
  derivatives T of g;
- second-order form (Taylor with the Lagrange remainder on the segment from xc to x):
  q(x) = q(xc) + grad q(xc) . (x - xc) + 1/2 sum_{k,l} T_kl(xi) (x - xc)_k (x - xc)_l with xi
  in the box, T enclosed over the box. The quadratic part is enclosed once (not wrapped into
  the gradient): a cross term k < l contributes |T_kl| r_k r_l (half the mean-value form's
  2 |T_kl| r_k r_l), a square 1/2 T_kk (x - xc)_k^2 lies in 1/2 [min(0, T_kk), max(0, T_kk)]
  r_k^2 and, with the interval's midpoint moved into the centre value, costs a quarter of
  the mean-value form's |T_kk| r_k^2.

On Van der Pol (Jf has -2 mu x1 x2 and mu (1 - x1^2)) the second-order remainder is exact for
the quadratic entries, which on the Van der Pol instances carry most of the system part of the
contraction matrix's remainder. Both forms are valid models of the same entry, so taking, per
entry, the one with the smaller remainder is a valid model; an entry whose second-order model
is NaN (an expression undefined on the box) keeps the mean-value one (NaN there too: never
decides). When every third derivative is identically 0 (g at most quadratic: the Hessian is
constant, the mean-value form is exact) only the mean-value form is built.

Rounding: the enclosures are outward (`certify.spec.enclosures`); each term of the quadratic
enclosure is a product rounded up in magnitude, their sums (non-negative terms, separately for
the two sides) are widened by gamma_K with K the number of terms, and `tm_from_intervals`
rounds the rest.
"""

from __future__ import annotations

import weakref
from typing import Any

import sympy
import torch

from certify.arith.intervals import TINY, Interval, gamma, up
from certify.arith.taylor import TM, tm_from_intervals
from certify.spec.enclosures import (
    enclose_list,
    hessian_f_enclosure,
    hessian_h_enclosure,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
    pad_y,
)

_TERMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _third_terms(system: Any, which: str) -> tuple[list[sympy.Expr], list[tuple[int, ...]]]:
    """The non-zero third derivatives of g = f or h (`which`) over sorted index triples
    j <= k <= l (they are symmetric in j, k, l), and for each Jacobian entry (i, a) the
    quadratic terms it receives: (expression index, entry i * n + a, k, l, off-diagonal).
    Cached per system."""
    per = _TERMS.setdefault(system, {})
    if which in per:
        return per[which]
    xs = list(system.symbols)
    n = len(xs)
    exprs: list[sympy.Expr] = []
    terms: list[tuple[int, ...]] = []
    g_exprs = system.f_expr if which == "f" else system.h_expr
    for i, e in enumerate(g_exprs):
        for j in range(n):
            for k in range(j, n):
                for m in range(k, n):
                    t = sympy.diff(e, xs[j], xs[k], xs[m])
                    if t == 0:
                        continue
                    idx = len(exprs)
                    exprs.append(t)
                    # each distinct index a of the triple is the Jacobian column; the other
                    # two are the quadratic term's pair
                    for a in sorted({j, k, m}):
                        rest = [j, k, m]
                        rest.remove(a)
                        terms.append((idx, i * n + a, rest[0], rest[1], int(rest[0] != rest[1])))
    per[which] = (exprs, terms)
    return per[which]


def quadratic_enclosure(system: Any, which: str, lo: torch.Tensor, hi: torch.Tensor,
                        r: torch.Tensor) -> Interval | None:
    """Enclosure [B, m, n] of 1/2 sum_{k,l} T_{i a k l}(xi) dx_k dx_l over |dx| <= r [B, n]
    and xi in the box [lo, hi] [B, n] (T the third derivatives of g = f or h, `which`), or
    None when every third derivative is identically 0. Module docstring: the rounding."""
    exprs, terms = _third_terms(system, which)
    if not exprs:
        return None
    n = system.n
    m = n if which == "f" else system.p
    lo, r = lo.to(torch.float64), r.to(torch.float64)
    Tlo, Thi = enclose_list(system, exprs, lo, hi)  # [B, E]
    dev = lo.device
    tt = torch.tensor(terms, dtype=torch.long, device=dev)  # [K, 5]
    src, dst, k, l_, off = tt.unbind(-1)
    off = off.bool()
    rk, rl = r[:, k], r[:, l_]  # [B, K]
    rr = up(rk * rl)
    tl, th = Tlo[:, src], Thi[:, src]
    mag = torch.maximum(tl.abs(), th.abs())
    cross = up(mag * rr)  # |T dx_k dx_l| (the pair (k, l) and (l, k) together, halved)
    # squares: 1/2 T dx_k^2 in 1/2 [min(0, T_lo), max(0, T_hi)] r_k^2 (magnitudes per side)
    neg = torch.where(off, cross, up(0.5 * up(tl.clamp(max=0.0).neg() * rr)))
    pos = torch.where(off, cross, up(0.5 * up(th.clamp(min=0.0) * rr)))
    # NaN (an undefined derivative) must reach the sums: clamp drops no NaN, max keeps it
    B = lo.shape[0]
    sneg = torch.zeros(B, m * n, dtype=torch.float64, device=dev).index_add_(1, dst, neg)
    spos = torch.zeros(B, m * n, dtype=torch.float64, device=dev).index_add_(1, dst, pos)
    widen = 1.0 + 2.0 * gamma(len(terms) + 1)
    ql = -up(sneg * widen + TINY)
    qh = up(spos * widen + TINY)
    return Interval(ql.reshape(B, m, n), qh.reshape(B, m, n))


def jacobian_tm(system: Any, which: str, lo: torch.Tensor, hi: torch.Tensor, r: torch.Tensor
                ) -> TM:
    """TM of Jf [B, n, n] (which = "f") or dh/dx [B, p, n] ("h") over z-boxes [B, n + p]
    (coefficients over all n + p box coordinates; the y ones are exactly 0): per entry the
    smaller remainder of the mean-value and the second-order forms (module docstring)."""
    n, p = system.n, system.p
    lo, hi = lo.to(torch.float64), hi.to(torch.float64)
    xl, xh = lo[:, :n], hi[:, :n]
    xc = (0.5 * (lo + hi))[:, :n]
    jac = jacobian_f_enclosure if which == "f" else jacobian_h_enclosure
    hess = hessian_f_enclosure if which == "f" else hessian_h_enclosure
    centre = Interval(*jac(system, xc, xc))
    mean_value = tm_from_intervals(centre, pad_y(Interval(*hess(system, xl, xh)), p), r)
    quad = quadratic_enclosure(system, which, xl, xh, r[:, :n])
    if quad is None:
        return mean_value
    second = tm_from_intervals(centre + quad, pad_y(Interval(*hess(system, xc, xc)), p), r)
    take = second.e < mean_value.e  # False where either is NaN: the mean-value form stays
    return TM(torch.where(take, second.c, mean_value.c),
              torch.where(take[..., None], second.g, mean_value.g),
              torch.where(take, second.e, mean_value.e))
