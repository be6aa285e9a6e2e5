"""Whole-box decisions of lam_max(A) <= level for affine families with many coordinates.

A box's Taylor model reduces it to A(v) = c + sum_m v_m G_m + E, v in [-1, 1]^d, |E| <= rem
entrywise (`certify.enclose.taylor.tm_lam_upper`). lam_max is convex in v, so the decision is
exact at the 2^d vertices (`certify.enclose.decide`); beyond MAX_VERTEX_DIM coordinates
(d = n + p = 9 for three measured oscillators, 12 for four) that is too many, and the first-
order part used to join the remainder entrywise: every box became an interval matrix whose
hull forgets which directions the coordinates move D in, so boxes far below the level stayed
open. `decide_whole_box` decides such a box as a whole instead:

1. congruence by the box's own room, M = (lvl I - c)^(-1/2) (`certify.enclose.decide.
   room_congruence`): M (A - lvl I) M <= 0 iff A <= lvl I, and there the centre is -I, each
   coordinate counts by ||M G_m M||_2 (its effect relative to the room the centre leaves in
   the directions it moves D in) and the remainder by rho(|M| rem |M|);
2. the `k` coordinates with the largest ||M G_m M||_2 (k = min(d, MAX_VERTEX_DIM)) stay
   vertices; the others are bounded by Weyl in the Loewner order, sum_{m not kept} v_m M G_m M
   <= sum ||M G_m M||_2 I, which lowers the level the vertices are held to;
3. every vertex of the kept coordinates is tested by the certified Cholesky test
   (`certify.arith.eigen.lam_max_at_most`), the likeliest-worst vertex first.

Sound: a congruence by any nonsingular float M preserves the decision, with the float errors
of forming M c M and M G_m M in the remainder (`room_congruence`); the spectral norms are
upper bounds of the (lower-triangle) symmetric matrices the vertex tests read
(`certify.arith.eigen.lam_max_upper_point` of G and -G); the vertex sums' float errors,
gamma_{d+5} (|M c M| + sum_m |M G_m M|) entrywise, join the remainder; the level is rounded
down at every step. A box whose centre is not below the level (lvl I - c not positive
definite) is never decided here. NaN/Inf never decide.
"""

from __future__ import annotations

import torch

from certify.arith.eigen import MAX_VERTEX_DIM, lam_max_at_most, lam_max_upper_point, rho_upper
from certify.arith.intervals import TINY, down, gamma, up
from certify.enclose.decide import likely_worst_vertex, lower_sym, room_congruence, vertex_test


def spectral_norm_upper(G: torch.Tensor) -> torch.Tensor:
    """Upper bound of ||sym_lower(G)||_2 for matrices G [..., n, n] read by their lower
    triangles: max(lam_max(G), lam_max(-G)), each a sound bound -> [...]."""
    G = lower_sym(G)
    return torch.maximum(lam_max_upper_point(G), lam_max_upper_point(-G))


def decide_whole_box(c: torch.Tensor, rG: torch.Tensor, rem: torch.Tensor, lvl: float,
                     keep: int = MAX_VERTEX_DIM) -> torch.Tensor:
    """Whether lam_max(A) <= lvl is proved on the whole box, for c [B, n, n], rG [B, d, n, n]
    (the first-order coefficients times the radii) and rem [B, n, n] (symmetric, >= 0, the
    entrywise remainder of the Taylor model, its own rounding included): the module
    docstring's test, with at most `keep` coordinates as vertices -> bool [B]."""
    B, d = rG.shape[:2]
    out = torch.zeros(B, dtype=torch.bool, device=c.device)
    finite = (torch.isfinite(c).flatten(1).all(-1) & torch.isfinite(rG).flatten(1).all(-1)
              & torch.isfinite(rem).flatten(1).all(-1))
    if not bool(finite.any()):
        return out
    idx = torch.nonzero(finite).squeeze(-1)
    # the centre must be below the level (a congruence cannot move it there)
    below = lam_max_at_most(c[idx], torch.full((len(idx),), lvl, dtype=c.dtype,
                                               device=c.device))
    idx = idx[below]
    if not len(idx):
        return out
    parts = room_congruence(c[idx], rG[idx], rem[idx], lvl)
    if parts is None:  # eigh failed: undecided (sound)
        return out
    cc, gc, rc = parts
    gk = gamma(d + 5)
    rc = up((rc + gk * (cc.abs() + gc.abs().sum(1))) * (1.0 + 2.0 * gk) + (d + 2) * TINY)
    rc = torch.maximum(rc, rc.transpose(1, 2))
    norms = spectral_norm_upper(gc)  # [b, d]
    k = min(d, int(keep))
    order = torch.argsort(norms, dim=-1, descending=True)
    kept, rest = order[:, :k], order[:, k:]
    weyl_rest = up(torch.gather(norms, 1, rest).sum(-1) * (1.0 + 2.0 * gamma(d)))
    t = down(down(-rho_upper(rc)) - weyl_rest)
    ok = torch.isfinite(t) & (t > -1.0)  # the centre is -I: below -1 nothing passes
    # all coordinates by Weyl (spectral norms) first: no vertex needed where it passes
    weyl_all = up(lam_max_upper_point(lower_sym(cc)) + up(norms.sum(-1) * (1.0 + 2.0 * gamma(d))))
    decided = ok & (weyl_all <= down(-rho_upper(rc)))
    todo = torch.nonzero(ok & ~decided).squeeze(-1)
    if len(todo):
        ar = torch.arange(len(todo), device=c.device)[:, None]
        gk_ = gc[todo][ar, kept[todo]]  # [b', k, n, n]
        worst = likely_worst_vertex(cc[todo], gk_)
        decided[todo] = vertex_test(cc[todo], gk_, t[todo], worst)
    out[idx] = decided
    return out


__all__ = ["decide_whole_box", "spectral_norm_upper"]
