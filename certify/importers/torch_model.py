"""Read a PyTorch gain network: a TorchScript file, or a state_dict of Linear layers.

TorchScript: `torch.jit.load`, then the module's *inlined* forward graph is walked node by node
(the same `ChainBuilder` as ONNX): `aten::linear` with the module's own parameters, or
`aten::matmul` by a parameter matrix (through `W.t()`, `W.T`, `transpose`, `permute`) plus
`aten::add` of a bias; the activations `aten::tanh`, `sigmoid`, `softplus` (beta = 1), `elu`
(alpha = scale = 1), `gelu` (approximate = "none"), `silu`, `mul`(u, sigmoid(u)); `aten::cat`
of two inputs; reshape/flatten/dropout (eval mode) no-ops; and a `prim::If` on a constant (the
`inplace` flag of torch.nn.functional) through the branch it takes. Class names are not trusted
(a TorchScript file carries its own code); only the graph's operators decide. Anything else is
refused with one line naming the node (%value and operator). The model is never run.

state_dict: `torch.load(weights_only=True)` (data only, never code) of an `nn.Sequential` of
Linear layers: keys `[prefix.]i.weight` / `[prefix.]i.bias` in index order. It carries no
activation, so the caller names one (`--activation`).
"""

from __future__ import annotations

import pickle
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from certify.checkpoint import ZIP_ERRORS
from certify.importers.chain import ChainBuilder, Const, Node
from certify.importers.result import READ_ERRORS, Layer, ModelImportError, first_line

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
def read_torchscript(path: str | Path, n: int, p: int) -> tuple[ChainBuilder, list[Layer]]:
    try:
        module = torch.jit.load(str(path), map_location="cpu")
    except Exception as exc:  # torch raises RuntimeError and friends for damaged archives
        raise ModelImportError(f"{path}: TorchScript cannot load it ({type(exc).__name__})"
                               ) from None
    graph = module.inlined_graph
    b = ChainBuilder(str(path), n, p)
    objects: dict[str, Any] = {}
    params = list(graph.inputs())
    objects[params[0].debugName()] = module
    data = params[1:]
    if len(data) not in (1, 2):
        raise ModelImportError(f"{path}: forward takes {len(data)} inputs; certify reads one "
                               "vector (xhat, y) or two inputs xhat and y")
    for index, value in enumerate(data):
        if len(data) == 1:
            b.input_vector(value.debugName(), None, f"input '{value.debugName()}'")
        else:
            b.input_part(value.debugName(), index, None)
    last = _walk(b, graph.nodes(), objects, str(path)) or Node("output", "return")
    outs = list(graph.outputs())
    if len(outs) != 1:
        raise ModelImportError(f"{path}: forward returns {len(outs)} values; certify reads one")
    return b, b.output(b.get(outs[0].debugName(), last), last)


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
        W = b.constant(args[1], where, "weight")
        bias = args[2] if isinstance(args[2], Const) and args[2].value is not None else None
        return b.linear(where, args[0], W, bias)
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


def read_state_dict(path: str | Path) -> list[Layer]:
    """The Linear layers of an `nn.Sequential` state_dict, in index order (data only)."""
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
    for index in sorted(groups):
        group = groups[index]
        if "weight" not in group:
            raise ModelImportError(f"{path}: layer {index} has a bias but no weight")
        wkey, W = group["weight"]
        where = f"layer '{wkey[:-len('.weight')]}'"
        W = W.detach().to(torch.float64).numpy()
        if W.ndim != 2:
            raise ModelImportError(f"{path}: {where}: weight has shape {list(W.shape)}; a "
                                   "Linear weight is a matrix")
        bkey, bias = group.get("bias", (None, torch.zeros(W.shape[0])))
        bias = bias.detach().to(torch.float64).numpy().reshape(-1)
        if bias.shape != (W.shape[0],):
            raise ModelImportError(f"{path}: {where}: bias has {bias.size} values for "
                                   f"{W.shape[0]} outputs")
        for key, arr in ((wkey, W), (bkey, bias)):
            if not np.all(np.isfinite(arr)):
                raise ModelImportError(f"{path}: {where}: weight '{key}' contains NaN or Inf")
        if layers and layers[-1].W.shape[0] != W.shape[1]:
            raise ModelImportError(f"{path}: {where}: reads {W.shape[1]} values but "
                                   f"{layers[-1].where} gives {layers[-1].W.shape[0]}")
        layers.append(Layer(np.ascontiguousarray(W), bias, where))
    return layers
