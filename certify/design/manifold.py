"""The gain-free part of D on the output manifold: its quantities, their search, their bound.

If k is C^1 and k(x, h(x)) = 0 on X, then on the manifold y = h(xhat) and along ker dh(xhat),
v^T D v = v^T (He{P Jf} + 2 lam P) v has no k in it (METHOD §3.5). With S(xhat) = He{P Jf(xhat)}
+ 2 lam P:

- q(xhat) = lam_max(Z^T S Z), Z an orthonormal basis of ker dh(xhat) (`q_values`,
  `manifold_quantity`): > 0 anywhere on {x in X : h(x) in Y} means no gain can pass;
- the largest rate any gain with exact BC could have at a point (`rate_values`);
- for linear h, the residual any gain satisfying the MPDI everywhere must pay
  (`residual_price`);
- the search for the largest value of such a quantity on the manifold (`search_manifold`: a
  tensor grid filtered to the manifold, then projected ascent that refuses steps leaving
  h(x) in Y; sampled, float64, its witness re-checked soundly by `certify.search.witness`);
- the sound upper bound of q for linear h (`vertex_upper_bound`: q is convex in Jf, so on
  each sub-box it is at most its largest value at the vertices of the interval enclosure of
  Jf there; floating-point error carried as a margin, see the function).

Used by the pre-flight check (`certify.checks.necessary`) and the report maps.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from certify.design.metric import (
    enclosure_vertices,
    kernel_basis,
    kernel_values,
    output_matrix,
    sub_boxes,
)
from certify.model.kernels import lam_max
from certify.prove.side import kernel_basis_with_error
from certify.search.falsify import projected_ascent
from certify.spec.system import System

_F64 = torch.float64


def gain_free_D(system: System, P: torch.Tensor, lam: float, x: torch.Tensor,
                with_lam: bool = True) -> torch.Tensor:
    """S(x) = He{P Jf(x)} + 2 lam P [B, n, n] (without 2 lam P unless `with_lam`): the part of
    D that no gain changes along ker dh, at x [B, n]."""
    PJ = P @ system.jac_f(x)
    S = 0.5 * (PJ + PJ.transpose(-1, -2))
    return S + 2.0 * lam * P if with_lam else S


def manifold_quantity(system: System, P, lam: float, x: torch.Tensor) -> torch.Tensor:
    """q(xhat) [B] at points x [B, n], for any h (constant kernel basis when h is linear)."""
    Z = None
    if system.h_is_linear:
        Z = torch.as_tensor(kernel_basis(output_matrix(system)), dtype=_F64)
    return q_values(system, torch.as_tensor(P, dtype=_F64), lam, x, Z)


def q_values(system: System, P: torch.Tensor, lam: float, x: torch.Tensor,
             Z: torch.Tensor | None) -> torch.Tensor:
    """q(x) [B] (differentiable). Z: constant kernel basis (linear h) or None (nonlinear h).

    Nonlinear h: with the projector Pi onto ker dh(x), q = lam_max(Pi S Pi - c (I - Pi)),
    c > ||S||, which equals the kernel-restricted lam_max; NaN where dh loses rank.
    Where ker dh = {0} (every state direction measured: Z with no columns, or p >= n and
    dh of full column rank) q is -inf, the largest value over no direction: the condition
    is vacuous there (and NaN where a nonlinear dh with p >= n loses rank).
    """
    S = gain_free_D(system, P, lam, x)
    if Z is not None:
        if Z.shape[1] == 0:  # every direction measured: the kernel is {0}, q = max of nothing
            return torch.full((x.shape[0],), -math.inf, dtype=_F64)
        return lam_max(Z.T @ S @ Z)
    Jh = system.jac_h(x)  # [B, p, n]
    if system.p >= system.n:  # ker dh = {0} where dh has full column rank, else unknown here
        sv = torch.linalg.svdvals(Jh)
        full = sv[:, system.n - 1] > 1e-9 * (1.0 + sv[:, 0])
        return torch.where(full, torch.full_like(sv[:, 0], -math.inf),
                           torch.full_like(sv[:, 0], math.nan))
    G = Jh @ Jh.transpose(-1, -2)
    n = system.n
    eye = torch.eye(n, dtype=_F64)
    try:
        Pi = eye - Jh.transpose(-1, -2) @ torch.linalg.solve(G, Jh)
    except RuntimeError:
        return torch.full((x.shape[0],), float("nan"), dtype=_F64)
    c = torch.linalg.matrix_norm(S).detach() + 1.0
    return lam_max(Pi @ S @ Pi - c[:, None, None] * (eye - Pi))


def kernel_bases_at(system: System, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point kernel bases for nonlinear h: Z [B, n, n-p] and a validity mask [B]."""
    Jh = system.jac_h(x)
    _, sv, Vh = torch.linalg.svd(Jh, full_matrices=True)
    p = Jh.shape[1]
    ok = sv[:, -1] > 1e-9 * (1.0 + sv[:, 0])
    return Vh[:, p:, :].transpose(-1, -2), ok


