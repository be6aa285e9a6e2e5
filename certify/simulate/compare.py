"""One run's error against the proved bounds, inside its valid window.

The bounds' formulas come from the check (`BoundFormulas`, implemented over
`certify.checks.bounds`), so that this layer reads only the result types. Two comparisons:

- the whole valid window [0, first exit): ||e(t)|| must stay under the pointwise minimum of
  every applicable proved bound's curve from the run's own start (`best_curve`);
- after the headline's settling time T: the peak of ||e|| must stay under the headline B
  and each |e_i| under its per-component bound (`peak_after_settling`): the claim
  "||e|| <= B after t >= T" that users read.

Both allow for the integrator: an excess is a breach only beyond the run's tolerance, the
estimated integration error (the run integrated again at twice the step, whose difference
from the dt run is about 15x the dt run's own error with RK4) plus `ATOL` (1 + the largest
bound). An excess within it (float noise against a bound of 1e-160, say) is never called a
breach; the message says that the run reached the bound within the tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from certify.results import BoundsResult

#: Absolute part of the comparison tolerance (on top of the estimated integration error).
ATOL = 1e-9


class BoundFormulas(Protocol):
    """The proved bounds' curves (`certify.checks.bounds`, given by the check).

    `names`: every bound name, in the order they are tried; `start(which, e0)`: the start
    value the bound multiplies, e0 [n] or [R, n] -> scalar or [R]; `curve(which, start, t)`:
    the bound on ||e(t)|| over t [T] -> [T] or [R, T]; `settle(which, start, level)`: the
    first time after which the curve stays <= level (inf: never)."""

    names: tuple[str, ...]

    def start(self, which: str, e0: np.ndarray) -> np.ndarray: ...

    def curve(self, which: str, start: float | np.ndarray, t: np.ndarray) -> np.ndarray: ...

    def settle(self, which: str, start: float, level: float) -> float: ...


def applicable(bounds: BoundsResult | None, formulas: BoundFormulas) -> list[str]:
    """The names of the applicable proved bounds (none: nothing to compare a run with)."""
    if bounds is None:
        return []
    return [which for which in formulas.names
            if (b := getattr(bounds, which)) is not None and b.applicable]


def best_curve(bounds: BoundsResult | None, formulas: BoundFormulas, e0: np.ndarray,
               t: np.ndarray) -> np.ndarray | None:
    """Pointwise minimum over every applicable proved bound -> [R, T] (None if none), for
    the runs' initial errors e0 [R, n] over times t [T]."""
    curves = [formulas.curve(which, formulas.start(which, e0), t)
              for which in applicable(bounds, formulas)]
    return np.minimum.reduce(curves) if curves else None


def component_bounds(bounds: BoundsResult | None) -> np.ndarray | None:
    """The headline's bounds on |e_i| after the settling time: per_component[i] * headline /
    ultimate (`BoundsResult.per_component`), None when there are none."""
    if (bounds is None or bounds.per_component is None or bounds.ultimate is None
            or bounds.headline is None):
        return None
    pc = np.asarray(bounds.per_component, dtype=np.float64)
    if bounds.ultimate > 0:
        return pc * (float(bounds.headline) / float(bounds.ultimate)) * (1.0 + 1e-12)
    return pc


@dataclass
class Peak:
    """A run's observed peak after its own settling time (see `peak_after_settling`)."""

    settle: float | None = None
    error: float | None = None
    time: float | None = None
    components: list[float] = field(default_factory=list)
    bound_at: float | None = None
    conservatism: float | None = None
    breach: str = ""


@dataclass
class Comparison:
    """A run against the bounds over its valid window.

    `max_ratio`: the largest ||e|| / (bound + tol) (> 1: a breach; None: not compared);
    `worst`: the step where it is reached; `late_ratio`: the same over t >= one time
    constant; `compared`: the window holds more than the start; `breaches`: in words."""

    max_ratio: float | None = None
    tol: float = 0.0
    worst: int | None = None
    late_ratio: float | None = None
    compared: bool = False
    peak: Peak = field(default_factory=Peak)
    breaches: list[str] = field(default_factory=list)

    @property
    def breach(self) -> bool:
        return bool(self.breaches)


