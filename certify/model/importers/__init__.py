"""Gain networks trained elsewhere: ONNX, TorchScript, or a state_dict of Linear layers.

`read_model(path, n, p, box=...)` recognises the file, reads its weights and graph (running
nothing from it: see `torch_model` for what TorchScript could run and how that is refused),
checks them against the spec's n and p, and then checks the network read against the model
itself (`crosscheck`: the model evaluated by its own runtime at points of the box, values and
Jacobians) before it returns an `ImportedModel`; refusals are `ModelImportError` (one line
naming the node; exit 2 on the CLI). `certify import` writes the model as a normal checkpoint;
`certify run MODEL --system SPEC` verifies it in memory (`certify.cli.importing`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from certify.model.importers.result import (
    ImportedModel,
    ModelImportError,
    check_activation,
    finish,
    supported_activations,
)

if TYPE_CHECKING:
    import numpy as np

__all__ = ["ImportedModel", "ModelImportError", "detect_format", "read_model"]

FORMATS = ("onnx", "torchscript", "state_dict")


def detect_format(path: Path) -> str:
    """'onnx', 'torchscript' or 'state_dict', from the file's first bytes (and .onnx)."""
    from certify.model.importers.torch_model import is_torchscript

    with open(path, "rb") as fh:
        head = fh.read(4)
    if head.startswith(b"PK"):
        return "torchscript" if is_torchscript(path) else "state_dict"
    if head.startswith(b"\x80"):
        return "state_dict"  # a pickle (torch's legacy format), read data-only
    return "onnx"  # protobuf has no magic number; the ONNX reader says if it is not one


def read_model(path: str | Path, n: int, p: int, *, activation: str | None = None,
               structure: str | None = None, box: np.ndarray | None = None) -> ImportedModel:
    """Read a model file as a gain network for a system with n states and p outputs.

    `activation` is required for a state_dict (it carries none); for ONNX and TorchScript it
    is optional and must agree with the graph. `structure` ("direct"/"structural") is needed
    only when the output width does not decide it (p = 1) and the file's metadata does not
    record it. `box` ([n+p, 2]: X then Y) is where the import check samples its points (and
    around it); None samples [-2, 2]^(n+p).
    """
    from certify.model.checkpoint import sha256_file
    from certify.model.importers.crosscheck import check_import

    path = Path(path)
    if not path.is_file():
        raise ModelImportError(f"model {path} not found" if not path.exists()
                               else f"model {path} is not a regular file")
    fmt = detect_format(path)
    if activation is not None:
        activation = check_activation(activation, f"{path}: --activation")
    if fmt == "state_dict":
        from certify.model.importers.torch_model import read_state_dict

        reading = read_state_dict(path)
        if activation is None and len(reading.layers) > 1:
            raise ModelImportError(f"{path}: a state_dict carries no activation; give "
                                   f"--activation NAME ({', '.join(supported_activations())})")
        found = activation
    else:
        if fmt == "onnx":
            from certify.model.importers.onnx_model import read_onnx as reader
        else:
            from certify.model.importers.torch_model import read_torchscript as reader
        reading = reader(path, n, p)
        found = reading.activation
        if activation is not None and found is not None and activation != found:
            raise ModelImportError(f"{path}: the model's graph uses {found} "
                                   f"({reading.activation_node}); --activation {activation} "
                                   "disagrees")
    model = finish(reading.layers, found, n=n, p=p, structure=structure, source_format=fmt,
                   path=str(path), sha256=sha256_file(path), notes=reading.notes,
                   recorded_structure=reading.structure)
    try:
        model.notes.append(check_import(model, reading.reference(model.activation), box))
    except ModelImportError as exc:
        text = str(exc)
        raise ModelImportError(text if text.startswith(str(path)) else f"{path}: {text}"
                               ) from None
    return model
