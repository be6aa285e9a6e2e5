"""Tensors in transit to and from Dask workers: as numpy arrays of their own.

`to_wire(obj)` replaces every torch tensor in `obj` (also inside tuples, lists, dicts and
dataclasses such as `certify.bnb.BoxEval`) by a `WireArray` holding a contiguous numpy copy;
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


def to_wire(obj: Any) -> Any:
    """`obj` with every CPU/GPU torch tensor (also inside tuples, lists, dicts and
    dataclasses) replaced by a `WireArray`; `from_wire` undoes it exactly (dtype, values)."""
    import dataclasses

    import torch

    if isinstance(obj, torch.Tensor):
        return WireArray(obj.detach().cpu().numpy().copy())
    if type(obj) in (tuple, list):
        return type(obj)(to_wire(v) for v in obj)
    if isinstance(obj, dict):
        return {k: to_wire(v) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: to_wire(getattr(obj, f.name))
                                           for f in dataclasses.fields(obj) if f.init})
    return obj


def from_wire(obj: Any) -> Any:
    """Inverse of `to_wire`: `WireArray`s back to (CPU) torch tensors."""
    import dataclasses

    import torch

    if isinstance(obj, WireArray):
        return torch.from_numpy(obj.array)
    if type(obj) in (tuple, list):
        return type(obj)(from_wire(v) for v in obj)
    if isinstance(obj, dict):
        return {k: from_wire(v) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: from_wire(getattr(obj, f.name))
                                           for f in dataclasses.fields(obj) if f.init})
    return obj
