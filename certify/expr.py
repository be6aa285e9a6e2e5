"""The function table and the evaluation of spec expression trees (torch, intervals).

Parsing lives in `certify.parse` (re-exported here as `parse_expression`): only numbers,
declared names, `+ - * / **`, unary minus/plus and the functions of `FUNCTIONS` are
accepted. The same table drives point evaluation (torch) and interval enclosures
(`certify.interval_rules`), so whatever parses can also be evaluated and enclosed;
`certify.domain` checks that it is defined and smooth on the box.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import sympy
import torch

from certify.errors import SpecError
from certify.parse import FUNCTION_NAMES, parse_expression

__all__ = ["FUNCTIONS", "DERIVED_FUNCTIONS", "parse_expression", "evaluate",
           "compile_torch", "compile_torch_rows", "function_name", "TORCH"]

#: Whitelisted functions: name -> (sympy function, torch point function).
FUNCTIONS: dict[str, tuple[Any, Callable[[torch.Tensor], torch.Tensor]]] = {
    "sin": (sympy.sin, torch.sin),
    "cos": (sympy.cos, torch.cos),
    "tan": (sympy.tan, torch.tan),
    "exp": (sympy.exp, torch.exp),
    "log": (sympy.log, torch.log),
    "sqrt": (sympy.sqrt, torch.sqrt),
    "tanh": (sympy.tanh, torch.tanh),
    "abs": (sympy.Abs, torch.abs),
}

assert set(FUNCTIONS) == set(FUNCTION_NAMES), "the parser and the evaluator list the same functions"

#: Functions that only appear in derivatives of whitelisted ones (never parsed from text).
DERIVED_FUNCTIONS: dict[str, tuple[Any, Callable[[torch.Tensor], torch.Tensor]]] = {
    "sign": (sympy.sign, torch.sign),  # d/dx abs(x)
}

#: Named constants accepted in expressions.
CONSTANTS: dict[str, Any] = {"pi": sympy.pi}

_SYMPY_TO_NAME = {
    sympy.sin: "sin", sympy.cos: "cos", sympy.tan: "tan", sympy.exp: "exp",
    sympy.log: "log", sympy.tanh: "tanh", sympy.Abs: "abs", sympy.sign: "sign",
}


class Algebra(Protocol):
    """Arithmetic on some value type (tensors, intervals) used by `evaluate`."""

    def const(self, value: float, like: Any) -> Any: ...
    def add(self, a: Any, b: Any) -> Any: ...
    def mul(self, a: Any, b: Any) -> Any: ...
    def pow_int(self, a: Any, k: int) -> Any: ...
    def pow_real(self, a: Any, e: float) -> Any: ...
    def func(self, name: str, a: Any) -> Any: ...


def function_name(expr: sympy.Expr) -> str:
    """Whitelist name of a sympy function node (or raise naming it)."""
    name = _SYMPY_TO_NAME.get(expr.func)
    if name is None:
        raise SpecError(f"no evaluation rule for {expr.func} (in {expr}); the checks need f and h "
                        "twice differentiable")
    return name


def evaluate(expr: sympy.Expr, env: Mapping[sympy.Symbol, Any], algebra: Algebra, like: Any) -> Any:
    """Evaluate a sympy tree bottom-up with the operations of `algebra`.

    `env` maps each symbol to a value of the algebra; constants are broadcast `like` it.
    """
    if expr.is_Symbol:
        return env[expr]
    if expr.is_Number or expr.is_NumberSymbol:
        return algebra.const(float(expr), like)
    if expr.is_Add:
        args = [evaluate(a, env, algebra, like) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = algebra.add(out, a)
        return out
    if expr.is_Mul:
        args = [evaluate(a, env, algebra, like) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = algebra.mul(out, a)
        return out
    if expr.is_Pow:
        base, exponent = expr.args
        b = evaluate(base, env, algebra, like)
        if exponent.is_Integer:
            return algebra.pow_int(b, int(exponent))
        if exponent.is_Number:
            return algebra.pow_real(b, float(exponent))
        # general a**b = exp(b * log(a))
        e = evaluate(exponent, env, algebra, like)
        return algebra.func("exp", algebra.mul(e, algebra.func("log", b)))
    if isinstance(expr, sympy.Function) and len(expr.args) == 1:
        return algebra.func(function_name(expr), evaluate(expr.args[0], env, algebra, like))
    raise SpecError(f"cannot evaluate expression node {expr.func.__name__}: {expr}")


Compiled = Callable[[Sequence[torch.Tensor]], "torch.Tensor | float"]
CompiledRows = Callable[[torch.Tensor], torch.Tensor]


class _Emitter:
    """Straight-line Python source for sympy trees, one temporary per operation.

    The operations are exactly those of a bottom-up walk (the same as `evaluate` with
    `TORCH`, except that constant subtrees are folded to Python floats): sums and products
    folded left to right, x**2 as x*x, x**k (k < 0) as 1/x**-k, functions from `FUNCTIONS`.
    A sub-expression that occurs twice is computed once (the same operations on the same
    inputs give the same floats, so this changes no value). The source holds only generated
    names (columns c0.., temporaries t0.., constants k.. and functions F.. bound in its
    namespace): no text of the spec reaches `exec`.
    """

    def __init__(self, symbols: Sequence[sympy.Symbol]) -> None:
        self.index = {s: i for i, s in enumerate(symbols)}
        self.lines: list[str] = []
        self.names: dict[str, Any] = {"torch": torch}
        self.memo: dict[sympy.Expr, str] = {}

    def _bind(self, prefix: str, value: Any) -> str:
        name = f"{prefix}{len(self.names)}"
        self.names[name] = value
        return name

    def _temp(self, code: str) -> str:
        name = f"t{len(self.lines)}"
        self.lines.append(f"{name} = {code}")
        return name

    def emit(self, e: sympy.Expr) -> str:
        """The name holding e's value (a tensor, or a Python float for a constant)."""
        if e not in self.memo:
            self.memo[e] = self._emit(e)
        return self.memo[e]

    def _emit(self, e: sympy.Expr) -> str:
        if e.is_Symbol:
            return f"c{self.index[e]}"
        if not e.free_symbols:
            return self._bind("k", float(e))
        if e.is_Add or e.is_Mul:
            parts = [self.emit(a) for a in e.args]
            op = " + " if e.is_Add else " * "
            out = parts[0]
            for part in parts[1:]:
                out = self._temp(out + op + part)
            return out
        if e.is_Pow:
            base, exponent = e.args
            b = self.emit(base)
            if exponent.is_Integer:
                k = int(exponent)
                if k == 2:
                    return self._temp(f"{b} * {b}")
                return self._temp(f"{b} ** {k}" if k >= 0 else f"1.0 / {b} ** {-k}")
            if exponent.is_Number:
                return self._temp(f"{b} ** {self._bind('k', float(exponent))}")
            ex = self.emit(exponent)
            return self._temp(f"torch.exp({ex} * torch.log({b}))")
        if isinstance(e, sympy.Function) and len(e.args) == 1:
            name = function_name(e)
            fn = (FUNCTIONS if name in FUNCTIONS else DERIVED_FUNCTIONS)[name][1]
            a = self.emit(e.args[0])
            return self._temp(f"{self._bind('F', fn)}({a})")
        raise SpecError(f"cannot evaluate expression node {e.func.__name__}: {e}")

    def function(self, header: str, unpack: str, result: str, label: str) -> Callable:
        body = "\n".join(f"    {line}" for line in [unpack, *self.lines, f"return {result}"])
        namespace = dict(self.names)
        exec(compile(f"def _fn({header}):\n{body}\n", f"<certify: {label}>", "exec"),
             namespace)
        return namespace["_fn"]


