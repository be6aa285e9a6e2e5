"""Read an ONNX gain network with the `onnx` package: graph and initializers; then check it.

Accepted: Gemm, MatMul (+ Add as bias; its weight may come through a Transpose), the
elementwise activations Tanh, Sigmoid, Softplus, Elu (alpha = 1), Gelu (approximate = "none"),
SiLU as Mul(u, Sigmoid(u)) and GELU's erf form (Div/Mul, Erf, Add, Mul; see
`certify.model.importers.chain`), with Identity, Flatten (axis 1), Reshape to [-1, width], Dropout
in
inference mode and Constant nodes as no-ops. The input is one vector (xhat, y) or two inputs
joined by a Concat (two inputs are xhat, then y, by position). Everything else is refused with
one line naming the node (its name, or #index when it has none, and its operator). Reading runs
nothing; the import check (`certify.model.importers.crosscheck`) then evaluates the accepted graph,
which holds only the operators above, with onnxruntime (optional; graph optimisations off) or,
where it is not installed or has no kernel for the model's type (onnxruntime has no float64
Erf or Softplus), with onnx's reference evaluator, whose Erf and Gelu are replaced by float64
ones (its own compute erf in float32). The gain structure for p = 1 may be recorded in the
model's metadata_props under `certify.structure`. `onnx` is imported only here, when a model is
read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from certify.model.importers.chain import ChainBuilder, Const, Node
from certify.model.importers.crosscheck import Deviation
from certify.model.importers.result import (
    READ_ERRORS,
    STRUCTURE_KEY,
    ModelImportError,
    Reading,
    first_line,
    recorded_structure,
)

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


def _batch(value_info: Any) -> int | None:
    """The fixed batch size of a [batch, width] input (None: symbolic, any batch)."""
    dims = value_info.type.tensor_type.shape.dim
    if len(dims) != 2 or not dims[0].HasField("dim_value") or dims[0].dim_value <= 0:
        return None
    return int(dims[0].dim_value)


#: ONNX element types the import check can feed (TensorProto.FLOAT, DOUBLE, FLOAT16)
_DTYPES = {1: np.float32, 11: np.float64, 10: np.float16}


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


def read_onnx(path: str | Path, n: int, p: int) -> Reading:
    """Walk the graph of `path` into a `ChainBuilder`: the layers, the activation, the
    structure its metadata records and the model's own evaluation for the import check."""
    from onnx import numpy_helper

    model = load_onnx(path)
    graph = model.graph
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
    b.input_names([vi.name for vi in inputs])
    for index, vi in enumerate(inputs):
        rank, width = _input_width(vi)
        if rank > 2:
            raise ModelImportError(f"{path}: input '{vi.name}' has rank {rank}; a batch of "
                                   "vectors [batch, width] is expected")
        if vi.type.tensor_type.elem_type not in _DTYPES:
            raise ModelImportError(f"{path}: input '{vi.name}' has element type "
                                   f"{vi.type.tensor_type.elem_type}; certify reads float32, "
                                   "float64 and float16 models")
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
    props = {prop.key: prop.value for prop in model.metadata_props}
    reference = OnnxReference(model, inputs, n, Deviation(relative=4 * b.constant_deviation))
    return Reading(layers, lambda activation: reference, b.activation,
                   str(b.activation_node) if b.activation_node else None,
                   recorded_structure(props.get(STRUCTURE_KEY), str(path)), b.notes)


# ----- the model's own evaluation, for the import check ---------------------------------------
def _precise_ops() -> list[type]:
    """Erf and Gelu for onnx's reference evaluator in float64 (its own round erf to float32)."""
    from onnx.reference.op_run import OpRun
    from scipy.special import erf

    class Erf(OpRun):
        op_domain = ""

        def _run(self, x):  # type: ignore[override]
            return (erf(x.astype(np.float64)).astype(x.dtype),)

    class Gelu(OpRun):
        op_domain = ""

        def _run(self, x, approximate=None):  # type: ignore[override]
            xd = x.astype(np.float64)
            return ((0.5 * xd * (1.0 + erf(xd / np.sqrt(2.0)))).astype(x.dtype),)

    return [Erf, Gelu]


