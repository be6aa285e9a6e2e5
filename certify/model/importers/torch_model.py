"""Read a PyTorch gain network: a TorchScript file, or a state_dict of Linear layers.

TorchScript: first the archive is inspected without loading it. `torch.jit.load` runs one kind
of code from the file, a class's `__setstate__` (called while unpickling its objects), so an
archive whose code, data.pkl or constants.pkl mention `__setstate__` or `__getstate__` is
refused, as are forward hooks (`module(x)` runs them, not `forward`) and archives that hold two
members of one name (which the C++ reader and Python's zipfile could resolve differently).
Then `torch.jit.load` (which, with no `__setstate__`, only compiles the code and unpickles data)
and the module's *inlined* forward graph is walked node by node (the same `ChainBuilder` as
ONNX): `aten::linear` with the module's own parameters (a model input or computed value as its
bias is a skip connection, refused), or `aten::matmul` by a parameter matrix (through `W.t()`,
`W.T`, `transpose`, `permute`) plus `aten::add` of a bias; the activations `aten::tanh`,
`sigmoid`, `softplus` (beta = 1), `elu` (alpha = scale = 1), `gelu` (approximate = "none"),
`silu`, `mul`(u, sigmoid(u)); `aten::cat` of two inputs, in either order; reshape/flatten/dropout
(eval mode) no-ops; and a `prim::If` on a constant (the `inplace` flag of torch.nn.functional)
through the branch it takes. Class names are not trusted (a TorchScript file carries its own
code); only the graph's operators decide. Anything else (prints, loops, raises, any other
operator) is refused with one line naming the node (%value and operator). Only a forward that
passed this walk is ever run, by the import check (`certify.model.importers.crosscheck`), which
evaluates `module.forward` with torch at sample points, values and Jacobians (autograd).
The gain structure for p = 1 may be recorded as the extra file `certify.structure`
(`torch.jit.save(m, path, _extra_files={"certify.structure": "structural"})`).

state_dict: `torch.load(weights_only=True)` (data only, never code) of an `nn.Sequential` of
Linear layers: keys `[prefix.]i.weight` / `[prefix.]i.bias`. It records the Linear layers only;
where the activations sit is read from the gaps in the module indices: `0, 2, 4, ...` is
Sequential(Linear, act, Linear, act, ..., Linear), the one module between two Linear layers being
the activation the caller names (`--activation`; a state_dict carries none). Adjacent indices
(a Linear directly followed by a Linear: no activation between them), a gap of two or more
modules (which of them are activations, a state_dict does not say) and a first Linear that is
not module 0 are refused, saying so; modules after the last Linear cannot be seen at all (a note
says the reading assumes none). The import check evaluates the same nn.Sequential built by torch
from the keys.
"""

from __future__ import annotations

import pickle
import re
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from certify.model.checkpoint import ZIP_ERRORS
from certify.model.importers.chain import ChainBuilder, Const, Node
from certify.model.importers.crosscheck import Deviation
from certify.model.importers.result import (
    READ_ERRORS,
    STRUCTURE_KEY,
    Layer,
    ModelImportError,
    Reading,
    first_line,
    recorded_structure,
)

_UNARY = {"aten::tanh": "tanh", "aten::sigmoid": "sigmoid", "aten::silu": "silu",
          "aten::erf": "erf"}
_BINARY = {"aten::mul": "mul", "aten::div": "div"}
NON_C1_OPS = {"aten::relu": "ReLU", "aten::relu6": "ReLU6", "aten::leaky_relu": "leaky ReLU",
              "aten::prelu": "PReLU", "aten::hardtanh": "hardtanh", "aten::hardsigmoid":
              "hard sigmoid", "aten::hardswish": "hard swish", "aten::selu": "SELU",
              "aten::abs": "abs", "aten::clamp": "clamp", "aten::threshold": "threshold",
              "aten::celu": "CELU", "aten::rrelu": "RReLU"}


