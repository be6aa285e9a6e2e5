"""What an importer hands back: the layers of a gain MLP, its activation, and where it came from.

Both readers (`onnx_model`, `torch_model`) end in an `ImportedModel`; building the
`GainNetwork`, checking it against the spec's n and p, and turning it into a `Problem` or a
`Checkpoint` happen here once. Every refusal is a `ModelImportError`: one line naming the file,
and where a graph node is at fault, the node (its name and operator); exit code 2 on the CLI.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.errors import CertifyError
from certify.model.network import GainNetwork

#: the key of an exported model's metadata that records the gain structure (ONNX
#: metadata_props; a TorchScript extra file) for p = 1, where the output width cannot tell
STRUCTURE_KEY = "certify.structure"

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
    from certify.model.activations import names

    return tuple(names())


def check_activation(name: str, where: str) -> str:
    """The registry's name for activation `name` ('Tanh' -> 'tanh', 'swish' -> 'silu'); non-C^1
    and unknown names are refused with `certify.model.activations`' reason, naming `where`."""
    from certify.model.activations import get

    try:
        return get(name).name
    except ValueError as exc:
        raise ModelImportError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Layer:
    """One affine layer: W [out, in] and b [out] (float64), and the node that holds it.

    `tensor` names the model's tensor that holds u = W h + b (where the model has one: the
    import check compares it to locate a mismatch); `fold`, on a first layer into which an
    input normalisation was folded, is (W, b, s, t) as the model computes W (s z + t) + b, in
    z's column order (the import check's rounding bound needs the model's own magnitudes).
    """

    W: np.ndarray
    b: np.ndarray
    where: str
    tensor: str | None = None
    fold: tuple[np.ndarray, ...] | None = None


@dataclass
class Reading:
    """What a reader found in a model file, before the spec's n and p are checked.

    `reference(activation)` gives the model's own evaluation (`certify.model.importers.crosscheck.
    Reference`) for the import check; `structure` is what the file's metadata records (or
    None); `activation_node` names where the graph's activation was found (None for a
    state_dict, which carries none).
    """

    layers: list[Layer]
    reference: Callable[[str], Any]
    activation: str | None = None
    activation_node: str | None = None
    structure: str | None = None
    notes: list[str] = field(default_factory=list)


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


def _structure(out: int, n: int, p: int, asked: str | None, recorded: str | None,
               path: str, where: str, can_record: bool) -> str:
    """The gain structure: asked for (--structure), else recorded in the file's metadata,
    else decided by the output width; with p = 1 (n = n*p) a model must say which."""
    if asked is not None and recorded is not None and asked != recorded:
        raise ModelImportError(f"{path}: --structure {asked} disagrees with the model's "
                               f"metadata ({STRUCTURE_KEY} = {recorded})")
    structure = asked or recorded
    wanted = {"direct": n, "structural": n * p}
    if structure is None:
        if out == n == n * p:
            raise ModelImportError(
                f"{path}: with one output (p = 1) the {out} values the model gives are either "
                f"the gain k itself (--structure direct) or G in k = G (y - h(xhat)) "
                f"(--structure structural); say which"
                + (f" (or record it at export: metadata {STRUCTURE_KEY})" if can_record else ""))
        structure = "direct" if out == n else "structural" if out == n * p else None
    if structure not in wanted or out != wanted[structure]:
        need = (f"{wanted.get(structure)} ({structure})" if structure is not None
                else f"n = {n}" if p == 1 else f"n = {n} (direct) or n*p = {n * p} (structural)")
        raise ModelImportError(f"{path}: {where}: the output has {out} values; the spec "
                               f"needs {need}")
    return structure


def finish(layers: list[Layer], activation: str | None, *, n: int, p: int,
           structure: str | None, source_format: str, path: str, sha256: str,
           notes: list[str] | None = None, recorded_structure: str | None = None
           ) -> ImportedModel:
    """Check a layer chain against the spec's n and p and decide the structure.

    The first layer must read n + p values; the last must give n (direct) or n*p (structural).
    `structure` (the user's) or else `recorded_structure` (the file's metadata) decides; without
    either, n outputs mean direct and n*p (p > 1) structural, and with p = 1, where both have n
    outputs, the model is refused with the two choices named (it is never guessed).
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
    structure = _structure(last.W.shape[0], n, p, structure, recorded_structure, path,
                           last.where, can_record=source_format != "state_dict")
    if len(layers) > 1 and activation is None:
        raise ModelImportError(f"{path}: no activation between the linear layers")
    activation = check_activation(activation or "tanh", path)
    return ImportedModel(layers=layers, activation=activation, structure=structure, n=n, p=p,
                         source_format=source_format, path=path, sha256=sha256,
                         notes=list(notes or []))


def recorded_structure(value: Any, path: str) -> str | None:
    """A structure recorded in a model's metadata, validated (None: none recorded)."""
    if value is None:
        return None
    text = value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
    text = text.strip()
    if text not in ("direct", "structural"):
        raise ModelImportError(f"{path}: the model's metadata {STRUCTURE_KEY} = {text[:40]!r}; "
                               "it must be 'direct' or 'structural'")
    return text
