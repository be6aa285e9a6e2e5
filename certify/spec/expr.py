"""The function table and the evaluation of spec expression trees (torch, intervals).

Parsing lives in `certify.spec.parse` (re-exported here as `parse_expression`): only numbers,
declared names, `+ - * / **`, unary minus/plus and the functions of `FUNCTIONS` are
accepted. The same table drives point evaluation (torch) and interval enclosures
(`certify.spec.interval_rules`), so whatever parses can also be evaluated and enclosed;
`certify.spec.domain` checks that it is defined and smooth on the box.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import sympy
import torch

from certify.errors import SpecError
from certify.spec.parse import FUNCTION_NAMES, parse_expression

__all__ = ["FUNCTIONS", "DERIVED_FUNCTIONS", "parse_expression", "evaluate",
           "compile_torch", "compile_torch_rows", "compile_numpy_rows", "folded_constants",
           "function_name", "TORCH"]

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

#: The same functions on NumPy arrays, for the simulation's tape (`compile_numpy_rows`):
#: NumPy's per-call cost is a quarter of torch's on the small batches of an integrator step.
NUMPY_FUNCTIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "sin": np.sin, "cos": np.cos, "tan": np.tan, "exp": np.exp, "log": np.log,
    "sqrt": np.sqrt, "tanh": np.tanh, "abs": np.abs, "sign": np.sign,
}

assert set(NUMPY_FUNCTIONS) == set(FUNCTIONS) | set(DERIVED_FUNCTIONS), \
    "every function has a NumPy form"

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


Slot = int  # index into the value list of one evaluation: columns, constants, temporaries
Ref = tuple[str, int]  # ("col" | "const" | "step", index) while the tape is being built
#: One operation: (function, slot of the first operand, slot of the second or -1 if unary).
Step = tuple[Callable[..., Any], Slot, Slot]


def _exp_log_constant_base(exponent: torch.Tensor, base: float) -> torch.Tensor:
    """base**exponent for a constant base, as exp(exponent * log(base)) (as `evaluate`)."""
    return torch.exp(exponent * torch.log(torch.full_like(exponent, base)))


def _exp_log_constant_base_np(exponent: np.ndarray, base: float) -> np.ndarray:
    """`_exp_log_constant_base` on NumPy arrays."""
    return np.exp(exponent * np.log(np.full_like(exponent, base)))


@dataclass(frozen=True)
class _Library:
    """The array library a tape calls: functions by name and the few other primitives."""

    functions: Mapping[str, Callable[..., Any]]
    exp_log_constant_base: Callable[..., Any]
    full_like: Callable[..., Any]

    def func(self, name: str) -> Callable[..., Any]:
        return self.functions[name]


_TORCH_LIBRARY = _Library({name: fn for table in (FUNCTIONS, DERIVED_FUNCTIONS)
                           for name, (_, fn) in table.items()},
                          _exp_log_constant_base, torch.full_like)
_NUMPY_LIBRARY = _Library(NUMPY_FUNCTIONS, _exp_log_constant_base_np, np.full_like)


def _negated(term: sympy.Expr) -> sympy.Expr | None:
    """u when `term` is -1 * u with u not constant (sympy's form of a subtracted term)."""
    if term.is_Mul and len(term.args) == 2 and term.args[0] == -1 \
            and term.args[1].free_symbols:
        return term.args[1]
    return None


class _Tape:
    """A straight-line program for sympy trees, built once from the parsed tree: a list of
    steps (function, operand slots) that `compile_torch*` run in order. No code generation.

    The operations are exactly those of a bottom-up walk (the same as `evaluate` with
    `TORCH`, except that constant subtrees are folded to Python floats): sums and products
    folded left to right, x**2 as x*x, x**k (k < 0) as 1/x**-k, a**b (b not a number) as
    exp(b * log(a)), functions from `FUNCTIONS`; a later term -1 * u of a sum is subtracted
    (s + (-1.0 * u) and s - u are the same float: negation is exact). A sub-expression that
    occurs twice is computed once (the same operations on the same inputs give the same
    floats, so this changes no value). The steps call builtins (`operator.add`, `torch.sin`,
    ...) directly, so a step costs one C call and no Python frame. A run's value list holds
    the input columns, then the folded constants (Python numbers), then one value per step.
    """

    def __init__(self, symbols: Sequence[sympy.Symbol], library: _Library = _TORCH_LIBRARY
                 ) -> None:
        self.lib = library
        self.index = {s: i for i, s in enumerate(symbols)}
        self.columns = len(symbols)
        self.constants: list[float | int] = []
        self.ops: list[tuple[Callable[..., Any], Ref, Ref | None]] = []
        self.memo: dict[sympy.Expr, Ref] = {}

    def _const(self, value: float | int) -> Ref:
        self.constants.append(value)
        return ("const", len(self.constants) - 1)

    def _op(self, fn: Callable[..., Any], a: Ref, b: Ref | None = None) -> Ref:
        self.ops.append((fn, a, b))
        return ("step", len(self.ops) - 1)

    def emit(self, e: sympy.Expr) -> Ref:
        """The reference holding e's value (a tensor, or a Python float for a constant)."""
        if e not in self.memo:
            self.memo[e] = self._emit(e)
        return self.memo[e]

    def _emit(self, e: sympy.Expr) -> Ref:
        if e.is_Symbol:
            return ("col", self.index[e])
        if not e.free_symbols:
            return self._const(float(e))
        if e.is_Add:
            out = self.emit(e.args[0])
            for term in e.args[1:]:
                negated = _negated(term)
                if negated is not None and term not in self.memo:
                    # out + (-1.0 * u) is out - u exactly (IEEE negation is exact): one step
                    out = self._op(operator.sub, out, self.emit(negated))
                else:
                    out = self._op(operator.add, out, self.emit(term))
            return out
        if e.is_Mul:
            parts = [self.emit(a) for a in e.args]
            out = parts[0]
            for part in parts[1:]:
                out = self._op(operator.mul, out, part)
            return out
        if e.is_Pow:
            base, exponent = e.args
            b = self.emit(base)
            if exponent.is_Integer:
                k = int(exponent)
                if k == 2:
                    return self._op(operator.mul, b, b)
                if k >= 0:
                    return self._op(operator.pow, b, self._const(k))
                # 1.0 / b ** -k: the power, then the quotient
                return self._op(operator.truediv, self._const(1.0),
                                self._op(operator.pow, b, self._const(-k)))
            if exponent.is_Number:
                return self._op(operator.pow, b, self._const(float(exponent)))
            ex = self.emit(exponent)
            if b[0] == "const":
                return self._op(self.lib.exp_log_constant_base, ex, b)
            return self._op(self.lib.func("exp"),
                            self._op(operator.mul, ex, self._op(self.lib.func("log"), b)))
        if isinstance(e, sympy.Function) and len(e.args) == 1:
            return self._op(self.lib.func(function_name(e)), self.emit(e.args[0]))
        raise SpecError(f"cannot evaluate expression node {e.func.__name__}: {e}")

    def as_column(self, ref: Ref) -> Ref:
        """`ref` itself, or for a constant (a float) a step filling a column like x's first."""
        return self._op(self.lib.full_like, ("col", 0), ref) if ref[0] == "const" else ref

    def slot(self, ref: Ref) -> Slot:
        """Where `ref` lives in a run's value list."""
        kind, i = ref
        if kind == "col":
            return i
        if kind == "const":
            return self.columns + i
        return self.columns + len(self.constants) + i

    def program(self) -> tuple[tuple[float | int, ...], tuple[Step, ...]]:
        """The folded constants and the steps with their operands resolved to slots."""
        steps = tuple((fn, self.slot(a), -1 if b is None else self.slot(b))
                      for fn, a, b in self.ops)
        return tuple(self.constants), steps


def compile_torch(expr: sympy.Expr, symbols: Sequence[sympy.Symbol]) -> Compiled:
    """A function evaluating `expr` on tensors (one per symbol), built once from the tree.

    No tree walk per call (the simulation evaluates f and h tens of thousands of times on
    small batches): a tape (`_Tape`) of builtin calls runs the operations in order. Constant
    subtrees are folded to Python floats; the result may be a float for a constant
    expression. See `compile_torch_rows` for whole vectors of expressions.
    """
    tape = _Tape(symbols)
    out = tape.slot(tape.emit(expr))
    constants, steps = tape.program()

    def run(values: Sequence[torch.Tensor]) -> torch.Tensor | float:
        v = [*values, *constants]
        append = v.append
        for fn, a, b in steps:  # one C call per step (the loop is inlined: small batches)
            append(fn(v[a]) if b < 0 else fn(v[a], v[b]))
        return v[out]

    return run


def folded_constants(exprs: Sequence[sympy.Expr], symbols: Sequence[sympy.Symbol]
                     ) -> list[float]:
    """The Python numbers a compiled tape of `exprs` (`compile_torch_rows`) combines with
    the tensors, in tape order: the literal operands and the folded constant sub-expressions
    (exponents included). Each meets tensors of the evaluation's dtype, so each must fit it
    (a float beyond float32's range cannot be applied to a float32 tensor)."""
    tape = _Tape(symbols)
    for e in exprs:
        tape.emit(e)
    return [float(c) for c in tape.constants]


def compile_torch_rows(exprs: Sequence[sympy.Expr], symbols: Sequence[sympy.Symbol],
                       label: str = "expressions") -> CompiledRows:
    """One function x [B, len(symbols)] -> [B, len(exprs)]: every expression at every row,
    columns stacked (a constant expression fills its column).

    The same operations as `compile_torch` on each expression (so the same floats), on one
    tape: the columns are unpacked once and shared sub-expressions computed once, which
    matters for the many small calls of the simulation and the grid sweeps. `label` names
    the expressions in errors.
    """
    return _compile_rows(exprs, symbols, label, _TORCH_LIBRARY,
                         lambda x: x.unbind(1), lambda cols: torch.stack(cols, dim=-1))


def compile_numpy_rows(exprs: Sequence[sympy.Expr], symbols: Sequence[sympy.Symbol],
                       label: str = "expressions"
                       ) -> Callable[[np.ndarray], np.ndarray]:
    """`compile_torch_rows` on float64 NumPy arrays (the simulation's right-hand side: an
    integrator step calls it on a few rows, where NumPy's per-call cost is a quarter of
    torch's). The same tape; the values agree with the torch form up to the libraries'
    last-ulp differences in powers, sin, exp, ... (tested on random specs). The result is
    a transposed view ([B, k], column-major): one copy of the columns, no `np.stack`."""
    return _compile_rows(exprs, symbols, label, _NUMPY_LIBRARY,
                         lambda x: list(x.T), lambda cols: np.array(cols).T)  # [B, k] view


def _compile_rows(exprs: Sequence[sympy.Expr], symbols: Sequence[sympy.Symbol], label: str,
                  library: _Library, unbind: Callable[[Any], Sequence[Any]],
                  stack: Callable[[Sequence[Any]], Any]) -> Callable[[Any], Any]:
    if not symbols:
        raise SpecError(f"{label}: no state variables to evaluate on")
    tape = _Tape(symbols, library)
    refs = [tape.emit(e) for e in exprs]
    outs = [tape.slot(tape.as_column(r)) for r in refs]
    constants, steps = tape.program()
    pick = operator.itemgetter(*outs) if len(outs) > 1 else (lambda v: [v[i] for i in outs])

    def run(x: Any) -> Any:
        v = [*unbind(x), *constants]
        append = v.append
        for fn, a, b in steps:  # one C call per step (the loop is inlined: small batches)
            append(fn(v[a]) if b < 0 else fn(v[a], v[b]))
        return stack(pick(v))

    return run


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