def is_torchscript(path: Path) -> bool:
    """A ZIP archive with the code/ folder and constants.pkl that TorchScript writes."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except ZIP_ERRORS:
        return False
    return any(n.endswith("/constants.pkl") for n in names) and any("/code/" in n for n in names)


# ----- TorchScript ----------------------------------------------------------------------------
#: what makes torch.jit.load run code from the file (any mention refuses the file)
_RUNS_ON_LOAD = re.compile(rb"__setstate__|__getstate__")
#: a class with forward hooks or pre-hooks (a non-empty list)
_HOOKS = re.compile(rb"__forward_(?:pre_)?hooks__\s*=\s*\[\s*[^\]\s]")
_EXTRA_LIMIT = 1 << 16


def inspect_archive(path: str | Path) -> dict[str, bytes]:
    """Refuse a TorchScript archive that would run code when loaded (see the module
    docstring), without loading it; returns its small extra files by name (metadata)."""
    extra: dict[str, bytes] = {}
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            names = [info.filename for info in infos]
            if len(set(names)) != len(names):
                twice = sorted({nm for nm in names if names.count(nm) > 1})[0]
                raise ModelImportError(f"{path}: the archive holds two members named '{twice}' "
                                       "(not something torch.jit.save writes); refused")
            for info in infos:
                name = info.filename
                parts = name.split("/")
                if len(parts) >= 3 and parts[-2] == "extra" and info.file_size <= _EXTRA_LIMIT:
                    extra[parts[-1]] = archive.read(info)
                if not name.endswith((".py", ".pkl")) or name.endswith(".debug_pkl"):
                    continue  # tensor storages, debug source ranges: never compiled or run
                text = archive.read(info)
                if _RUNS_ON_LOAD.search(text):
                    what = ("defines __setstate__, which torch.jit.load runs when the file is "
                            "opened" if b"__setstate__" in text else "defines __getstate__ (custom "
                            "serialisation, restored by code when the file is opened)")
                    raise ModelImportError(
                        f"{path}: its TorchScript ({name}) {what}: a model file that runs code "
                        "is refused (save the module without __getstate__/__setstate__, or "
                        "export ONNX)")
                if name.endswith(".py") and _HOOKS.search(text):
                    raise ModelImportError(
                        f"{path}: a module in it ({name}) has forward hooks, which run outside "
                        "its forward graph: not supported (remove the hooks before scripting)")
    except (*ZIP_ERRORS, zlib.error) as exc:  # zlib: a compressed member with flipped bytes
        raise ModelImportError(f"{path}: damaged TorchScript archive ({type(exc).__name__}"
                               f"{first_line(exc)})") from None
    return extra


class _TorchBuilder(ChainBuilder):
    """A `ChainBuilder` that also records what the import check needs from a TorchScript
    graph: the floating dtypes of the tensors read and softplus's threshold."""

    def __init__(self, path: str, n: int, p: int) -> None:
        super().__init__(path, n, p)
        self.dtypes: list[torch.dtype] = []
        self.softplus_threshold: float | None = None


