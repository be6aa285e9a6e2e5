"""From a model's graph operations to a chain of affine layers and one activation.

Both readers (ONNX, TorchScript) walk their graph in order and report each operation here; a
`ChainBuilder` keeps a symbolic value per tensor and accepts only the shape of a certify gain:

    z = concat(xhat, y) -> Linear -> act -> Linear -> act -> ... -> Linear

The model input is used exactly once, as the chain's input: the two inputs of a two-input
model (xhat first, then y, by position) meet in one Concat, in either order (a Concat of (y, xhat)
is honoured by reordering the first layer's columns, which is exact); any other use of an input
(a bias, a residual add, a second branch) is refused like other skip connections, naming the
node. Elementwise operations after a linear layer build a small expression tree of that layer's
output u; when the tree is read by the next linear layer (or would be the output) it must be
one of the known activations, matched structurally (never by evaluating it):
tanh(u), sigmoid(u), softplus(u), elu(u) (alpha = 1), gelu(u) (exact), u * sigmoid(u) (SiLU),
and 0.5 * u * (1 + erf(u / sqrt 2)) in any order of its factors (the erf form of GELU that
`torch.onnx.export` writes below opset 20). Constants in that pattern may be float32 roundings
of 0.5, 1 and 1/sqrt 2 (exporters store them so); the network certified is the exact GELU.
An input normalisation (z - mean) / std, or any add/sub/mul/div of the input by constants
(scalars or one per input value), is folded into the first layer: W (s z + t) + b =
(W diag s) z + (b + W t), exact in reals and one float64 rounding per weight (a note says so).
Nothing is executed: weights are read, shapes and finiteness checked, the graph's meaning
recognised or refused with one line naming the node.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, NoReturn

import numpy as np

from certify.model.importers.patterns import U, constant_deviation, match_activation
from certify.model.importers.result import NOT_C1, Layer, ModelImportError, check_activation


def _columns_to_z(a: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """`a` (columns, or entries of a vector, in the model's input order) in z's order."""
    out = np.empty_like(a)
    out[..., cols] = a
    return out


@dataclass(frozen=True)
class Node:
    """A graph node, as the user's tools name it."""

    name: str
    op: str

    def __str__(self) -> str:
        return f"node '{self.name}' ({self.op})"


@dataclass(frozen=True, eq=False)
class Const:
    """A constant tensor (initializer, Constant node, module parameter)."""

    value: np.ndarray
    name: str


#: what each of a two-input model's inputs is, by position
PART_NAMES = ("xhat", "y")
#: input names (lower case, letters only) that say which input is which
_X_NAMES = {"xhat", "x", "xh", "xest", "estimate", "state", "states"}
_Y_NAMES = {"y", "ymeas", "meas", "measurement", "measurements"}


@dataclass(frozen=True, eq=False)
class Part:
    """One of two model inputs (index 0: xhat, 1: y) before they are concatenated, as
    scale * input + shift when the model normalises it (scale, shift None: as given)."""

    index: int
    width: int | None
    scale: np.ndarray | None = None
    shift: np.ndarray | None = None
    name: str = ""


@dataclass(frozen=True, eq=False)
class Post:
    """The input z (k = 0; normalised as scale * z + shift where the model does so) or the
    activation output after k linear layers. For k = 0, `order` is the input each block of the
    model's vector comes from ((0, 1): xhat then y, as certify's z; (1, 0): the model joined
    (y, xhat)); scale and shift are in the model's order."""

    k: int
    width: int | None
    scale: np.ndarray | None = None
    shift: np.ndarray | None = None
    order: tuple[int, ...] = (0, 1)


@dataclass(frozen=True, eq=False)
class Pre:
    """The output u = W h + b of a linear layer, not yet through an activation."""

    W: np.ndarray
    b: np.ndarray
    node: Node
    reads: int  # the k of the Post(k) it reads: a layer joins the chain only at position k
    #: a folded input normalisation: (W, b, s, t) as the model computes W (s z + t) + b
    fold: tuple[np.ndarray, ...] | None = None

    @property
    def width(self) -> int:
        return int(self.W.shape[0])


@dataclass(frozen=True, eq=False)
class Elem:
    """An elementwise expression of one layer's output `pre` (the tree's leaf U is `pre`)."""

    expr: tuple
    pre: Pre
    node: Node


@dataclass(frozen=True, eq=False)
class Shaped:
    """A last layer's output reshaped to [batch, n, p] (allowed only as the graph output)."""

    pre: Pre
    node: Node


class ChainBuilder:
    """Symbolic values per tensor name; layers and the activation as they are recognised."""

    def __init__(self, path: str, n: int, p: int) -> None:
        self.path, self.n, self.p = path, n, p
        self.values: dict[str, Any] = {}
        self.layers: list[Layer] = []
        self.activation: str | None = None
        self.activation_node: Node | None = None
        self.notes: list[str] = []
        self.names: dict[int, str] = {}  # id(value) -> the last tensor name holding it
        #: largest relative deviation of an activation pattern's constants from the exact ones
        self.constant_deviation = 0.0

    # ----- bookkeeping --------------------------------------------------------------------
    def fail(self, where: Node | str, why: str) -> NoReturn:
        raise ModelImportError(f"{self.path}: {where}: {why}")

    def get(self, name: str, node: Node) -> Any:
        if name not in self.values:
            self.fail(node, f"its input '{name}' is not produced by an earlier node")
        return self.values[name]

    def set(self, name: str, value: Any) -> None:
        self.values[name] = value
        if value is not None:
            self.names[id(value)] = name

    def describe(self, value: Any) -> str:
        """What a symbolic value is, in a refusal's words."""
        if isinstance(value, Part):
            return f"the model input '{value.name}' ({PART_NAMES[value.index]})"
        if isinstance(value, Post):
            return "the model input" if value.k == 0 else f"the activation after layer {value.k}"
        if isinstance(value, (Pre, Shaped)):
            return f"the output of {value.node}"
        if isinstance(value, Elem):
            return f"the output of {value.node}"
        return "a value that is not a constant"

    def constant(self, value: Any, node: Node, what: str) -> Const:
        if not isinstance(value, Const):
            self.fail(node, f"its {what} must be a constant (an initializer or parameter)")
        return value

    def finite(self, const: Const, node: Node) -> np.ndarray:
        arr = np.asarray(const.value, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            self.fail(node, f"weight '{const.name}' contains NaN or Inf")
        return arr

    def width(self, value: Any) -> int | None:
        if isinstance(value, (Pre, Part, Post)):
            return value.width
        if isinstance(value, Elem):
            return value.pre.width
        return None

    # ----- inputs -------------------------------------------------------------------------
    def input_vector(self, name: str, width: int | None, where: str) -> None:
        if width is not None and width != self.n + self.p:
            self.fail(where, f"has {width} values; the spec needs n+p = {self.n + self.p} "
                             f"(xhat: {self.n}, then y: {self.p})")
        self.set(name, Post(0, self.n + self.p))

    def input_names(self, names: list[str]) -> None:
        """Two inputs are xhat, then y, by position; names that say the opposite ('y' first,
        'xhat' second) are refused rather than read against the model's intent."""
        if len(names) != 2:
            return
        first, second = (re.sub(r"[^a-z]", "", re.sub(r"\.\d+$", "", nm.lower()))
                         for nm in names)
        if first in _Y_NAMES and second in _X_NAMES:
            self.fail(f"inputs ('{names[0]}', '{names[1]}')",
                      "their names say y comes first; certify reads a two-input model by "
                      "position as (xhat, y): export it with forward(xhat, y)")

    def input_part(self, name: str, index: int, width: int | None) -> None:
        """Input `index` of a two-input model: xhat (n values) first, then y (p values)."""
        need = (self.n, self.p)[index]
        if width is not None and width != need:
            self.fail(f"input '{name}'", f"has {width} values; certify reads a two-input model "
                                         f"by position as xhat ({self.n} values) first, then y "
                                         f"({self.p})")
        self.set(name, Part(index, width, name=name))

    def part_width(self, part: Part) -> int:
        return (self.n, self.p)[part.index]

    def concat(self, node: Node, parts: list[Any], axis: int) -> Post:
        """The two inputs joined, in either order: (xhat, y) is certify's z; (y, xhat) is
        recorded as `order` and honoured in the first layer (its columns reordered)."""
        if axis not in (1, -1):
            self.fail(node, f"concatenates along axis {axis}; xhat and y are joined along "
                            "the feature axis (1 or -1)")
        for v in parts:
            if not isinstance(v, Part):
                self.fail(node, f"concatenates {self.describe(v)}; only the two model inputs "
                                "(xhat, y) may be concatenated, once each")
        order = tuple(part.index for part in parts)
        if sorted(order) != [0, 1]:
            used = ", ".join(PART_NAMES[i] for i in order)
            self.fail(node, f"concatenates ({used}); only the two model inputs (xhat, y) may "
                            "be concatenated, once each")
        if order != (0, 1):
            self.notes.append(f"{node} joins the inputs as (y, xhat); the first layer's columns "
                              "are reordered to read certify's z = (xhat, y) (exact)")
        if all(part.scale is None and part.shift is None for part in parts):
            return Post(0, self.n + self.p, order=order)
        scale, shift = zip(*(self.affine_vectors(part, self.part_width(part), node)
                             for part in parts))
        return Post(0, self.n + self.p, np.concatenate(scale), np.concatenate(shift), order)

    def z_columns(self, order: tuple[int, ...]) -> np.ndarray:
        """For a model vector joined in `order`, the column of z = (xhat, y) each of its
        entries is."""
        blocks = {0: np.arange(self.n), 1: np.arange(self.n, self.n + self.p)}
        return np.concatenate([blocks[i] for i in order])

    # ----- input normalisation, folded into the first layer -------------------------------
    def affine_vectors(self, value: Post | Part, width: int, node: Node
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(scale, shift) of a normalised input as vectors of `width` values."""
        scale = np.ones(1) if value.scale is None else value.scale
        shift = np.zeros(1) if value.shift is None else value.shift
        if scale.size not in (1, width) or shift.size not in (1, width):
            self.fail(node, f"normalises an input of {width} values with constants of "
                            f"{max(scale.size, shift.size)}")
        return np.broadcast_to(scale, (width,)).copy(), np.broadcast_to(shift, (width,)).copy()

    def normalise(self, node: Node, op: str, value: Post | Part, c: Const, c_first: bool
                  ) -> Post | Part:
        """value (op) c, or c (op) value, as a new scale * input + shift (exact in reals;
        folding it into W and b later rounds each weight once in float64)."""
        arr = self.finite(c, node)
        if arr.ndim > 2 or (arr.ndim == 2 and arr.shape[0] != 1) or (
                arr.size != 1 and value.width is not None and arr.size != value.width):
            self.fail(node, f"constant '{c.name}' of shape {list(arr.shape)} does not match "
                            f"the input's {value.width} values")
        cv = arr.reshape(-1)
        scale = np.ones(1) if value.scale is None else value.scale
        shift = np.zeros(1) if value.shift is None else value.shift
        if op == "add":
            shift = shift + cv
        elif op == "sub":
            scale, shift = (-scale, cv - shift) if c_first else (scale, shift - cv)
        elif op == "mul":
            scale, shift = scale * cv, shift * cv
        elif c_first or not np.all(cv != 0):
            self.fail(node, "divides by the input or by zero: not an input normalisation")
        else:
            scale, shift = scale / cv, shift / cv
        if isinstance(value, Part):
            return Part(value.index, value.width, scale, shift, value.name)
        return Post(0, value.width, scale, shift, value.order)

    # ----- linear layers ------------------------------------------------------------------
    def linear(self, node: Node, x: Any, W: Any, b: Any) -> Pre:
        """u = W h + b for W [out, in]; h must be the latest activation output (or z). The
        bias b is None, a constant holding None (no bias) or a constant tensor; anything else
        (a model input or a computed value as the bias) is a skip connection, refused."""
        h = self.activate(x, node)
        W = self.constant(W, node, "weight")
        Wa = self.finite(W, node)
        if Wa.ndim != 2:
            self.fail(node, f"weight '{W.name}' has shape {list(Wa.shape)}; a matrix is needed")
        if h.width is not None and Wa.shape[1] != h.width:
            self.fail(node, f"weight '{W.name}' reads {Wa.shape[1]} values but its input has "
                            f"{h.width}")
        out = Wa.shape[0]
        if b is not None and not isinstance(b, Const):
            self.fail(node, f"uses {self.describe(b)} as its bias: a skip connection; only a "
                            "chain of layers (constant biases) is supported")
        ba = np.zeros(out) if b is None or b.value is None else self.bias(b, out, node)
        fold = None
        if h.scale is not None or h.shift is not None:  # W (s z + t) + b = (W diag s) z + (b + W t)
            scale, shift = self.affine_vectors(h, Wa.shape[1], node)
            fold = (Wa, ba, scale, shift)
            Wa, ba = Wa * scale[None, :], ba + Wa @ shift
            self.notes.append(f"input normalisation folded into the first layer ({node}): "
                              "exact up to one float64 rounding per weight")
        if h.k == 0 and h.order != (0, 1):  # the model reads (y, xhat): reorder the columns
            cols = self.z_columns(h.order)
            Wa = _columns_to_z(Wa, cols)
            if fold is not None:
                fold = (_columns_to_z(fold[0], cols), fold[1], _columns_to_z(fold[2], cols),
                        _columns_to_z(fold[3], cols))
        return Pre(np.ascontiguousarray(Wa), ba, node, h.k, fold)

    def bias(self, b: Const, out: int, node: Node) -> np.ndarray:
        arr = self.finite(b, node)
        if arr.size not in (1, out) or arr.ndim > 2 or (arr.ndim == 2 and arr.shape[0] != 1):
            self.fail(node, f"bias '{b.name}' has shape {list(arr.shape)}; the layer gives "
                            f"{out} values")
        return np.broadcast_to(arr.reshape(-1), (out,)).astype(np.float64).copy()

    def activate(self, x: Any, node: Node) -> Post:
        """The value a linear layer reads: z, or a recognised activation of the last layer."""
        if isinstance(x, Post):
            if x.k != len(self.layers):
                self.fail(node, "reads an earlier layer's output: only a chain of layers "
                                "(no skip connections) is supported")
            return x
        if isinstance(x, Pre):
            self.fail(node, f"reads {x.node} directly: two linear layers with no activation "
                            "between them")
        if isinstance(x, Part):
            self.fail(node, "reads one model input alone; xhat and y must be concatenated "
                            "first (Concat)")
        if isinstance(x, Shaped):
            self.fail(node, f"reads the reshaped output of {x.node}")
        if not isinstance(x, Elem):
            self.fail(node, "reads a constant where the layer input is expected")
        name = match_activation(x.expr)
        if name is None:
            self.fail(x.node, "the elementwise operations ending here are not a supported "
                              "activation (tanh, sigmoid, softplus, elu, gelu, silu)")
        check_activation(name, f"{self.path}: {x.node}")
        if self.activation is not None and name != self.activation:
            self.fail(x.node, f"uses {name} but {self.activation_node} uses "
                              f"{self.activation}; certify's gain has one activation")
        self.activation, self.activation_node = name, x.node
        self.constant_deviation = max(self.constant_deviation, constant_deviation(x.expr))
        self.seal(x.pre)
        return Post(len(self.layers), x.pre.width)

    def seal(self, pre: Pre) -> None:
        """Append `pre` as the next layer; it must read the chain's latest value (so a layer
        read twice, a branch or a skip connection is refused, never silently re-ordered)."""
        if pre.reads != len(self.layers):
            self.fail(pre.node, "its output or input is shared with another branch: only a "
                                "chain of layers is supported")
        self.layers.append(Layer(pre.W, pre.b, str(pre.node), self.names.get(id(pre)),
                                 pre.fold))

    # ----- elementwise --------------------------------------------------------------------
    def add(self, node: Node, a: Any, b: Any) -> Any:
        """A bias folded into the layer (u + c), else an elementwise sum."""
        for pre, c in ((a, b), (b, a)):
            if isinstance(pre, Pre) and isinstance(c, Const):
                bias = self.bias(c, pre.width, node)
                fold = None if pre.fold is None else (*pre.fold[:1], pre.fold[1] + bias,
                                                      *pre.fold[2:])
                return Pre(pre.W, pre.b + bias, pre.node, pre.reads, fold)
        return self.binary(node, "add", a, b)

    def binary(self, node: Node, op: str, a: Any, b: Any) -> Any:
        for value, c, c_first in ((a, b, False), (b, a, True)):
            if isinstance(value, (Part, Post)) and isinstance(c, Const) and (
                    isinstance(value, Part) or value.k == 0):
                return self.normalise(node, op, value, c, c_first)
        exprs, pres = [], []
        for v in (a, b):
            if isinstance(v, Const):
                arr = np.asarray(v.value, dtype=np.float64)
                if arr.size != 1:
                    self.fail(node, f"constant '{v.name}' of shape {list(arr.shape)}: only "
                                    "scalars may enter an activation")
                if not np.isfinite(arr).all():
                    self.fail(node, f"constant '{v.name}' is NaN or Inf")
                exprs.append(("c", float(arr.reshape(-1)[0])))
            else:
                expr, pre = self.expression(v, node, b if v is a else a)
                exprs.append(expr)
                pres.append(pre)
        if not pres:
            self.fail(node, "an operation on constants only is not supported (fold it when "
                            "exporting)")
        if len(pres) == 2 and pres[0] is not pres[1]:
            self.fail(node, "combines the outputs of two different layers")
        return Elem((op, *exprs), pres[0], node)

    def unary(self, node: Node, op: str, x: Any) -> Elem:
        expr, pre = self.expression(x, node)
        return Elem((op, expr), pre, node)

    def expression(self, v: Any, node: Node, other: Any = None) -> tuple[tuple, Pre]:
        """The expression tree of `v`, an operand of an elementwise node (`other`: the node's
        other operand, for the refusal's words)."""
        if isinstance(v, Pre):
            return U, v
        if isinstance(v, Elem):
            return v.expr, v.pre
        if isinstance(v, (Part, Post)) and (isinstance(v, Part) or v.k == 0):
            if isinstance(other, (Pre, Elem, Post)) and not (isinstance(other, Post)
                                                              and other.k == 0):
                self.fail(node, f"combines {self.describe(v)} with {self.describe(other)}: a "
                                "skip connection; only a chain of layers is supported (the "
                                "model input is read once, by the first layer)")
            self.fail(node, f"acts on {self.describe(v)} before any linear layer (only an "
                            "input normalisation by constants may come before it)")
        self.fail(node, f"acts on {self.describe(v)}, which is not one layer's output "
                        "(u = W h + b)")

    def non_c1(self, node: Node, what: str) -> NoReturn:
        self.fail(node, f"{what} is not C^1: {NOT_C1}")

    # ----- shape no-ops -------------------------------------------------------------------
    def reshape(self, node: Node, x: Any, target: list[int]) -> Any:
        """Harmless reshapes only: [-1|0, width] (a no-op) or, on a last layer's output,
        [-1|0, n, p] (row-major, as certify reshapes a structural gain)."""
        width = self.width(x)
        lead_ok = len(target) >= 2 and target[0] in (-1, 0)
        if lead_ok and len(target) == 2 and width is not None and target[1] in (width, -1):
            return x
        if lead_ok and target[1:] == [self.n, self.p] and isinstance(x, Pre) \
                and x.width == self.n * self.p:
            return Shaped(x, node)
        self.fail(node, f"reshapes a value of width {width} to {target}: only [-1, width] "
                        f"(or [-1, n, p] on the output) is a harmless no-op")

    def flatten(self, node: Node, x: Any, axis: int) -> Any:
        if axis != 1:
            self.fail(node, f"flattens from axis {axis}; only axis 1 is a no-op here")
        return x.pre if isinstance(x, Shaped) else x

    # ----- output -------------------------------------------------------------------------
    def output(self, value: Any, where: Node | str) -> list[Layer]:
        if isinstance(value, Shaped):
            value = value.pre
        if isinstance(value, Elem):
            self.fail(value.node, "the output passes through an activation; certify's gain "
                                  "ends with a linear layer")
        if not isinstance(value, Pre):
            self.fail(where, "the output is not a linear layer's result")
        self.seal(value)
        return self.layers