class OnnxReference:
    """An accepted ONNX graph evaluated by onnxruntime, else onnx's reference evaluator (see
    the module docstring); inputs fed as the graph declares them (one vector z or xhat and y;
    a fixed batch size or rank 1 fed row by row)."""

    def __init__(self, model: Any, inputs: list[Any], n: int, deviation: Deviation) -> None:
        self.model, self.n, self.deviation = model, n, deviation
        self.inputs = [(vi.name, _input_width(vi)[0], _batch(vi)) for vi in inputs]
        self.dtype = np.dtype(_DTYPES[inputs[0].type.tensor_type.elem_type])
        self.output = model.graph.output[0].name
        self.what = "onnxruntime"
        self._runner: Any = None

    def _ort(self, outputs: list[str]) -> Any:
        import onnxruntime as ort

        model = self.model
        if outputs != [self.output]:
            import onnx

            model = onnx.ModelProto()
            model.CopyFrom(self.model)
            del model.graph.output[:]
            model.graph.output.extend([onnx.ValueInfoProto(name=name) for name in outputs])
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        options.log_severity_level = 4  # nothing on stderr
        options.intra_op_num_threads = 1
        session = ort.InferenceSession(model.SerializeToString(), options,
                                       providers=["CPUExecutionProvider"])
        return lambda feeds: session.run(outputs, feeds)

    def _evaluator(self, outputs: list[str]) -> Any:
        from onnx.reference import ReferenceEvaluator

        evaluator = ReferenceEvaluator(self.model, new_ops=_precise_ops())
        return lambda feeds: evaluator.run(outputs, feeds)

    def _run(self, z: np.ndarray, outputs: list[str]) -> list[np.ndarray]:
        """The tensors `outputs` at the rows of z, each [rows, -1] (float64)."""
        runner = None
        if self.what == "onnxruntime":
            try:
                runner = self._ort(outputs)
                result = self._feed(runner, z)
            except Exception:  # not installed, or no kernel for this type: the evaluator
                self.what, runner = "onnx reference evaluator", None
        if runner is None:
            result = self._feed(self._evaluator(outputs), z)
        return [np.asarray(r, dtype=np.float64).reshape(len(z), -1) for r in result]

    def _feed(self, run: Any, z: np.ndarray) -> list[np.ndarray]:
        x = z.astype(self.dtype)
        parts = [x] if len(self.inputs) == 1 else [x[:, :self.n], x[:, self.n:]]
        rank, batch = self.inputs[0][1], self.inputs[0][2]
        if rank == 1 or batch is not None:  # fed in blocks of the fixed batch (rank 1: rows)
            size = 1 if rank == 1 else batch
            blocks = []
            for start in range(0, len(x), size):
                rows = [part[start:start + size] for part in parts]
                short = size - len(rows[0])
                rows = [np.concatenate([r, np.repeat(r[-1:], short, axis=0)]) for r in rows]
                feeds = {name: (r[0] if rank == 1 else r)
                         for (name, _, _), r in zip(self.inputs, rows)}
                out = run(feeds)
                blocks.append([np.asarray(o).reshape(size, -1)[:size - short] for o in out])
            return [np.concatenate(col) for col in zip(*blocks)]
        return run({name: part for (name, _, _), part in zip(self.inputs, parts)})

    def values(self, z: np.ndarray) -> np.ndarray:
        return self._run(z, [self.output])[0]

    def jacobians(self, z: np.ndarray) -> None:
        return None  # runtimes give values only: the check takes finite differences

    def tensors(self, z: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
        return dict(zip(names, self._run(z, list(names))))


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
        C = args[2] if len(args) > 2 else None  # not a constant: refused as a skip by linear
        if isinstance(C, Const):
            C = Const(beta * np.asarray(C.value, dtype=np.float64), C.name)
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
