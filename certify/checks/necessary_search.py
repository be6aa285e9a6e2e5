"""The search for the largest value of a quantity on the output manifold {x in X : h(x) in Y}.

A tensor grid over X (odd, centre lines on it) filtered to the manifold, then a multi-start
projected ascent (`certify.search.falsify.projected_ascent`) that refuses steps leaving h(x) in Y,
from the best grid points and seeded random ones. Ties are broken towards the centre of X
(a witness that reads best). Used by `certify.checks.necessary` for q and the rate cap: a
sampled, float64 search (the witness is re-checked soundly by `certify.search.witness`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from certify.search.falsify import projected_ascent
from certify.spec.system import System

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
