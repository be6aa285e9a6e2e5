"""What the report's figures draw, read from a certificate: typed figure data to arrays.

Every figure is optional: these readers return None when a check did not run, failed, or
its map is missing or malformed, and the figure is then left out (never drawn half-empty).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from certify.certificate import Certificate
from certify.figuredata import GridMap
from certify.results import CheckFailure


def as_array(values: Any) -> np.ndarray:
    """Typed figure data (float lists, NaN where undefined) to a float array."""
    return np.asarray(values, dtype=float)


def check_result(cert: Certificate, name: str) -> Any:
    """A check's own result, or None (not run, or a `CheckFailure`: nothing to draw)."""
    r = cert.checks.get(name)
    return None if r is None or isinstance(r, CheckFailure) else r


def grid_map(cert: Certificate, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 list[str]] | None:
    """(x [nx], y [ny], values [ny, nx], axis names) of a figure map, or None if unusable."""
    data: GridMap | None = getattr(cert.figures, key, None)
    if data is None:
        return None
    try:
        x, y, v = as_array(data.x), as_array(data.y), as_array(data.values)
    except (ValueError, TypeError):
        return None
    if v.ndim != 2 or v.shape != (len(y), len(x)) or v.size == 0:
        return None
    return x, y, v, list(data.axes or ["x1", "x2"])


def state_names(cert: Certificate) -> list[str]:
    """The system's state names (x1, x2 when the certificate has none)."""
    return list((cert.system or {}).get("states") or ["x1", "x2"])