def rate_values(system: System, P: torch.Tensor, x: torch.Tensor, Z: torch.Tensor | None
                ) -> torch.Tensor:
    """-lam_max(Z^T He{P Jf} Z, Z^T P Z) / 2 at x [B] (the largest rate any exact-BC gain
    could have at that point); NaN where the kernel basis is unavailable."""
    S0 = gain_free_D(system, P, 0.0, x, with_lam=False)
    if Z is not None:
        A, Bm = Z.T @ S0 @ Z, Z.T @ P @ Z
        L = torch.linalg.cholesky(Bm)
        Li = torch.linalg.inv(L)
        return -0.5 * lam_max(Li @ A @ Li.T)
    Zb, ok = kernel_bases_at(system, x)
    A = Zb.transpose(-1, -2) @ S0 @ Zb
    Bm = Zb.transpose(-1, -2) @ P @ Zb
    L, info = torch.linalg.cholesky_ex(Bm)
    Li = torch.linalg.inv(torch.where((info == 0)[:, None, None], L,
                                      torch.eye(L.shape[-1], dtype=_F64)))
    r = -0.5 * lam_max(Li @ A @ Li.transpose(-1, -2))
    return torch.where(ok & (info == 0), r, torch.full_like(r, float("nan")))


def residual_price(system: System, P: torch.Tensor, lam: float, directions: torch.Tensor,
                   bases: torch.Tensor, samples: int = 201) -> tuple[float, list[float] | None]:
    """max over chords z + s v in X (v in ker C unit, h(z) in Y) of the best sub-segment
    integral of v^T (He{P Jf} + 2 lam P) v, divided by 2 ||P v||.

    If D <= 0 held on all of X x Y, eps_bar would be at least this (METHOD §3.5); trapezoid
    quadrature on `samples` points per chord. Returns (price, [chord start..end as x0, x1]).
    """
    X = torch.as_tensor(system.X, dtype=_F64)
    best, where = 0.0, None
    for v in directions:  # a handful of kernel directions
        v = v / torch.linalg.vector_norm(v)
        a = (X[:, 0] - bases) / v  # inf/nan where v_i = 0: masked just below
        b = (X[:, 1] - bases) / v
        lo_s = torch.where(v.abs() > 1e-15, torch.minimum(a, b), torch.full_like(a, -math.inf))
        hi_s = torch.where(v.abs() > 1e-15, torch.maximum(a, b), torch.full_like(a, math.inf))
        s0, s1 = lo_s.max(1).values, hi_s.min(1).values  # [Nz]
        frac = torch.linspace(0.0, 1.0, samples, dtype=_F64)
        s = s0[:, None] + (s1 - s0)[:, None] * frac[None]  # [Nz, S]
        pts = bases[:, None, :] + s[..., None] * v  # [Nz, S, n]
        pts = torch.maximum(torch.minimum(pts, X[:, 1]), X[:, 0])
        S = gain_free_D(system, P, lam, pts.reshape(-1, system.n))
        qv = torch.einsum("i,bij,j->b", v, S, v).reshape(len(bases), samples)
        ds = ((s1 - s0) / (samples - 1))[:, None]
        seg = 0.5 * (qv[:, 1:] + qv[:, :-1]) * ds
        cum = torch.cat([torch.zeros(len(bases), 1, dtype=_F64), seg.cumsum(1)], 1)
        run_min, arg_min = torch.cummin(cum, dim=1)
        gain = cum - run_min  # best segment ending at each sample
        j = torch.argmax(gain, dim=1)
        g = gain[torch.arange(len(bases)), j]
        i_best = int(torch.argmax(g))
        val = float(g[i_best]) / (2.0 * float(torch.linalg.vector_norm(P @ v)))
        if val > best:
            jb = int(j[i_best])
            ib = int(arg_min[i_best, jb])
            best = val
            where = pts[i_best, ib].tolist() + pts[i_best, jb].tolist()
    return best, where


_F64 = torch.float64
Quantity = Callable[[torch.Tensor], torch.Tensor]  # points [B, n] -> values [B]


