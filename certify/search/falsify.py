"""The lower side of every check: dense grid + multi-start projected gradient ascent.

`maximize_over_box` looks for the largest value of a batched scalar function over a box. Every
number it returns is the function's float64 value at a concrete point, so it is a valid lower
bound on the supremum (never a proof of anything about the whole box).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.progress import NullProgress, Progress
from certify.search.threads import parallel_chunks

ScoreFn = Callable[[torch.Tensor], torch.Tensor]  # [B, d] float64 -> [B]


@dataclass
class SearchOutcome:
    """Best points found; values are float64 evaluations at those points."""

    best_value: float
    best_point: np.ndarray  # [d]
    top_points: np.ndarray  # [k, d], distinct, best first
    top_values: np.ndarray  # [k]
    grid_points: int
    grid_shape: list[int]
    above_threshold: int  # grid points with value > threshold
    starts: int
    grid_best_value: float
    nonfinite: int = 0  # grid points where the function was NaN/Inf
    history: list[float] = field(default_factory=list)

    @property
    def above_fraction(self) -> float:
        return self.above_threshold / max(1, self.grid_points)


def grid_shape(lo: np.ndarray, hi: np.ndarray, min_points: int) -> list[int]:
    """Per-dimension resolution, proportional to the box widths, with product >= min_points."""
    d = len(lo)
    widths = np.maximum(hi - lo, 1e-300)
    scale = (min_points / np.prod(widths)) ** (1.0 / d)
    counts = np.maximum(2, np.ceil(widths * scale)).astype(int)
    while np.prod(counts) < min_points:  # rounding can leave it short
        counts[np.argmin(counts / widths)] += 1
    return counts.tolist()


def grid_chunk(lo: torch.Tensor, hi: torch.Tensor, shape: list[int], start: int,
               stop: int) -> torch.Tensor:
    """Points start..stop-1 of the tensor-product grid (row-major), shape [stop-start, d]."""
    idx = torch.arange(start, stop, dtype=torch.int64, device=lo.device)
    cols = []
    for j in reversed(range(len(shape))):
        m = shape[j]
        k = idx % m
        idx = idx // m
        cols.append(lo[j] + (hi[j] - lo[j]) * k.to(lo.dtype) / (m - 1))
    return torch.stack(cols[::-1], dim=1)


def screen_tolerance(fn: ScoreFn, screen: ScoreFn, lo: torch.Tensor, hi: torch.Tensor,
                     seed: int, threshold: float = 0.0, samples: int = 4096
                     ) -> tuple[float, float]:
    """The re-check band: 8x the largest |screen - fn| seen on random points (plus a floor);
    and the fraction of those points that would fall in the band or above the threshold."""
    gen = torch.Generator().manual_seed(seed + 7919)  # on the CPU: the same on every device
    pts = lo + (hi - lo) * torch.rand(samples, len(lo), generator=gen, dtype=torch.float64,
                                      device="cpu").to(lo.device)
    exact = fn(pts)
    approx = screen(pts).to(torch.float64)
    ok = torch.isfinite(exact) & torch.isfinite(approx)
    if not bool(ok.any()):
        return math.inf, 1.0
    err = torch.abs(exact - approx)[ok].max().item()
    scale = torch.abs(exact[ok]).max().item()
    tol = 8.0 * err + 1e-6 * (1.0 + scale)
    return tol, float((~ok | (approx > threshold - tol)).double().mean())


def _distinct_top(points: torch.Tensor, values: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                  k: int, min_sep: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to k best points pairwise at least `min_sep` apart in box-scaled sup-norm."""
    order = torch.argsort(values, descending=True)
    pts, vals = points[order], values[order]
    scaled = (pts - lo) / (hi - lo)
    keep: list[int] = []
    for i in range(len(pts)):  # over a short candidate list, not over samples
        if len(keep) >= k:
            break
        if not keep or torch.min(torch.max(torch.abs(scaled[keep] - scaled[i]), dim=1).values) \
                > min_sep:
            keep.append(i)
    return pts[keep], vals[keep]


