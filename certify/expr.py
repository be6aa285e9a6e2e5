"""The function table and the evaluation of spec expression trees (torch, intervals).

Parsing lives in `certify.parse` (re-exported here as `parse_expression`): only numbers,
declared names, `+ - * / **`, unary minus/plus and the functions of `FUNCTIONS` are
accepted. The same table drives point evaluation (torch) and interval enclosures
(`certify.intervals`), so whatever parses can also be evaluated and enclosed;
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
           "compile_torch", "function_name", "TORCH"]

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


def compile_torch(expr: sympy.Expr, symbols: Sequence[sympy.Symbol]) -> Compiled:
    """A closure evaluating `expr` on tensors (one per symbol), built once from the tree.

    Same operations as `evaluate` with `TORCH`, without re-walking the tree on every call
    (the simulation calls f and h tens of thousands of times on small batches). Constant
    subtrees are folded to Python floats; the result may be a float for a constant expression.
    """
    index = {s: i for i, s in enumerate(symbols)}

    def build(e: sympy.Expr) -> Compiled:
        if e.is_Symbol:
            i = index[e]
            return lambda v: v[i]
        if not e.free_symbols:
            c = float(e)
            return lambda v: c
        if e.is_Add or e.is_Mul:
            parts = [build(a) for a in e.args]
            add = e.is_Add

            def fold(v: Sequence[torch.Tensor]) -> torch.Tensor | float:
                out = parts[0](v)
                for part in parts[1:]:
                    out = out + part(v) if add else out * part(v)
                return out

            return fold
        if e.is_Pow:
            base, exponent = e.args
            b = build(base)
            if exponent.is_Integer:
                k = int(exponent)
                if k == 2:
                    return lambda v: b(v) * b(v)
                return (lambda v: b(v) ** k) if k >= 0 else (lambda v: 1.0 / b(v) ** (-k))
            if exponent.is_Number:
                r = float(exponent)
                return lambda v: b(v) ** r
            ex = build(exponent)
            return lambda v: torch.exp(ex(v) * torch.log(b(v)))
        if isinstance(e, sympy.Function) and len(e.args) == 1:
            name = function_name(e)
            fn = (FUNCTIONS if name in FUNCTIONS else DERIVED_FUNCTIONS)[name][1]
            a = build(e.args[0])
            return lambda v: fn(a(v))
        raise SpecError(f"cannot evaluate expression node {e.func.__name__}: {e}")

    return build(expr)


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