def read_torchscript(path: str | Path, n: int, p: int) -> Reading:
    """Inspect the archive, load it, walk its inlined forward graph into a `ChainBuilder`
    (see the module docstring); the reading's reference runs `module.forward` with torch."""
    extra = inspect_archive(path)
    try:
        module = torch.jit.load(str(path), map_location="cpu")
    except Exception as exc:  # torch raises RuntimeError and friends for damaged archives
        raise ModelImportError(f"{path}: TorchScript cannot load it ({type(exc).__name__})"
                               ) from None
    hooks = [getattr(module._c, f"_get_forward{kind}_hooks", lambda: [])()
             for kind in ("", "_pre")]
    if any(hooks):
        raise ModelImportError(f"{path}: the module has forward hooks, which run outside its "
                               "forward graph: not supported (remove them before scripting)")
    graph = module.inlined_graph
    b = _TorchBuilder(str(path), n, p)
    objects: dict[str, Any] = {}
    params = list(graph.inputs())
    objects[params[0].debugName()] = module
    data = params[1:]
    if len(data) not in (1, 2):
        raise ModelImportError(f"{path}: forward takes {len(data)} inputs; certify reads one "
                               "vector (xhat, y) or two inputs xhat and y")
    b.input_names([value.debugName() for value in data])
    for index, value in enumerate(data):
        if len(data) == 1:
            b.input_vector(value.debugName(), None, f"input '{value.debugName()}'")
        else:
            b.input_part(value.debugName(), index, None)
    last = _walk(b, graph.nodes(), objects, str(path)) or Node("output", "return")
    outs = list(graph.outputs())
    if len(outs) != 1:
        raise ModelImportError(f"{path}: forward returns {len(outs)} values; certify reads one")
    layers = b.output(b.get(outs[0].debugName(), last), last)
    t = b.softplus_threshold
    deviation = Deviation(value=0.0 if t is None else float(np.log1p(np.exp(-t))),
                          slope=0.0 if t is None else float(1 / (1 + np.exp(t))),
                          relative=4 * b.constant_deviation)
    dtypes = b.dtypes or [torch.float64]

    def reference(activation: str) -> TorchReference:
        return TorchReference(module.forward, len(data), n, dtypes, deviation,
                              "torch, the TorchScript forward",
                              lambda z, names: _graph_tensors(module, graph, z, names,
                                                              len(data), n, dtypes[0]))

    return Reading(layers, reference, b.activation,
                   str(b.activation_node) if b.activation_node else None,
                   recorded_structure(extra.get(STRUCTURE_KEY), str(path)), b.notes)


_NUMPY = {torch.float64: np.float64, torch.float32: np.float32, torch.float16: np.float16}