def manifold_grid(system: System, points: int) -> torch.Tensor:
    """Odd tensor grid over X with the centre lines exactly on it."""
    n = system.n
    per = max(3, int(round(points ** (1.0 / n))) | 1)
    k = torch.arange(per, dtype=_F64) / (per - 1)
    axes = []
    for a, b in system.X:
        ax = float(a) + (float(b) - float(a)) * k
        ax[per // 2] = 0.5 * (float(a) + float(b))
        ax[-1] = float(b)
        axes.append(ax)
    return torch.cartesian_prod(*axes).reshape(-1, n)


def on_manifold(system: System, x: torch.Tensor) -> torch.Tensor:
    """Mask [B]: h(x) in Y at each of x [B, n]."""
    Y = torch.as_tensor(system.Y, dtype=_F64)
    hx = system.h(x)
    return ((hx >= Y[:, 0]) & (hx <= Y[:, 1])).all(-1)


def maximise_on_manifold(system: System, fn: Quantity, x0: torch.Tensor, steps: int = 150
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Projected ascent of fn over X from x0 [B, n], refusing steps that leave h(x) in Y."""
    X = torch.as_tensor(system.X, dtype=_F64)
    return projected_ascent(fn, x0, X[:, 0], X[:, 1], steps,
                            feasible=lambda x: on_manifold(system, x))


def search_manifold(system: System, fn: Quantity, x: torch.Tensor, vals: torch.Tensor,
                    starts: int, seed: int) -> tuple[float, torch.Tensor]:
    """Best of grid values and a multi-start ascent from the top grid points + random ones."""
    vals = torch.where(torch.isfinite(vals), vals, torch.full_like(vals, -math.inf))
    k = min(starts, len(vals))
    centre = torch.as_tensor(system.X.mean(1), dtype=_F64)
    diam = float(np.linalg.norm(system.X[:, 1] - system.X[:, 0]))
    fin = vals[torch.isfinite(vals)]
    scale = 1.0 + (float(fin.abs().max()) if len(fin) else 0.0)
    # rank by value, ties broken towards the centre of X (a witness that reads best)
    key = vals - 1e-10 * scale * torch.linalg.vector_norm(x - centre, dim=1) / diam
    top = torch.topk(key, k).indices
    gen = torch.Generator().manual_seed(seed)
    rnd = x[torch.randint(len(x), (max(1, starts // 2),), generator=gen)]
    bx, bv = maximise_on_manifold(system, fn, torch.cat([x[top], rnd]))
    allv = torch.cat([vals[top], bv])
    allx = torch.cat([x[top], bx])
    best = float(allv.max())
    # among (numerically) tied maxima, the point nearest the centre of X reads best
    tied = allv >= best - 1e-12 * (1.0 + abs(best))
    dist = torch.where(tied, torch.linalg.vector_norm(allx - centre, dim=1),
                       torch.full_like(allv, math.inf))
    i = int(torch.argmin(dist))
    return float(allv[i]), allx[i]


def vertex_upper_bound(system: System, P: np.ndarray, lam: float, subdivisions: int | None = None
                       ) -> float | None:
    """Sound bound on max q over the manifold (linear h): q is lam_max of an affine function
    of Jf, hence convex in Jf, so on each sub-box it is at most its value at the vertices of
    the interval enclosure of Jf. Sub-boxes whose h-enclosure misses Y are dropped. A margin
    of 64 n u (||S|| + 1) covers LAPACK's eigenvalue error and the rounding in S."""
    if not system.h_is_linear:
        return None
    Z, z_err = kernel_basis_with_error(output_matrix(system))
    n = system.n
    if Z.shape[1] == 0:
        return -math.inf
    per = subdivisions or max(1, int(4096 ** (1.0 / n)))
    lo, hi = sub_boxes(system, per)
    if len(lo) == 0:
        return -math.inf
    relevant = np.repeat((np.abs(Z).sum(1) > 0)[None, :], n, axis=0)
    try:
        verts = enclosure_vertices(system, lo, hi, relevant)
    except ValueError:
        return None
    vals = kernel_values(verts.all, P, Z, lam)
    if not np.all(np.isfinite(vals)):
        return None
    Snorm = np.abs(P).sum() * np.abs(verts.all).max(initial=0.0) + 2 * abs(lam) * np.abs(P).sum()
    # 3 z_err ||S||: Z is within z_err of an exact orthonormal kernel basis (as in the prover)
    return float(vals.max() + 64 * n * np.finfo(float).eps * (Snorm + 1.0) + 3 * z_err * Snorm)