def sweep_range(fn: ScoreFn, screen: ScoreFn | None, lo: torch.Tensor, hi: torch.Tensor,
                shape: list[int], start: int, stop: int, threshold: float, tol: float,
                keep: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """Grid points start..stop-1: their top `keep` candidates (points, float64 values), the
    count above `threshold` and the non-finite count (see `maximize_over_box`)."""
    pts = grid_chunk(lo, hi, shape, start, stop)
    with torch.no_grad():
        if screen is None:
            vals = fn(pts)
            bad = ~torch.isfinite(vals)
            vals = torch.where(bad, torch.full_like(vals, math.inf), vals)
            n_above, n_bad = int((vals > threshold).sum()), int(bad.sum())
            tv, ti = torch.topk(vals, min(keep, len(vals)))
        else:
            approx = screen(pts).to(torch.float64)
            approx = torch.where(torch.isfinite(approx), approx,
                                 torch.full_like(approx, math.inf))
            near = approx > threshold - tol
            n_above = n_bad = 0
            if bool(near.any()):
                exact = fn(pts[near])
                bad = ~torch.isfinite(exact)
                n_bad = int(bad.sum())
                n_above = int((exact > threshold).sum()) + n_bad
            # every point of the float64 top `keep` has approx >= (the keep-th approx) - 2 err
            # (err: the screen's error, tol = 8 err): those are evaluated in float64, the
            # others stand below the keep-th float64 value and take no part in the choice
            kth = torch.topk(approx, min(keep, len(approx))).values[-1]
            top = approx >= kth - tol
            vals = torch.full_like(approx, -math.inf)
            exact = fn(pts[top])
            vals[top] = torch.where(torch.isfinite(exact), exact,
                                    torch.full_like(exact, math.inf))
            tv, ti = torch.topk(vals, min(keep, len(vals)))
    return pts[ti], tv, n_above, n_bad


def _remote_sweep(remote: tuple[Any, Callable[..., Any], dict[str, Any]], grid: dict[str, Any],
                  total: int, tol: float, use_screen: bool, progress: Progress,
                  task: str) -> list[tuple]:
    """The grid's chunks on `remote`'s executor, a few tasks per worker, flattened in order."""
    from certify.search.distributed.executor import chunk_ranges

    executor, chunk_fn, payload = remote
    ranges = chunk_ranges(total, 4 * executor.workers, align=grid["chunk"])
    grid_payload = {**payload, "grid": grid}
    grid_payload["key"] = f"{payload.get('key')}:{hash(repr(grid))}"  # one scatter per sweep
    parts = executor.map_chunks(chunk_fn, grid_payload,
                                [(a, b, tol, use_screen) for a, b in ranges])
    progress.update(task, advance=total)
    return [r for part in parts for r in part]


def maximize_over_box(fn: ScoreFn, lo: np.ndarray, hi: np.ndarray, *, grid_points: int,
                      starts: int = 32, steps: int = 100, top_k: int = 5, seed: int = 0,
                      threshold: float = 0.0, chunk: int = 8192,
                      screen: ScoreFn | None = None,
                      progress: Progress | None = None, task: str = "search",
                      remote: tuple[Any, Callable[..., Any], Any] | None = None,
                      device: torch.device | str | None = None) -> SearchOutcome:
    """Largest value of `fn` over the box [lo, hi]: grid, then projected gradient ascent.

    Ascent starts from the best distinct grid points and from seeded random points; steps are
    normalised (Adam-like) and projected back to the box.

    `screen`, if given, is a cheaper approximation of `fn` (e.g. float32) used to sweep the
    grid: its error is measured on a calibration sample, every grid point within 8x that error
    of `threshold`, and every point within 8x that error of a chunk's `keep`-th best screen
    value (a superset of the chunk's float64 best), is re-evaluated with `fn` in float64, so
    the returned values, the candidates and the count above `threshold` are float64 results,
    as without it (where the calibration's error holds over the grid).

    `remote = (executor, chunk_fn, payload)`, with an executor whose work runs elsewhere, sweeps
    the grid there instead of on local threads: `chunk_fn(payload, start, stop, tol,
    use_screen)` (payload with the grid added under "grid") must return `sweep_range`'s
    results for [start, stop) in `chunk`-sized pieces (e.g.
    `certify.search.distributed.payload.mpdi_grid_chunk`);
    the merge is the same, in grid order, so the outcome is identical.

    `device`: where the points live (`fn` must accept them there, e.g. a GridKernel of a
    problem moved with `Problem.on`); random numbers are drawn on the CPU and moved, so the
    points are the same on every device. Returned arrays are on the CPU.
    """
    progress = progress or NullProgress()
    device = torch.device("cpu" if device is None else device)
    lo_t = torch.as_tensor(np.asarray(lo, np.float64), dtype=torch.float64, device=device)
    hi_t = torch.as_tensor(np.asarray(hi, np.float64), dtype=torch.float64, device=device)
    shape = grid_shape(np.asarray(lo, float), np.asarray(hi, float), grid_points)
    total = int(np.prod(shape))
    keep = max(4 * starts, 4 * top_k, 16)
    cand_pts = torch.empty(0, len(shape), dtype=torch.float64, device=device)
    cand_vals = torch.empty(0, dtype=torch.float64, device=device)
    above = 0
    nonfinite = 0
    progress.start(task, total=total)
    with torch.no_grad():
        tol = 0.0
        if screen is not None:
            tol, near_fraction = screen_tolerance(fn, screen, lo_t, hi_t, seed, threshold)
            if near_fraction > 0.25:  # most points need the float64 re-check: skip the screen
                screen = None

        def sweep(start: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
            out = sweep_range(fn, screen, lo_t, hi_t, shape, start, min(total, start + chunk),
                              threshold, tol, keep)
            progress.update(task, advance=min(total, start + chunk) - start)
            return out

        with contextlib.ExitStack() as stack:
            if remote is not None and (getattr(remote[0], "remote", False)
                                       or getattr(remote[0], "workers", 1) > 1):
                grid = {"lo": lo_t.cpu().numpy(), "hi": hi_t.cpu().numpy(), "shape": shape,
                        "threshold": threshold, "keep": keep, "chunk": chunk}
                results: Any = _remote_sweep(remote, grid, total, tol, screen is not None,
                                             progress, task)
            else:
                results = stack.enter_context(parallel_chunks()).map(
                    sweep, range(0, total, chunk))
            for pts, tv, n_above, n_bad in results:
                above += n_above
                nonfinite += n_bad
                cand_pts = torch.cat([cand_pts, pts.to(device)])
                cand_vals = torch.cat([cand_vals, tv.to(device)])
                if len(cand_vals) > 4 * keep:
                    tv, ti = torch.topk(cand_vals, keep)
                    cand_pts, cand_vals = cand_pts[ti], tv
    grid_best = float(cand_vals.max()) if len(cand_vals) else -math.inf
    gen = torch.Generator().manual_seed(seed)
    seeds, _ = _distinct_top(cand_pts, cand_vals, lo_t, hi_t, max(1, starts // 2), 0.02)
    n_rand = max(0, starts - len(seeds))
    rand = lo_t + (hi_t - lo_t) * torch.rand(n_rand, len(shape), generator=gen,
                                             dtype=torch.float64, device="cpu").to(device)
    x = torch.cat([seeds, rand]) if starts > 0 else seeds[:0]
    history: list[float] = []
    if len(x) and steps > 0:
        x, v = projected_ascent(fn, x, lo_t, hi_t, steps, history)
        cand_pts = torch.cat([cand_pts, x])
        cand_vals = torch.cat([cand_vals, v])
    finite = torch.isfinite(cand_vals) | (cand_vals == math.inf)
    cand_pts, cand_vals = cand_pts[finite], cand_vals[finite]
    top_p, top_v = _distinct_top(cand_pts, cand_vals, lo_t, hi_t, max(1, top_k))
    progress.finish(task)
    return SearchOutcome(
        best_value=float(top_v[0]) if len(top_v) else -math.inf,
        best_point=top_p[0].cpu().numpy() if len(top_p)
        else (np.asarray(lo) + np.asarray(hi)) / 2,
        top_points=top_p.cpu().numpy(), top_values=top_v.cpu().numpy(), grid_points=total,
        grid_shape=shape, above_threshold=above, starts=len(x), grid_best_value=grid_best,
        nonfinite=nonfinite, history=history,
    )


def projected_ascent(fn: ScoreFn, x0: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                     steps: int, history: list[float] | None = None,
                     feasible: Callable[[torch.Tensor], torch.Tensor] | None = None,
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched projected Adam ascent from x0 [B, d]; the best point seen per start and its value.

    Steps are projected onto the box; where `feasible` (a [B, d] -> [B] bool mask) refuses the
    new point, that start keeps its old one (e.g. to stay on an output manifold).
    """
    history = [] if history is None else history
    width = hi - lo
    x = x0.clone().requires_grad_(True)
    m = torch.zeros_like(x0)
    v = torch.zeros_like(x0)
    best_x = x0.clone()
    with torch.no_grad():
        best_v = fn(x0)
    best_v = torch.where(torch.isfinite(best_v), best_v, torch.full_like(best_v, -math.inf))
    lr0 = 0.02
    for it in range(1, steps + 1):
        val = fn(x)
        finite = torch.isfinite(val)
        if not val.requires_grad:  # fn does not depend on x: nothing to climb
            break
        (grad,) = torch.autograd.grad(torch.where(finite, val, 0.0).sum(), x)
        with torch.no_grad():
            improved = finite & (val > best_v)
            best_v = torch.where(improved, val, best_v)
            best_x[improved] = x[improved]
            g = torch.nan_to_num(grad * width, nan=0.0, posinf=0.0, neginf=0.0)
            m.mul_(0.9).add_(0.1 * g)
            v.mul_(0.999).add_(0.001 * g * g)
            mhat = m / (1 - 0.9**it)
            vhat = v / (1 - 0.999**it)
            lr = lr0 * (1.0 - 0.9 * it / steps)
            cand = torch.maximum(torch.minimum(x + lr * width * mhat / (vhat.sqrt() + 1e-12), hi),
                                 lo)
            if feasible is not None:
                cand = torch.where(feasible(cand)[:, None], cand, x)
            x.copy_(cand)
        if it % 10 == 0:
            history.append(float(best_v.max()))
    with torch.no_grad():
        val = fn(x.detach())
        val = torch.where(torch.isfinite(val), val, torch.full_like(val, -math.inf))
        improved = val > best_v
        best_x[improved] = x.detach()[improved]
        best_v = torch.where(improved, val, best_v)
    return best_x.detach(), best_v
