"""Read an ONNX gain network with the `onnx` package: graph and initializers, nothing executed.

Accepted: Gemm, MatMul (+ Add as bias; its weight may come through a Transpose), the
elementwise activations Tanh, Sigmoid, Softplus, Elu (alpha = 1), Gelu (approximate = "none"),
SiLU as Mul(u, Sigmoid(u)) and GELU's erf form (Div/Mul, Erf, Add, Mul; see
`certify.importers.chain`), with Identity, Flatten (axis 1), Reshape to [-1, width], Dropout in
inference mode and Constant nodes as no-ops. The input is one vector (xhat, y) or two inputs
joined by a Concat. Everything else is refused with one line naming the node (its name, or
#index when it has none, and its operator). `onnx` is imported only here, when a model is read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from certify.importers.chain import ChainBuilder, Const, Node
from certify.importers.result import READ_ERRORS, ModelImportError, first_line

#: ONNX operators that are not C^1 (refused with the reason, not as "unsupported")
NON_C1_OPS = {"Relu": "ReLU", "LeakyRelu": "leaky ReLU", "PRelu": "PReLU", "Clip": "Clip",
              "HardSigmoid": "hard sigmoid", "HardSwish": "hard swish", "Selu": "SELU",
              "Abs": "Abs", "Sign": "Sign", "Max": "Max", "Min": "Min", "Floor": "Floor",
              "Ceil": "Ceil", "Round": "Round", "ThresholdedRelu": "thresholded ReLU",
              "Shrink": "Shrink"}
_UNARY = {"Tanh": "tanh", "Sigmoid": "sigmoid", "Softplus": "softplus", "Erf": "erf"}
_BINARY = {"Mul": "mul", "Div": "div", "Sub": "sub"}
ACCEPTED = ("Gemm", "MatMul", "Transpose", "Add", "Sub", "Mul", "Div", "Tanh", "Sigmoid",
            "Softplus", "Elu", "Gelu", "Erf", "Concat", "Identity", "Flatten", "Reshape",
            "Dropout", "Constant")


def _attrs(node: Any) -> dict[str, Any]:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _constant_value(node: Any, where: Node, builder: ChainBuilder) -> np.ndarray:
    from onnx import numpy_helper

    attrs = {a.name: a for a in node.attribute}
    if "value" in attrs:
        return numpy_helper.to_array(attrs["value"].t)
    for key in ("value_float", "value_floats", "value_int", "value_ints"):
        if key in attrs:
            return np.asarray(_attrs(node)[key])
    builder.fail(where, "a Constant without a numeric value")


def _input_width(value_info: Any) -> tuple[int, int | None]:
    """(rank, width) of a graph input; width None when the last dimension is symbolic."""
    dims = value_info.type.tensor_type.shape.dim
    if not dims:
        return 0, None
    last = dims[-1]
    return len(dims), (last.dim_value if last.HasField("dim_value") else None)


def load_onnx(path: str | Path) -> Any:
    """The ModelProto of `path`, or one line saying why it is not an ONNX model."""
    try:
        import onnx
    except ImportError:
        raise ModelImportError(f"{path}: reading ONNX models needs the 'onnx' package "
                               "(pip install onnx)") from None
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf decode errors have no common public base class
        raise ModelImportError(f"{path}: not an ONNX model, or a damaged one "
                               f"({type(exc).__name__}{first_line(exc)})") from None
    if not model.graph.node:
        raise ModelImportError(f"{path}: not an ONNX model (no graph nodes)")
    return model


def read_onnx(path: str | Path, n: int, p: int) -> tuple[ChainBuilder, list]:
    """Walk the graph of `path` into a `ChainBuilder`; returns it and the layers."""
    from onnx import numpy_helper

    graph = load_onnx(path).graph
    b = ChainBuilder(str(path), n, p)
    initializers = set()
    for init in graph.initializer:
        try:
            b.set(init.name, Const(numpy_helper.to_array(init), init.name))
        except READ_ERRORS as exc:
            raise ModelImportError(f"{path}: initializer '{init.name}' cannot be read "
                                   f"({type(exc).__name__}{first_line(exc)})") from None
        initializers.add(init.name)
    inputs = [vi for vi in graph.input if vi.name not in initializers]
    if len(inputs) not in (1, 2):
        names = ", ".join(vi.name for vi in inputs)
        raise ModelImportError(f"{path}: the model has {len(inputs)} inputs ({names}); certify "
                               "reads one vector (xhat, y) or two inputs xhat and y")
    for index, vi in enumerate(inputs):
        rank, width = _input_width(vi)
        if rank > 2:
            raise ModelImportError(f"{path}: input '{vi.name}' has rank {rank}; a batch of "
                                   "vectors [batch, width] is expected")
        if len(inputs) == 1:
            b.input_vector(vi.name, width, f"input '{vi.name}'")
        else:
            b.input_part(vi.name, index, width)
    producers: dict[str, Node] = {}
    for index, node in enumerate(graph.node):
        where = Node(node.name or f"#{index}", node.op_type)
        try:
            value = _apply(b, node, where)
        except READ_ERRORS as exc:  # malformed attributes or tensors: the file's fault
            b.fail(where, f"cannot be read ({type(exc).__name__}{first_line(exc)})")
        for out in node.output[:1]:
            b.set(out, value)
            producers[out] = where
    if len(graph.output) != 1:
        raise ModelImportError(f"{path}: the model has {len(graph.output)} outputs; certify "
                               "reads one (the gain)")
    name = graph.output[0].name
    where = producers.get(name, Node(name, "graph output"))
    layers = b.output(b.get(name, where), where)
    return b, layers


def _apply(b: ChainBuilder, node: Any, where: Node) -> Any:
    """The symbolic value of one node's (first) output."""
    op = node.op_type
    if node.domain not in ("", "ai.onnx"):
        b.fail(where, f"operator from domain '{node.domain}' is not supported")
    if op in NON_C1_OPS:
        b.non_c1(where, NON_C1_OPS[op])
    if op not in ACCEPTED:
        b.fail(where, f"unsupported operator {op}; certify reads {', '.join(ACCEPTED)}")
    if op == "Constant":
        return Const(_constant_value(node, where, b), node.output[0])
    args = [b.get(name, where) if name else None for name in node.input]
    attrs = _attrs(node)
    if op == "Gemm":
        if attrs.get("transA", 0):
            b.fail(where, "transA = 1 is not supported")
        B = b.constant(args[1], where, "second operand (the weight)")
        alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
        W = np.asarray(B.value, dtype=np.float64)
        W = alpha * (W if attrs.get("transB", 0) else W.T)
        C = None
        if len(args) > 2 and args[2] is not None:
            c = b.constant(args[2], where, "third operand (the bias)")
            C = Const(beta * np.asarray(c.value, dtype=np.float64), c.name)
        return b.linear(where, args[0], Const(W, B.name), C)
    if op == "Transpose":  # of a weight matrix (an initializer), as some exporters write
        W = b.constant(args[0], where, "operand (a weight matrix)")
        value = np.asarray(W.value)
        if value.ndim != 2 or list(attrs.get("perm", [1, 0])) != [1, 0]:
            b.fail(where, f"only the transpose of a matrix; got shape {list(value.shape)}")
        return Const(value.T, W.name)
    if op == "MatMul":
        B = b.constant(args[1], where, "second operand (the weight)")
        W = np.asarray(B.value, dtype=np.float64)
        return b.linear(where, args[0], Const(W.T if W.ndim == 2 else W, B.name), None)
    if op == "Add":
        return b.add(where, args[0], args[1])
    if op in _BINARY:
        return b.binary(where, _BINARY[op], args[0], args[1])
    if op in _UNARY:
        return b.unary(where, _UNARY[op], args[0])
    if op == "Elu":
        alpha = float(attrs.get("alpha", 1.0))
        if alpha != 1.0:
            b.fail(where, f"ELU with alpha = {alpha:g}: only alpha = 1 is C^1")
        return b.unary(where, "elu", args[0])
    if op == "Gelu":
        approx = attrs.get("approximate", "none")
        approx = approx.decode() if isinstance(approx, bytes) else approx
        if approx != "none":
            b.fail(where, f"GELU with approximate = '{approx}' is not supported; export the "
                          "exact (erf) GELU")
        return b.unary(where, "gelu", args[0])
    if op == "Concat":
        return b.concat(where, args, int(attrs.get("axis", 1)))
    if op == "Flatten":
        return b.flatten(where, args[0], int(attrs.get("axis", 1)))
    if op == "Reshape":
        shape = b.constant(args[1], where, "shape")
        return b.reshape(where, args[0], [int(s) for s in np.asarray(shape.value).reshape(-1)])
    if op == "Dropout" and len(args) > 2 and args[2] is not None:
        mode = args[2]
        if not isinstance(mode, Const) or bool(np.asarray(mode.value).reshape(-1)[0]):
            b.fail(where, "Dropout in training mode is not a no-op")
    return args[0]  # Identity, Dropout in inference mode
