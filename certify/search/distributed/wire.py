"""Tensors in transit to and from Dask workers: as numpy arrays of their own.

`to_wire(obj)` replaces every torch tensor in `obj` (also inside tuples, lists, dicts and
dataclasses such as `certify.search.evaluation.BoxEval`) by a `WireArray` holding a contiguous
numpy copy;
`from_wire` undoes it exactly (dtype, values). A chunk of a round's boxes is a slice, and
pickling a torch slice writes the whole storage it views; numpy arrays also travel as Dask's
out-of-band buffers, without a copy.
"""

from __future__ import annotations

from typing import Any


class WireArray:
    """A torch tensor in transit: its values as a contiguous numpy array of its own.

    Pickling a torch tensor that is a slice (a chunk of a round's boxes) writes the whole
    storage it views, so W chunks would carry W copies of the round; torch's own pickling is
    also slower than numpy's, which Dask sends as out-of-band buffers without copying."""

    __slots__ = ("array",)

    def __init__(self, array: Any) -> None:
        self.array = array

    def __reduce__(self) -> tuple:
        return (WireArray, (self.array,))


def _map_leaves(obj: Any, leaf: Any) -> Any:
    """`obj` with `leaf(v)` applied to every value inside tuples, lists, dicts and dataclass
    fields (the containers rebuilt as they were); `leaf` returns its argument to keep it."""
    import dataclasses

    if type(obj) in (tuple, list):
        return type(obj)(_map_leaves(v, leaf) for v in obj)
    if isinstance(obj, dict):
        return {k: _map_leaves(v, leaf) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: _map_leaves(getattr(obj, f.name), leaf)
                                           for f in dataclasses.fields(obj) if f.init})
    return leaf(obj)


def to_wire(obj: Any) -> Any:
    """`obj` with every CPU/GPU torch tensor (also inside tuples, lists, dicts and
    dataclasses) replaced by a `WireArray`; `from_wire` undoes it exactly (dtype, values)."""
    import torch

    return _map_leaves(obj, lambda v: WireArray(v.detach().cpu().numpy().copy())
                       if isinstance(v, torch.Tensor) else v)


def from_wire(obj: Any) -> Any:
    """Inverse of `to_wire`: `WireArray`s back to (CPU) torch tensors."""
    import torch

    return _map_leaves(obj, lambda v: torch.from_numpy(v.array)
                       if isinstance(v, WireArray) else v)