def _columns(count: int) -> str:
    return ", ".join(f"c{i}" for i in range(count)) + ("," if count == 1 else "")


def compile_torch(expr: sympy.Expr, symbols: Sequence[sympy.Symbol]) -> Compiled:
    """A function evaluating `expr` on tensors (one per symbol), generated once from the tree.

    No tree walk per call (the simulation evaluates f and h tens of thousands of times on
    small batches). Constant subtrees are folded to Python floats; the result may be a float
    for a constant expression. See `compile_torch_rows` for whole vectors of expressions.
    """
    em = _Emitter(symbols)
    result = em.emit(expr)
    return em.function("v", f"{_columns(len(symbols))} = v" if symbols else "pass", result,
                       str(expr)[:60])


def compile_torch_rows(exprs: Sequence[sympy.Expr], symbols: Sequence[sympy.Symbol],
                       label: str = "expressions") -> CompiledRows:
    """One generated function x [B, len(symbols)] -> [B, len(exprs)]: every expression at
    every row, columns stacked (a constant expression fills its column).

    The same operations as `compile_torch` on each expression (so the same floats), in one
    Python function: the columns are unpacked once and shared sub-expressions computed once,
    which matters for the many small calls of the simulation and the grid sweeps.
    """
    em = _Emitter(symbols)
    results = []
    for e in exprs:
        name = em.emit(e)
        # a constant expression is a float (name "k..."): it fills a column like x's first
        results.append(f"torch.full_like(c0, {name})" if name.startswith("k") else name)
    return em.function("x", f"{_columns(len(symbols))} = x.unbind(1)",
                       f"torch.stack([{', '.join(results)}], dim=-1)", label)


class TorchAlgebra:
    """Point evaluation on batched float tensors."""

    def const(self, value: float, like: torch.Tensor) -> torch.Tensor:
        return torch.full_like(like, value)

    def add(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a + b

    def mul(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a * b

    def pow_int(self, a: torch.Tensor, k: int) -> torch.Tensor:
        if k >= 0:
            return a**k
        return 1.0 / a ** (-k)

    def pow_real(self, a: torch.Tensor, e: float) -> torch.Tensor:
        return a**e

    def func(self, name: str, a: torch.Tensor) -> torch.Tensor:
        table = FUNCTIONS if name in FUNCTIONS else DERIVED_FUNCTIONS
        return table[name][1](a)


TORCH = TorchAlgebra()