@dataclass
class PeakTest:
    """The claim after settling for one run: the best bound `which` from the run's start
    e0 [n], the headline B and the per-component bounds `comp` [n] (or None)."""

    bounds: BoundsResult
    formulas: BoundFormulas
    which: str
    e0: np.ndarray
    headline: float
    comp: np.ndarray | None

    def run(self, t: np.ndarray, e: np.ndarray, k_exit: int, tol: float) -> Peak:
        """The peak of ||e|| (and of each |e_i|) over [settle, first exit), e [T, n].

        settle: the headline's settling time T (`BoundsResult.settle_time`: the worst start
        in X is within the headline value by then; the run's own curve of the best bound
        gets there no later), or that own time when T is not recorded. After it the
        certificate says ||e|| <= B and |e_i| <= comp[i], so that is what is tested; the
        transient of the start is mostly over by then, and the peak is what the noise holds
        the error at. conservatism = B / peak. A peak above B (or a component above its
        bound) by more than `tol` is a breach, in words.
        """
        start = float(self.formulas.start(self.which, self.e0))
        own = self.formulas.settle(self.which, start, self.headline)
        T = self.bounds.settle_time
        settle = own if T is None else max(own, float(T))
        out = Peak(settle=settle)
        if not math.isfinite(settle):
            return out
        k0 = int(np.searchsorted(t, settle, side="left"))
        if k0 >= k_exit:
            return out
        seg = e[k0:k_exit]
        norms = np.linalg.norm(seg, axis=-1)
        j = int(np.argmax(np.where(np.isnan(norms), np.inf, norms)))
        out.error = float(norms[j])
        out.time = float(t[k0 + j])
        out.components = np.max(np.abs(seg), axis=0).tolist()
        out.bound_at = float(self.formulas.curve(self.which, start, np.array([out.time]))[0])
        out.conservatism = self.headline / out.error if out.error > 0 else math.inf
        B, comp = self.headline, self.comp
        if not out.error <= B + tol:
            out.breach = (f"after the settling time {settle:.4g} s, ||e|| = {out.error:.6g} "
                          f"at t = {out.time:.4g} > the headline bound {B:.6g} + tolerance "
                          f"{tol:.2g}")
        elif comp is not None:
            over = [i for i in range(len(comp)) if not out.components[i] <= comp[i] + tol]
            if over:
                i = over[0]
                out.breach = (f"after the settling time {settle:.4g} s, |e_{i + 1}| reached "
                              f"{out.components[i]:.6g} > its bound {comp[i]:.6g} + "
                              f"tolerance {tol:.2g}")
        return out


def compare_run(label: str, t: np.ndarray, e: np.ndarray, k_exit: int, curve: np.ndarray,
                doubling: np.ndarray, *, tau: float | None, peak: PeakTest | None
                ) -> Comparison:
    """One run: e [T, n] over t [T], valid on [0, k_exit), its bound curve [T] and the
    difference from its 2 dt integration at the even steps `doubling` [>= k_exit / 2]."""
    out = Comparison()
    if k_exit <= 0:
        return out
    norms = np.linalg.norm(e, axis=-1)
    w = slice(0, k_exit)
    b = curve[w]
    d = doubling[: (k_exit + 1) // 2]
    est = float(np.max(d)) if d.size and np.all(np.isfinite(d)) else math.inf
    out.tol = tol = ATOL * (1.0 + float(np.max(b))) + est
    ratio = norms[w] / (b + tol)
    out.max_ratio = float(np.max(ratio))
    with np.errstate(invalid="ignore"):
        j = out.worst = int(np.argmax(np.where(np.isnan(ratio), np.inf, ratio)))
    out.compared = k_exit > 1
    if tau is not None:
        late = t[w] >= tau
        if late.any():
            out.late_ratio = float(np.max(ratio[late]))
    if out.max_ratio > 1.0 or not math.isfinite(out.max_ratio):
        out.breaches.append(f"run '{label}' at t = {t[j]:.4g}: ||e|| = {norms[j]:.6g} > "
                            f"bound {b[j]:.6g} + tolerance {tol:.2g}")
    if peak is not None:
        out.peak = peak.run(t, e, k_exit, tol)
        if out.peak.breach:
            out.breaches.append(f"run '{label}': {out.peak.breach}")
    return out
