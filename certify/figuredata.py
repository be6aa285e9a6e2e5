"""Typed arrays behind the report's figures, carried by the Certificate, at figure size.

Plain float lists (NaN where a value is undefined, e.g. where h(x) leaves Y), so that the
JSON form round-trips through `certify.results.to_jsonable` / `from_jsonable`, which is the
one place where JSON's "NaN"/"Infinity" spellings are turned back into floats. Renderers
read these dataclasses and never decode strings. Computed by `certify.verify.report_maps`
(maps) and the MPDI check (the prover's leaf boxes and its proved volume over time).

Figure arrays hold what a figure can show, not more (`FigureData.compact`, applied by the
Certificate, so a report drawn in memory and one re-drawn from the saved JSON are the
same): values keep `FIGURE_DIGITS` significant digits; a map keeps at most `MAP_POINTS`
points per axis, each coarse cell the largest value of the fine cells it covers (every map
here is worse when larger: lam_max(D), q, ||k||), so the worst grid value survives and no
cell > 0 is hidden; the prover's leaves are merged where their projections coincide, the
worst status winning, with the leaf counts kept. The numbers a check decides with are in
its result, at full precision, never here.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any

#: significant digits kept in figure arrays (a colour scale or a line needs about 3)
FIGURE_DIGITS = 4
#: significant digits kept in the coordinates of map points (positions need no more)
COORD_DIGITS = 9
#: at most this many points per axis of a map (the report draws one cell per point)
MAP_POINTS = 41
#: status precedence where projected leaf boxes coincide: the worst one is shown
STATUS_RANK = {"proved": 0, "unknown": 1, "violated": 2}


def round_sig(value: float, digits: int = FIGURE_DIGITS) -> float:
    """`value` to `digits` significant digits; the sign, zero, NaN and +-Inf are kept (a
    non-zero value never rounds to zero, so a value > 0 stays > 0)."""
    if value == 0 or not math.isfinite(value):
        return value
    r = float(f"{value:.{digits}g}")
    return r if math.isfinite(r) else value  # near the largest float, rounding up overflows


def round_list(values: Any, digits: int = FIGURE_DIGITS) -> Any:
    """`round_sig` through nested lists of floats."""
    if isinstance(values, list):
        return [round_list(v, digits) for v in values]
    return round_sig(float(values), digits)


def _cover(fine: Any, coarse: Any) -> Any:
    """[len(coarse), len(fine)] bool: which fine cells each coarse cell overlaps (cells are
    centred on their points, edges halfway between neighbours); every fine cell is covered."""
    import numpy as np

    def edges(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mid = (c[1:] + c[:-1]) / 2
        return np.concatenate([[c[0]], mid]), np.concatenate([mid, [c[-1]]])

    flo, fhi = edges(fine)
    clo, chi = edges(coarse)
    # both sets of cells tile [first point, last point], so each fine cell overlaps one
    return (flo[None, :] < chi[:, None]) & (fhi[None, :] > clo[:, None])


def downsample_max(x: list[float], y: list[float], values: list[list[float]],
                   points: int = MAP_POINTS) -> tuple[list[float], list[float], list[list[float]]]:
    """A map on at most `points` x `points` evenly spaced points spanning the same box, each
    value the largest finite value of the fine cells its cell overlaps (NaN where all are
    NaN). Hence the largest value survives, and every fine cell > 0 lies in a coarse cell
    > 0 (positive regions may grow by up to one fine cell, never shrink). values[j][i] is at
    (x[i], y[j]), x and y increasing; a grid already small enough is returned unchanged."""
    import numpy as np

    v = np.asarray(values, dtype=float)
    fx, fy = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if (len(fx) <= points and len(fy) <= points) or not (
            np.all(np.diff(fx) > 0) and np.all(np.diff(fy) > 0)):
        return x, y, values
    cx = np.linspace(fx[0], fx[-1], points) if len(fx) > points else fx
    cy = np.linspace(fy[0], fy[-1], points) if len(fy) > points else fy
    mx = _cover(fx, cx) if len(fx) > points else np.eye(len(fx), dtype=bool)
    my = _cover(fy, cy) if len(fy) > points else np.eye(len(fy), dtype=bool)
    finite = ~np.isnan(v)
    filled = np.where(finite, v, -np.inf)
    # along x, then along y: max over the covered fine cells, and how many were not NaN
    rows = np.stack([filled[:, m].max(axis=1) for m in mx], axis=1)           # [ny, cx]
    rows_n = np.stack([finite[:, m].sum(axis=1) for m in mx], axis=1)
    out = np.stack([rows[m].max(axis=0) for m in my], axis=0)                 # [cy, cx]
    out_n = np.stack([rows_n[m].sum(axis=0) for m in my], axis=0)
    out = np.where(out_n > 0, out, np.nan)
    return cx.tolist(), cy.tolist(), out.tolist()


@dataclass
class GridMap:
    """A quantity on a grid over the first two state coordinates: values[j][i] at (x[i], y[j])."""

    x: list[float]
    y: list[float]
    values: list[list[float]]
    axes: list[str] = field(default_factory=list)

    def compact(self) -> GridMap:
        """At most `MAP_POINTS` per axis (`downsample_max`), values to `FIGURE_DIGITS`
        digits; a malformed map (ragged, wrong shape) is returned unchanged (the report
        leaves its figure out)."""
        try:
            ny, nx = len(self.values), len(self.values[0]) if self.values else 0
            if ny != len(self.y) or nx != len(self.x) or any(len(r) != nx for r in self.values):
                return self
            x, y, values = downsample_max(self.x, self.y, self.values)
            return replace(self, x=round_list(list(x), COORD_DIGITS),
                           y=round_list(list(y), COORD_DIGITS), values=round_list(values))
        except (TypeError, ValueError, IndexError):
            return self


@dataclass
class ProofBoxes:
    """The prover's leaf sub-boxes projected onto two coordinates, with their status.

    One entry per distinct projected box, in drawing order (proved, then unknown, then
    violated on top); where several leaves project onto the same box, the worst status is
    kept. `leaf_counts`: how many leaves the prover kept, per status, before merging (empty
    in certificates written before it: then one per box).
    """

    lo: list[list[float]]
    hi: list[list[float]]
    status: list[str]  # "proved" | "violated" | "unknown", one per box
    axes: list[str] = field(default_factory=list)
    leaf_counts: dict[str, int] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        """Leaves per status (from `leaf_counts`, else one per box)."""
        return dict(self.leaf_counts) if self.leaf_counts else dict(Counter(self.status))

    def compact(self) -> ProofBoxes:
        """Projected onto the first two coordinates, coinciding boxes merged (worst status
        kept), sorted into drawing order; a malformed record is returned unchanged."""
        try:
            if not (len(self.lo) == len(self.hi) == len(self.status)):
                return self
            best: dict[tuple[float, ...], str] = {}
            for lo, hi, st in zip(self.lo, self.hi, self.status):
                key = (*map(float, lo[:2]), *map(float, hi[:2]))
                old = best.get(key)
                if old is None or STATUS_RANK.get(st, 1) > STATUS_RANK.get(old, 1):
                    best[key] = st
            order = sorted(best.items(), key=lambda kv: STATUS_RANK.get(kv[1], 1))
            return replace(self, lo=[list(k[:2]) for k, _ in order],
                           hi=[list(k[2:]) for k, _ in order], status=[s for _, s in order],
                           leaf_counts=self.counts())
        except (TypeError, ValueError):
            return self


@dataclass
class FigureData:
    """Every array a figure needs; a missing one (None, empty) means its figure is left out."""

    mpdi_map: GridMap | None = None
    necessary_map: GridMap | None = None
    residual_map: GridMap | None = None
    proof_boxes: ProofBoxes | None = None
    #: (prover seconds, proved volume fraction) samples
    proof_history: list[list[float]] = field(default_factory=list)

    def compact(self) -> FigureData:
        """The same figures at figure size (see the module's docstring); idempotent."""
        maps = {k: m.compact() for k in ("mpdi_map", "necessary_map", "residual_map")
                if isinstance(m := getattr(self, k), GridMap)}
        boxes = (self.proof_boxes.compact() if isinstance(self.proof_boxes, ProofBoxes)
                 else self.proof_boxes)
        return replace(self, **maps, proof_boxes=boxes)  # the history is short already

    @classmethod
    def coerce(cls, value: Any) -> FigureData:
        """A FigureData from itself, None, or its JSON/dict form (schema v1 to v3)."""
        if isinstance(value, FigureData):
            return value
        if not value:
            return cls()
        from certify.results import from_jsonable

        return from_jsonable(cls, {k: v for k, v in dict(value).items()
                                   if k in cls.__dataclass_fields__})
