"""Typed arrays behind the report's figures, carried by the Certificate.

Plain float lists (NaN where a value is undefined, e.g. where h(x) leaves Y), so that the
JSON form round-trips through `certify.results.to_jsonable` / `from_jsonable`, which is the
one place where JSON's "NaN"/"Infinity" spellings are turned back into floats. Renderers
read these dataclasses and never decode strings. Computed by `certify.verify.report_maps`
(maps) and the MPDI check (the prover's leaf boxes and its proved volume over time).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class GridMap:
    """A quantity on a grid over the first two state coordinates: values[j][i] at (x[i], y[j])."""

    x: list[float]
    y: list[float]
    values: list[list[float]]
    axes: list[str] = field(default_factory=list)


@dataclass
class ProofBoxes:
    """The prover's leaf sub-boxes projected onto two coordinates, with their status."""

    lo: list[list[float]]
    hi: list[list[float]]
    status: list[str]  # "proved" | "violated" | "unknown", one per box
    axes: list[str] = field(default_factory=list)


@dataclass
class FigureData:
    """Every array a figure needs; a missing one (None, empty) means its figure is left out."""

    mpdi_map: GridMap | None = None
    necessary_map: GridMap | None = None
    residual_map: GridMap | None = None
    proof_boxes: ProofBoxes | None = None
    #: (prover seconds, proved volume fraction) samples
    proof_history: list[list[float]] = field(default_factory=list)

    @classmethod
    def coerce(cls, value: Any) -> FigureData:
        """A FigureData from itself, None, or its JSON/dict form (schema v1 and v2)."""
        if isinstance(value, FigureData):
            return value
        if not value:
            return cls()
        from certify.results import from_jsonable

        return from_jsonable(cls, {k: v for k, v in dict(value).items()
                                   if k in cls.__dataclass_fields__})
