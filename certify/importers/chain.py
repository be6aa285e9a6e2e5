"""From a model's graph operations to a chain of affine layers and one activation.

Both readers (ONNX, TorchScript) walk their graph in order and report each operation here; a
`ChainBuilder` keeps a symbolic value per tensor and accepts only the shape of a certify gain:

    z = concat(xhat, y) -> Linear -> act -> Linear -> act -> ... -> Linear

Elementwise operations after a linear layer build a small expression tree of that layer's
output u; when the tree is read by the next linear layer (or would be the output) it must be
one of the known activations, matched structurally (never by evaluating it):
tanh(u), sigmoid(u), softplus(u), elu(u) (alpha = 1), gelu(u) (exact), u * sigmoid(u) (SiLU),
and 0.5 * u * (1 + erf(u / sqrt 2)) in any order of its factors (the erf form of GELU that
`torch.onnx.export` writes below opset 20). Constants in that pattern may be float32 roundings
of 0.5, 1 and 1/sqrt 2 (exporters store them so); the network certified is the exact GELU.
Nothing is executed: weights are read, shapes and finiteness checked, the graph's meaning
recognised or refused with one line naming the node.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NoReturn

import numpy as np

from certify.importers.result import NOT_C1, Layer, ModelImportError, check_activation

U: tuple = ("u",)
#: relative tolerance on the constants of the erf form of GELU: a few float32 roundings
GELU_CONSTANT_RTOL = 4 * 2.0 ** -24


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


@dataclass(frozen=True, eq=False)
class Part:
    """One of two model inputs (xhat or y) before they are concatenated."""

    index: int
    width: int | None


@dataclass(frozen=True, eq=False)
class Post:
    """The input z (k = 0) or the activation output after k linear layers."""

    k: int
    width: int | None


@dataclass(frozen=True, eq=False)
class Pre:
    """The output u = W h + b of a linear layer, not yet through an activation."""

    W: np.ndarray
    b: np.ndarray
    node: Node
    reads: int  # the k of the Post(k) it reads: a layer joins the chain only at position k

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

    # ----- bookkeeping --------------------------------------------------------------------
    def fail(self, where: Node | str, why: str) -> NoReturn:
        raise ModelImportError(f"{self.path}: {where}: {why}")

    def get(self, name: str, node: Node) -> Any:
        if name not in self.values:
            self.fail(node, f"its input '{name}' is not produced by an earlier node")
        return self.values[name]

    def set(self, name: str, value: Any) -> None:
        self.values[name] = value

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

    def input_part(self, name: str, index: int, width: int | None) -> None:
        self.set(name, Part(index, width))

    def concat(self, node: Node, parts: list[Any], axis: int) -> Post:
        if axis not in (1, -1):
            self.fail(node, f"concatenates along axis {axis}; xhat and y are joined along "
                            "the feature axis (1 or -1)")
        if len(parts) != 2 or not all(isinstance(v, Part) for v in parts) \
                or parts[0] is parts[1]:
            self.fail(node, "only the two model inputs (xhat, y) may be concatenated")
        first, second = parts
        if (first.width, second.width) not in ((self.n, self.p), (None, None), (self.n, None),
                                               (None, self.p)):
            self.fail(node, f"joins inputs of widths {first.width} and {second.width}; the "
                            f"spec needs xhat ({self.n} values) first, then y ({self.p})")
        return Post(0, self.n + self.p)

    # ----- linear layers ------------------------------------------------------------------
    def linear(self, node: Node, x: Any, W: Const, b: Const | None) -> Pre:
        """u = W h + b for W [out, in]; h must be the latest activation output (or z)."""
        h = self.activate(x, node)
        Wa = self.finite(W, node)
        if Wa.ndim != 2:
            self.fail(node, f"weight '{W.name}' has shape {list(Wa.shape)}; a matrix is needed")
        if h.width is not None and Wa.shape[1] != h.width:
            self.fail(node, f"weight '{W.name}' reads {Wa.shape[1]} values but its input has "
                            f"{h.width}")
        out = Wa.shape[0]
        ba = np.zeros(out) if b is None else self.bias(b, out, node)
        return Pre(np.ascontiguousarray(Wa), ba, node, h.k)

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
        self.seal(x.pre)
        return Post(len(self.layers), x.pre.width)

    def seal(self, pre: Pre) -> None:
        """Append `pre` as the next layer; it must read the chain's latest value (so a layer
        read twice, a branch or a skip connection is refused, never silently re-ordered)."""
        if pre.reads != len(self.layers):
            self.fail(pre.node, "its output or input is shared with another branch: only a "
                                "chain of layers is supported")
        self.layers.append(Layer(pre.W, pre.b, str(pre.node)))

    # ----- elementwise --------------------------------------------------------------------
    def add(self, node: Node, a: Any, b: Any) -> Any:
        """A bias folded into the layer (u + c), else an elementwise sum."""
        for pre, c in ((a, b), (b, a)):
            if isinstance(pre, Pre) and isinstance(c, Const):
                return Pre(pre.W, pre.b + self.bias(c, pre.width, node), pre.node, pre.reads)
        return self.binary(node, "add", a, b)

    def binary(self, node: Node, op: str, a: Any, b: Any) -> Elem:
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
                expr, pre = self.expression(v, node)
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

    def expression(self, v: Any, node: Node) -> tuple[tuple, Pre]:
        if isinstance(v, Pre):
            return U, v
        if isinstance(v, Elem):
            return v.expr, v.pre
        if isinstance(v, Post) and v.k == 0:
            self.fail(node, "acts on the model input before any linear layer")
        self.fail(node, "acts on a value that is not one layer's output (u = W h + b)")

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


# ----- activation patterns ----------------------------------------------------------------
def _factors(expr: tuple) -> tuple[float, list[tuple]]:
    """A product flattened: (constant factor, other factors); a / c counts as a * (1/c)."""
    if expr[0] == "mul":
        c1, f1 = _factors(expr[1])
        c2, f2 = _factors(expr[2])
        return c1 * c2, f1 + f2
    if expr[0] == "div" and expr[2][0] == "c" and expr[2][1] != 0.0:
        c, f = _factors(expr[1])
        return c / expr[2][1], f
    if expr[0] == "c":
        return expr[1], []
    return 1.0, [expr]


def _close(value: float, exact: float) -> bool:
    return abs(value - exact) <= GELU_CONSTANT_RTOL * abs(exact)


def _is_erf_gelu(expr: tuple) -> bool:
    """0.5 * u * (1 + erf(u / sqrt 2)), any order, constants up to float32 rounding."""
    scale, factors = _factors(expr)
    if not _close(scale, 0.5) or len(factors) != 2 or U not in factors:
        return False
    other = factors[1] if factors[0] == U else factors[0]
    if other[0] != "add":
        return False
    terms = [other[1], other[2]]
    one = [t for t in terms if t[0] == "c" and _close(t[1], 1.0)]
    erf = [t for t in terms if t[0] == "erf"]
    if len(one) != 1 or len(erf) != 1:
        return False
    inner_scale, inner = _factors(erf[0][1])
    return inner == [U] and _close(inner_scale, 1.0 / math.sqrt(2.0))


def match_activation(expr: tuple) -> str | None:
    """The activation name an expression tree of u is, or None."""
    if len(expr) == 2 and expr[1] == U and expr[0] in ("tanh", "sigmoid", "softplus", "elu",
                                                       "gelu", "silu"):
        return expr[0]
    if expr[0] == "mul" and {expr[1], expr[2]} == {U, ("sigmoid", U)}:
        return "silu"
    if _is_erf_gelu(expr):
        return "gelu"
    return None
