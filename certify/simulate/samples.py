"""Which steps of a run the certificate keeps for the reports, and at what precision.

The check compares every step; the reports draw a run in a panel about 330 pixels wide, so
a run keeps at most `MAX_SAMPLES` steps, chosen so that nothing that matters is hidden
(`keep_samples`), stored at figure precision (`certify.figuredata`).
"""

from __future__ import annotations

import numpy as np

from certify.figuredata import FIGURE_DIGITS, round_list

#: Samples kept per run for reports (the check itself uses every step)
MAX_SAMPLES = 150
#: significant digits of the kept times (the series keep `FIGURE_DIGITS`)
TIME_DIGITS = 7


def keep_samples(error: np.ndarray, *, exit_index: int, worst_index: int | None = None,
                 limit: int = MAX_SAMPLES) -> np.ndarray:
    """The steps a run keeps for the reports: at most `limit` (>= 16) indices into error
    [T], increasing, no repeats.

    Always kept: the first and last step, the last step before the first exit and the exit
    itself, the worst step (`worst_index`: the largest error / bound, so a breach is always
    drawn where it happened), the largest and smallest error and the first non-finite one;
    then, in each of the equal buckets the remaining room allows, the bucket's smallest and
    largest error, so a spike between two kept steps is never hidden (the error is drawn on
    a log scale: its dips matter as much as its peaks).
    """
    T = len(error)
    if T <= limit:
        return np.arange(T)
    finite = np.isfinite(error)
    hi = np.where(finite, error, -np.inf)
    lo = np.where(finite, error, np.inf)
    special = {0, T - 1, int(np.argmax(hi)), int(np.argmin(lo))}
    if exit_index < T:
        special |= {max(exit_index - 1, 0), exit_index}
    if worst_index is not None and 0 <= worst_index < T:
        special.add(int(worst_index))
    if not finite.all():
        special.add(int(np.argmin(finite)))
    buckets = max((limit - len(special)) // 2, 1)
    edges = np.linspace(0, T, buckets + 1).round().astype(np.int64)
    picks = [int(np.argmax(hi[a:b])) + a for a, b in zip(edges[:-1], edges[1:]) if b > a]
    picks += [int(np.argmin(lo[a:b])) + a for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return np.sort(np.fromiter(special | set(picks), dtype=np.int64))


def series(values: np.ndarray, digits: int = FIGURE_DIGITS) -> list:
    """Kept samples as float lists at figure precision (`certify.figuredata.round_list`)."""
    return round_list(values.tolist(), digits)