class TorchReference:
    """A torch model evaluated by torch: values, Jacobians by autograd (one backward pass per
    output), intermediate tensors where `tensors` is given. The input is fed in the dtype of
    the model's first floating tensor; `dtype` (the precision judged) is the least precise of
    its tensors."""

    def __init__(self, forward: Any, inputs: int, n: int, dtypes: list[torch.dtype],
                 deviation: Deviation, what: str, tensors: Any = None) -> None:
        unknown = sorted({str(d) for d in dtypes if d not in _NUMPY})
        if unknown:
            raise ModelImportError(f"its weights are {unknown[0]}: certify checks float16, "
                                   "float32 and float64 models (convert it before exporting)")
        self.forward, self.inputs, self.n = forward, inputs, n
        self.input_dtype = dtypes[0]
        self.dtype = np.dtype(max((_NUMPY[d] for d in dtypes), key=lambda t: np.finfo(t).eps))
        self.deviation, self.what, self._tensors = deviation, what, tensors

    def _split(self, z: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return (z,) if self.inputs == 1 else (z[:, :self.n], z[:, self.n:])

    def values(self, z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = self.forward(*self._split(torch.as_tensor(z, dtype=self.input_dtype)))
        return out.detach().reshape(len(z), -1).to(torch.float64).numpy()

    def jacobians(self, z: np.ndarray) -> np.ndarray:
        zt = torch.tensor(z, dtype=self.input_dtype, requires_grad=True)
        with torch.enable_grad():
            out = self.forward(*self._split(zt)).reshape(len(z), -1)
            rows = [torch.autograd.grad(out[:, i].sum(), zt, retain_graph=True,
                                        allow_unused=True)[0] for i in range(out.shape[1])]
        rows = [torch.zeros_like(zt) if r is None else r for r in rows]
        return torch.stack(rows, dim=1).detach().to(torch.float64).numpy()

    def tensors(self, z: np.ndarray, names: list[str]) -> dict[str, np.ndarray] | None:
        return None if self._tensors is None else self._tensors(z, names)


def _graph_tensors(module: Any, read: Any, z: np.ndarray, names: list[str], inputs: int,
                   n: int, dtype: torch.dtype) -> dict[str, np.ndarray] | None:
    """The values `names` of the inlined forward graph `read` (the one walked: each call of
    `inlined_graph` numbers its values anew) at z, a diagnosis of a failed import check: that
    graph, already accepted, with those values as its outputs."""
    graph = read.copy()  # a copy numbers its unnamed values anew: match them by position
    found = {}
    for node, twin in zip(read.nodes(), graph.nodes()):
        for out, copied in zip(node.outputs(), twin.outputs()):
            if out.debugName() in names:
                found[out.debugName()] = copied
    if set(found) != set(names):
        return None
    wanted = [found[name] for name in names]
    node = graph.create("prim::TupleConstruct", wanted, 1)
    node.insertBefore(graph.return_node())
    node.output().setType(torch._C.TupleType([v.type() for v in wanted]))
    graph.eraseOutput(0)
    graph.registerOutput(node.output())
    function = torch._C._create_function_from_graph("certify_tensors", graph)
    x = torch.as_tensor(z, dtype=dtype)
    with torch.no_grad():
        values = function(module._c, *((x,) if inputs == 1 else (x[:, :n], x[:, n:])))
    return {name: v.detach().reshape(len(z), -1).to(torch.float64).numpy()
            for name, v in zip(names, values)}


def _walk(b: ChainBuilder, nodes: Any, objects: dict[str, Any], path: str) -> Node | None:
    """Read `nodes` in order into `b`; returns the last node. A `prim::If` on a constant (the
    `inplace` flags of torch.nn.functional) is read through the branch it takes."""
    last = None
    for node in nodes:
        outs = list(node.outputs())
        last = Node(f"%{outs[0].debugName()}" if outs else node.kind(), node.kind())
        if node.kind() == "prim::If":
            cond = b.get(next(node.inputs()).debugName(), last)
            if not isinstance(cond, Const) or not isinstance(cond.value, bool):
                b.fail(last, "a branch on a value computed at run time is not supported")
            block = list(node.blocks())[0 if cond.value else 1]
            _walk(b, block.nodes(), objects, path)
            for out, value in zip(outs, block.outputs()):
                b.set(out.debugName(), b.get(value.debugName(), last))
            continue
        try:
            result = _apply(b, node, last, objects, path)
        except READ_ERRORS as exc:  # an attribute or constant that cannot be read
            b.fail(last, f"cannot be read ({type(exc).__name__}{first_line(exc)})")
        for out in outs[:1]:
            b.set(out.debugName(), result)
    return last


def _constant(b: ChainBuilder, args: list[Any], i: int, where: Node) -> Any:
    value = args[i] if i < len(args) else None
    if not isinstance(value, Const):
        b.fail(where, f"argument {i} must be a constant")
    return value.value


def _apply(b: ChainBuilder, node: Any, where: Node, objects: dict[str, Any], path: str) -> Any:
    kind = node.kind()
    ins = [v.debugName() for v in node.inputs()]
    if kind == "prim::Constant":
        return Const(node.output().toIValue(), where.name)
    if kind == "prim::GetAttr":
        owner = objects.get(ins[0])
        if owner is None:
            b.fail(where, "reads an attribute of something that is not a module")
        name = node.s("name")
        value = getattr(owner, name)
        if isinstance(value, torch.Tensor):
            if value.is_floating_point() and isinstance(b, _TorchBuilder):
                b.dtypes.append(value.dtype)
            return Const(value.detach().to(torch.float64).cpu().numpy(),
                         f"{where.name[1:]} ({name})")
        if isinstance(value, torch.nn.Module):
            objects[node.output().debugName()] = value
            return None
        return Const(value, name)
    if kind in NON_C1_OPS:
        b.non_c1(where, NON_C1_OPS[kind])
    if kind == "prim::ListConstruct":
        return [b.get(name, where) for name in ins]
    args = [b.get(name, where) for name in ins]
    if kind == "aten::linear":
        return b.linear(where, args[0], args[1], args[2] if len(args) > 2 else None)
    if kind in ("aten::t", "aten::numpy_T", "aten::transpose", "aten::permute"):
        return _transposed(b, kind, args, where)
    if kind == "aten::matmul":  # h @ W.T written by hand: the weight is the second operand
        W = b.constant(args[1], where, "second operand (the weight)")
        return b.linear(where, args[0], Const(np.asarray(W.value, dtype=np.float64).T, W.name),
                        None)
    if kind in _UNARY:
        return b.unary(where, _UNARY[kind], args[0])
    if kind in _BINARY:
        return b.binary(where, _BINARY[kind], args[0], args[1])
    if kind in ("aten::add", "aten::sub"):
        if len(args) > 2 and _constant(b, args, 2, where) != 1:
            b.fail(where, "add/sub with alpha != 1 is not supported")
        if kind == "aten::add":
            return b.add(where, args[0], args[1])
        return b.binary(where, "sub", args[0], args[1])
    if kind == "aten::softplus":
        beta, threshold = _constant(b, args, 1, where), _constant(b, args, 2, where)
        if beta != 1:
            b.fail(where, f"softplus with beta = {beta}: only beta = 1 is supported")
        if isinstance(b, _TorchBuilder):
            b.softplus_threshold = min(float(threshold), b.softplus_threshold or np.inf)
        b.notes.append(f"softplus read as log(1 + exp(u)); torch returns u above u = "
                       f"{threshold:g} (a difference below {np.exp(-threshold):.1e})")
        return b.unary(where, "softplus", args[0])
    if kind == "aten::elu":
        consts = [_constant(b, args, i, where) for i in (1, 2, 3)]
        if consts != [1, 1, 1]:
            b.fail(where, f"ELU with (alpha, scale, input_scale) = {tuple(consts)}: only "
                          "(1, 1, 1) is supported (C^1)")
        return b.unary(where, "elu", args[0])
    if kind == "aten::gelu":
        approx = _constant(b, args, 1, where)
        if approx != "none":
            b.fail(where, f"GELU with approximate = '{approx}' is not supported; use the "
                          "exact (erf) GELU")
        return b.unary(where, "gelu", args[0])
    if kind == "aten::dropout":
        if _constant(b, args, 2, where) is not False:
            b.fail(where, "dropout in training mode is not a no-op; save the module after "
                          ".eval()")
        return args[0]
    if kind in ("aten::reshape", "aten::view"):
        shape = args[1] if isinstance(args[1], list) else [args[1]]
        if not all(isinstance(v, Const) for v in shape):
            b.fail(where, "reshape to a shape that is not constant")
        return b.reshape(where, args[0], [int(v.value) for v in shape])
    if kind == "aten::flatten":
        start, end = _constant(b, args, 1, where), _constant(b, args, 2, where)
        if (start, end) != (1, -1):
            b.fail(where, f"flatten({start}, {end}): only flatten(1, -1) is a no-op here")
        return b.flatten(where, args[0], 1)
    if kind == "aten::cat":
        parts = args[0] if isinstance(args[0], list) else [args[0]]
        return b.concat(where, parts, int(_constant(b, args, 1, where)))
    b.fail(where, "unsupported operation; certify reads Linear layers and the activations "
                  "tanh, sigmoid, softplus, elu, gelu, silu")


def _transposed(b: ChainBuilder, kind: str, args: list[Any], where: Node) -> Const:
    """W.t(), W.T, W.transpose(0, 1), W.permute(1, 0) of a weight matrix (a constant)."""
    W = b.constant(args[0], where, "operand (a weight matrix)")
    value = np.asarray(W.value)
    if value.ndim != 2:
        b.fail(where, f"transposes a tensor of shape {list(value.shape)}; only matrices")
    if kind == "aten::transpose":
        dims = sorted(int(_constant(b, args, i, where)) % 2 for i in (1, 2))
        if dims != [0, 1]:
            b.fail(where, "transpose that is not of the two matrix axes")
    if kind == "aten::permute":
        perm = args[1] if isinstance(args[1], list) else []
        if [int(v.value) % 2 for v in perm if isinstance(v, Const)] != [1, 0]:
            b.fail(where, "permute that is not a matrix transpose")
    return Const(value.T, W.name)


# ----- state_dict -----------------------------------------------------------------------------
_KEY = re.compile(r"^(?:(?P<prefix>.+)\.)?(?P<index>\d+)\.(?P<kind>weight|bias)$")


def read_state_dict(path: str | Path) -> Reading:
    """The Linear layers of an `nn.Sequential` state_dict, in index order (data only), with
    the activations placed as the module indices show (see the module docstring)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            state = torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise ModelImportError(f"{path}: not a data-only state_dict (it holds Python objects, "
                               "e.g. a whole pickled module); save model.state_dict(), or "
                               "export TorchScript or ONNX") from None
    except Exception as exc:
        raise ModelImportError(f"{path}: PyTorch cannot read it ({type(exc).__name__})"
                               ) from None
    if isinstance(state, dict) and state.get("format") == "certify-checkpoint":
        raise ModelImportError(f"{path} is a certify checkpoint: run it without --system")
    if not isinstance(state, dict) or not state:
        raise ModelImportError(f"{path}: not a state_dict (a dict of tensors)")
    groups: dict[int, dict[str, Any]] = {}
    prefixes = set()
    for key, value in state.items():
        m = _KEY.match(str(key))
        if m is None:
            raise ModelImportError(f"{path}: key '{key}' is not a Linear layer's weight or bias "
                                   "of an nn.Sequential ('0.weight', '0.bias', '2.weight', ...)")
        if not isinstance(value, torch.Tensor):
            raise ModelImportError(f"{path}: key '{key}' is not a tensor")
        prefixes.add(m["prefix"])
        groups.setdefault(int(m["index"]), {})[m["kind"]] = (key, value)
    if len(prefixes) > 1:
        raise ModelImportError(f"{path}: keys under several modules ({sorted(map(str, prefixes))})"
                               "; one nn.Sequential is expected")
    layers: list[Layer] = []
    tensors: dict[int, tuple[torch.Tensor, torch.Tensor | None]] = {}
    for index in sorted(groups):
        group = groups[index]
        if "weight" not in group:
            raise ModelImportError(f"{path}: layer {index} has a bias but no weight")
        wkey, Wt = group["weight"]
        where = f"layer '{wkey[:-len('.weight')]}'"
        W = Wt.detach().to(torch.float64).numpy()
        if W.ndim != 2:
            raise ModelImportError(f"{path}: {where}: weight has shape {list(W.shape)}; a "
                                   "Linear weight is a matrix")
        bkey, bt = group.get("bias", (None, None))
        bias = (np.zeros(W.shape[0]) if bt is None
                else bt.detach().to(torch.float64).numpy().reshape(-1))
        if bias.shape != (W.shape[0],):
            raise ModelImportError(f"{path}: {where}: bias has {bias.size} values for "
                                   f"{W.shape[0]} outputs")
        for key, arr in ((wkey, W), (bkey, bias)):
            if not np.all(np.isfinite(arr)):
                raise ModelImportError(f"{path}: {where}: weight '{key}' contains NaN or Inf")
        if layers and layers[-1].W.shape[0] != W.shape[1]:
            raise ModelImportError(f"{path}: {where}: reads {W.shape[1]} values but "
                                   f"{layers[-1].where} gives {layers[-1].W.shape[0]}")
        layers.append(Layer(np.ascontiguousarray(W), bias, where, str(index)))
        tensors[index] = (Wt.detach(), None if bt is None else bt.detach())
    indices = sorted(groups)
    _check_placement(indices, [layer.where for layer in layers], str(path))
    notes = [] if len(layers) == 1 else [
        "a state_dict records the Linear layers only: read as nn.Sequential(Linear, act, "
        "Linear, ..., Linear), the module between two Linear layers taken to be the "
        "activation named, and nothing after the last one"]
    return Reading(layers, lambda activation: _sequential_reference(tensors, activation),
                   notes=notes)


def _check_placement(indices: list[int], wheres: list[str], path: str) -> None:
    """Linear layers at module indices 0, 2, 4, ...: one module (the activation) between two."""
    if indices[0] != 0:
        raise ModelImportError(
            f"{path}: {wheres[0]}: the first Linear layer is module {indices[0]} of the "
            f"nn.Sequential; modules before it hold no weights and a state_dict does not say "
            "what they are: export TorchScript or ONNX, which carry the graph")
    for (i, j), where in zip(zip(indices, indices[1:]), wheres[1:]):
        if j == i + 1:
            raise ModelImportError(
                f"{path}: {where}: Linear layers {i} and {j} are adjacent modules of the "
                "nn.Sequential, so no activation lies between them; certify's gain has one "
                "activation between every two linear layers (merge them, or export TorchScript "
                "or ONNX)")
        if j > i + 2:
            raise ModelImportError(
                f"{path}: {where}: {j - i - 1} modules lie between Linear layers {i} and {j}, "
                "and a state_dict does not say which of them are activations (Tanh? Dropout?): "
                "export TorchScript or ONNX, which carry the graph")


#: the torch modules a state_dict's user most likely used for each activation (softplus with
#: torch's threshold 20, accounted for by the import check)
_TORCH_MODULES = {"tanh": torch.nn.Tanh, "sigmoid": torch.nn.Sigmoid,
                  "softplus": torch.nn.Softplus, "silu": torch.nn.SiLU,
                  "elu": lambda: torch.nn.ELU(alpha=1.0),
                  "gelu": lambda: torch.nn.GELU(approximate="none")}


def _sequential_reference(tensors: dict[int, tuple[torch.Tensor, torch.Tensor | None]],
                          activation: str) -> TorchReference:
    """The nn.Sequential a state_dict's keys describe, built by torch with the activation
    module at each gap, its weights loaded by `load_state_dict` (strict)."""
    modules: list[torch.nn.Module] = []
    state: dict[str, torch.Tensor] = {}
    for index in range(max(tensors) + 1):
        if index not in tensors:
            modules.append(_TORCH_MODULES[activation]())
            continue
        W, b = tensors[index]
        modules.append(torch.nn.Linear(W.shape[1], W.shape[0], bias=b is not None,
                                       dtype=W.dtype))
        state[f"{index}.weight"] = W
        if b is not None:
            state[f"{index}.bias"] = b.reshape(-1)
    model = torch.nn.Sequential(*modules)
    model.load_state_dict(state, strict=True)
    model.eval().requires_grad_(False)
    t = 20.0  # nn.Softplus's threshold
    deviation = (Deviation(value=float(np.log1p(np.exp(-t))), slope=float(1 / (1 + np.exp(t))))
                 if activation == "softplus" else Deviation())

    def intermediate(z: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
        x = torch.as_tensor(z, dtype=next(iter(tensors.values()))[0].dtype)
        out = {}
        with torch.no_grad():
            for index, module in enumerate(model):
                x = module(x)
                out[str(index)] = x.to(torch.float64).numpy()
        return {name: out[name] for name in names}

    dtypes = [t for pair in tensors.values() for t in pair if t is not None]
    return TorchReference(model, 1, 0, [t.dtype for t in dtypes], deviation,
                          "torch, the nn.Sequential of its keys", intermediate)
