"""What an importer hands back: the layers of a gain MLP, its activation, and where it came from.

Both readers (`onnx_model`, `torch_model`) end in an `ImportedModel`; building the
`GainNetwork`, checking it against the spec's n and p, and turning it into a `Problem` or a
`Checkpoint` happen here once. Every refusal is a `ModelImportError`: one line naming the file,
and where a graph node is at fault, the node (its name and operator); exit code 2 on the CLI.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.errors import CertifyError
from certify.network import GainNetwork

NOT_C1 = ("D would be discontinuous; Theorem 1 needs a C^1 gain, so non-C^1 activations "
          "(ReLU, leaky ReLU, hardtanh, clamp, abs, ...) are refused")


class ModelImportError(CertifyError):
    """A model file that cannot be read as a certify gain network (one line, exit 2)."""


#: what reading a malformed node or tensor raises (a model file's fault, not certify's)
READ_ERRORS = (ValueError, TypeError, KeyError, IndexError, AttributeError, RuntimeError,
               OSError)


def first_line(exc: Exception) -> str:
    """': <the first line of the exception's message>' (cut at 120 characters), or ''."""
    text = str(exc).strip().splitlines()
    return f": {text[0][:120]}" if text else ""


def supported_activations() -> tuple[str, ...]:
    """The activations a `GainNetwork` (and so the verifier) evaluates."""
    from certify.activations import names

    return tuple(names())


def check_activation(name: str, where: str) -> str:
    """The registry's name for activation `name` ('Tanh' -> 'tanh', 'swish' -> 'silu'); non-C^1
    and unknown names are refused with `certify.activations`' reason, naming `where`."""
    from certify.activations import get

    try:
        return get(name).name
    except ValueError as exc:
        raise ModelImportError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Layer:
    """One affine layer: W [out, in] and b [out] (float64), and the node that holds it."""

    W: np.ndarray
    b: np.ndarray
    where: str


@dataclass
class ImportedModel:
    """A gain MLP read from a file: z = concat(xhat, y) -> Linear (-> activation -> Linear)*."""

    layers: list[Layer]
    activation: str
    structure: str
    n: int
    p: int
    source_format: str  # "onnx", "torchscript" or "state_dict"
    path: str
    sha256: str
    notes: list[str] = field(default_factory=list)

    @property
    def hidden(self) -> list[int]:
        return [layer.W.shape[0] for layer in self.layers[:-1]]

    def network(self) -> GainNetwork:
        """The `GainNetwork` (float64, K = 0) with exactly these weights."""
        net = GainNetwork(self.n, self.p, self.hidden, structure=self.structure,
                          activation=self.activation).double()
        with torch.no_grad():
            for module, layer in zip(net.layers, self.layers):
                module.weight.copy_(torch.from_numpy(layer.W))
                module.bias.copy_(torch.from_numpy(layer.b))
        return net.requires_grad_(False)

    def provenance(self) -> dict[str, Any]:
        """Plain data recorded in checkpoints and certificates: what was imported, from where."""
        return {"imported_from": {"path": self.path, "format": self.source_format,
                                  "sha256": self.sha256, "activation": self.activation,
                                  "structure": self.structure, "hidden": self.hidden,
                                  "notes": list(self.notes)}}


def finish(layers: list[Layer], activation: str | None, *, n: int, p: int,
           structure: str | None, source_format: str, path: str, sha256: str,
           notes: list[str] | None = None) -> ImportedModel:
    """Check a layer chain against the spec's n and p and decide the structure.

    The first layer must read n + p values; the last must give n (direct) or n*p (structural).
    Without `structure`, n outputs mean direct and n*p (p > 1) structural; with p = 1 both have
    n outputs and direct is taken unless `structure="structural"` is asked for.
    """
    if not layers:
        raise ModelImportError(f"{path}: no linear layer found between the input and output")
    for before, layer in zip(layers, layers[1:]):
        if layer.W.shape[1] != before.W.shape[0]:
            raise ModelImportError(f"{path}: {layer.where}: reads {layer.W.shape[1]} values but "
                                   f"{before.where} gives {before.W.shape[0]}")
    first, last = layers[0], layers[-1]
    if first.W.shape[1] != n + p:
        raise ModelImportError(f"{path}: {first.where}: the first layer reads "
                               f"{first.W.shape[1]} values; the spec needs n+p = {n + p} "
                               f"(xhat: {n}, y: {p})")
    out = last.W.shape[0]
    wanted = {"direct": n, "structural": n * p}
    if structure is None:
        structure = "direct" if out == n else "structural" if out == n * p else None
    if structure not in wanted or out != wanted[structure]:
        need = (f"{wanted.get(structure)} ({structure})" if structure is not None
                else f"n = {n}" if p == 1 else f"n = {n} (direct) or n*p = {n * p} (structural)")
        raise ModelImportError(f"{path}: {last.where}: the output has {out} values; the spec "
                               f"needs {need}")
    if len(layers) > 1 and activation is None:
        raise ModelImportError(f"{path}: no activation between the linear layers")
    activation = check_activation(activation or "tanh", path)
    return ImportedModel(layers=layers, activation=activation, structure=structure, n=n, p=p,
                         source_format=source_format, path=path, sha256=sha256,
                         notes=list(notes or []))
