"""The spec expression parser: text -> a sympy tree built EXACTLY as written, within limits.

A spec is untrusted input. The text is parsed by Python's `ast` (never evaluated), checked
against a whitelist (numbers, declared names, `pi`, `+ - * / **`, unary minus/plus and the
functions of `certify.spec.expr.FUNCTIONS`) and against size limits (`LIMITS`: characters, nodes,
depth, literal and exponent sizes), and only then handed to sympy, node by node with
`evaluate=False`: `sqrt(x)**2` stays a square of a square root and `(x - a)/(x - a)` stays a
quotient, so that `certify.spec.domain` can check every sub-expression over the box before
anything is simplified away.

Constant sub-expressions (no state in them) are folded, but only after a guarded float64
evaluation shows that they are finite real numbers of moderate size: `9**9**9`, `1/0`,
`(-1)**0.5` or `log(-1)` are refused in microseconds instead of hanging or turning complex.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping
from dataclasses import dataclass

import sympy

from certify.errors import SpecError


@dataclass(frozen=True)
class ParseLimits:
    """What one expression may contain (each one is a refusal with exit 2 when exceeded)."""

    max_chars: int = 8000
    max_nodes: int = 2000
    max_depth: int = 64
    max_int: int = 2**53  # integer literals beyond this are not exact doubles
    max_exponent: float = 100.0  # |k| of a constant exponent of a state expression
    max_constant: float = 1e300  # folded constants beyond this are refused (overflow ahead)


LIMITS = ParseLimits()
_MAX_CONSTANT_EXPONENT = 1100  # a double's range: 2**1100 overflows, 2**-1100 is 0

#: Function name -> (sympy constructor taking evaluate=, float function for folding).
_SYMPY = {
    "sin": (sympy.sin, math.sin), "cos": (sympy.cos, math.cos), "tan": (sympy.tan, math.tan),
    "exp": (sympy.exp, math.exp), "log": (sympy.log, math.log), "tanh": (sympy.tanh, math.tanh),
    "abs": (sympy.Abs, abs), "sqrt": (None, math.sqrt),
}
_CONSTANTS = {"pi": (sympy.pi, math.pi)}
FUNCTION_NAMES = tuple(sorted(_SYMPY))
#: Refused with the reason spelled out (abs is allowed only where it is smooth:
# certify.spec.domain).
_NON_SMOOTH = {"sign", "floor", "ceil", "round", "max", "min", "heaviside", "Heaviside", "mod"}

_KINDS = {
    ast.Attribute: "attribute access", ast.Subscript: "subscript", ast.Lambda: "lambda",
    ast.Compare: "comparison", ast.BoolOp: "boolean operator", ast.IfExp: "conditional",
    ast.List: "list", ast.Tuple: "tuple", ast.Dict: "dict", ast.JoinedStr: "string",
    ast.NamedExpr: "assignment",
}


def _describe(node: ast.AST) -> str:
    try:
        text = ast.unparse(node)
    except Exception:  # pragma: no cover - unparse handles every parsed node
        return type(node).__name__
    return f"'{text if len(text) <= 60 else text[:57] + '...'}'"


_ADDITIVE = (ast.Add, ast.Sub)
_MULTIPLICATIVE = (ast.Mult, ast.Div)


def _chain_kind(op: ast.operator) -> tuple[type, ...] | None:
    for kind in (_ADDITIVE, _MULTIPLICATIVE):
        if isinstance(op, kind):
            return kind
    return None


def _continues_chain(parent: ast.AST, child: ast.AST) -> bool:
    """child is the left operand of parent in one sum (or one product): a + b + c is a flat
    sum of three terms, not a nesting of depth three."""
    if not (isinstance(parent, ast.BinOp) and isinstance(child, ast.BinOp)
            and child is parent.left):
        return False
    kind = _chain_kind(parent.op)
    return kind is not None and isinstance(child.op, kind)


def _depth(node: ast.AST) -> int:
    """Nesting depth of an expression, sums and products counted flat (iterative: a deep
    tree cannot overflow the stack here)."""
    best, stack = 0, [(node, 1)]
    while stack:
        cur, d = stack.pop()
        best = max(best, d)
        stack.extend((child, d if _continues_chain(cur, child) else d + 1)
                     for child in ast.iter_child_nodes(cur))
    return best


def _tree(text: str, prefix: str, limits: ParseLimits) -> ast.Expression:
    if not isinstance(text, str):
        raise SpecError(f"{prefix}expression must be a string; got {type(text).__name__}")
    if not text.strip():
        raise SpecError(f"{prefix}expression is empty")
    if len(text) > limits.max_chars:
        raise SpecError(f"{prefix}expression is {len(text)} characters long; the limit is "
                        f"{limits.max_chars} (split the model or simplify it)")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise SpecError(f"{prefix}cannot parse {text!r}: {exc.msg}") from None
    except (RecursionError, MemoryError, ValueError) as exc:
        raise SpecError(f"{prefix}cannot parse the expression: {type(exc).__name__} "
                        "(too deeply nested or too large)") from None
    nodes = sum(1 for node in ast.walk(tree) if isinstance(node, ast.expr))
    if nodes > limits.max_nodes:
        raise SpecError(f"{prefix}expression has {nodes} terms and operations; the limit is "
                        f"{limits.max_nodes}")
    depth = _depth(tree)
    if depth > limits.max_depth:
        raise SpecError(f"{prefix}expression is nested {depth} deep; the limit is "
                        f"{limits.max_depth}")
    return tree


def _fold(op: str, *args: float) -> float:
    """A guarded float64 operation: raises ArithmeticError/ValueError where the real result
    does not exist or does not fit."""
    if op == "+":
        out = args[0] + args[1]
    elif op == "*":
        out = args[0] * args[1]
    elif op == "/":
        out = args[0] / args[1]
    elif op == "**":
        out = args[0] ** args[1]
    else:
        out = _SYMPY[op][1](args[0])
    if isinstance(out, complex):
        raise ValueError("not a real number")
    return float(out)


def parse_expression(text: str, names: Mapping[str, sympy.Symbol], where: str = "",
                     limits: ParseLimits = LIMITS,
                     sources: dict[sympy.Expr, str] | None = None) -> sympy.Expr:
    """Parse `text` into an unevaluated sympy tree over the declared `names`.

    Raises `SpecError` (one line, prefixed by `where`, e.g. ``"spec vdp.toml: f[1]"``) naming
    the offending construct for anything outside the whitelist or the limits. The tree is
    not checked against a box here: that is `certify.spec.domain.check_domain`. `sources`, when
    given, receives the source text of every sub-tree (for messages that quote the user).
    """
    prefix = f"{where}: " if where else ""
    tree = _tree(text, prefix, limits)

    def refuse_constant(node: ast.AST, why: str) -> SpecError:
        return SpecError(f"{prefix}constant {_describe(node)} {why}")

    def build(node: ast.AST) -> tuple[sympy.Expr, float | None]:
        """(sympy tree, float value when the sub-expression is constant, else None); notes
        the source text of the sub-tree in `sources`."""
        out = build_node(node)
        if sources is not None and not isinstance(node, ast.Expression):
            sources.setdefault(out[0], ast.unparse(node))
        return out

    def build_node(node: ast.AST) -> tuple[sympy.Expr, float | None]:
        if isinstance(node, ast.Expression):
            return build(node.body)
        if isinstance(node, ast.Constant):
            value = node.value
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise SpecError(f"{prefix}constant {_describe(node)} is not a real number")
            if isinstance(value, int):
                if abs(value) > limits.max_int:
                    raise refuse_constant(node, f"is larger than {limits.max_int} (not an "
                                          "exact double)")
                return sympy.Integer(value), float(value)
            if not math.isfinite(value):
                raise SpecError(f"{prefix}constant {_describe(node)} is not finite")
            return sympy.Float(value), value  # the double as written, exactly (53 bits)
        if isinstance(node, ast.Name):
            if node.id in names:
                return names[node.id], None
            if node.id in _CONSTANTS:
                return _CONSTANTS[node.id]
            raise SpecError(f"{prefix}uses unknown name '{node.id}'")
        if isinstance(node, ast.UnaryOp):
            operand, value = build(node.operand)
            if isinstance(node.op, ast.USub):
                if value is not None:
                    return constant(node, -operand, -value)
                return sympy.Mul(sympy.Integer(-1), operand, evaluate=False), None
            if isinstance(node.op, ast.UAdd):
                return operand, value
            raise SpecError(f"{prefix}operator in {_describe(node)} is not allowed")
        if isinstance(node, ast.BinOp):
            return binop(node)
        if isinstance(node, ast.Call):
            return call(node)
        kind = next((v for k, v in _KINDS.items() if isinstance(node, k)), type(node).__name__)
        raise SpecError(f"{prefix}{kind} {_describe(node)} is not allowed")

    def constant(node: ast.AST, expr: sympy.Expr, value: float) -> tuple[sympy.Expr, float]:
        if not math.isfinite(value) or abs(value) > limits.max_constant:
            raise refuse_constant(node, f"evaluates to {value:.3g}, beyond "
                                  f"{limits.max_constant:.0e}")
        return expr, value

    def guarded(node: ast.AST, op: str, *args: float) -> float:
        try:
            return _fold(op, *args)
        except ZeroDivisionError:
            raise refuse_constant(node, "divides by zero") from None
        except (OverflowError, ValueError, ArithmeticError):
            raise refuse_constant(node, "has no finite real value") from None

    def binop(node: ast.BinOp) -> tuple[sympy.Expr, float | None]:
        op = node.op
        if not isinstance(op, (*_ADDITIVE, *_MULTIPLICATIVE, ast.Pow)):
            raise SpecError(f"{prefix}operator in {_describe(node)} is not allowed "
                            "(use + - * / **)")
        if isinstance(op, ast.Pow):
            return power(node)
        # a sum or product of many terms: walk its left spine iteratively (one stack frame
        # per nesting level, not per term) and build one flat unevaluated Add / Mul
        kind = _chain_kind(op)
        spine, cur = [], node
        while isinstance(cur, ast.BinOp) and isinstance(cur.op, kind):
            spine.append(cur)
            cur = cur.left
        acc, vacc = build(cur)
        for step in reversed(spine):
            b, vb = build(step.right)
            acc, vacc = combine(step, acc, vacc, b, vb)
        return acc, vacc

    def combine(node: ast.BinOp, a: sympy.Expr, va: float | None, b: sympy.Expr,
                vb: float | None) -> tuple[sympy.Expr, float | None]:
        """a (op) b for + - * /, folded when both are constant, else flat and unevaluated."""
        op = node.op
        if va is not None and vb is not None:  # constant: fold after the float guard
            if isinstance(op, ast.Add):
                return constant(node, a + b, guarded(node, "+", va, vb))
            if isinstance(op, ast.Sub):
                return constant(node, a - b, guarded(node, "+", va, -vb))
            if isinstance(op, ast.Mult):
                return constant(node, a * b, guarded(node, "*", va, vb))
            return constant(node, a / b, guarded(node, "/", va, vb))
        if isinstance(op, _ADDITIVE):
            term = b if isinstance(op, ast.Add) else sympy.Mul(sympy.Integer(-1), b,
                                                               evaluate=False)
            left = a.args if (a.is_Add and va is None) else (a,)
            return sympy.Add(*left, term, evaluate=False), None
        factor = b if isinstance(op, ast.Mult) else sympy.Pow(b, sympy.Integer(-1),
                                                              evaluate=False)
        left = a.args if (a.is_Mul and va is None) else (a,)
        return sympy.Mul(*left, factor, evaluate=False), None

    def power(node: ast.BinOp) -> tuple[sympy.Expr, float | None]:
        (a, va), (b, vb) = build(node.left), build(node.right)
        if va is not None and vb is not None:
            if abs(vb) > _MAX_CONSTANT_EXPONENT:  # exact sympy powers would take forever
                raise refuse_constant(node, f"has an exponent of {vb:.3g} (limit "
                                      f"{_MAX_CONSTANT_EXPONENT})")
            return constant(node, a**b, guarded(node, "**", va, vb))
        if vb is not None and abs(vb) > limits.max_exponent:
            raise SpecError(f"{prefix}exponent {_describe(node.right)} = {vb:.3g} in "
                            f"{_describe(node)} is beyond +-{limits.max_exponent:g}")
        return sympy.Pow(a, b, evaluate=False), None

    def call(node: ast.Call) -> tuple[sympy.Expr, float | None]:
        allowed = ", ".join(sorted(_SYMPY))
        if not isinstance(node.func, ast.Name):
            raise SpecError(f"{prefix}call {_describe(node)} is not allowed "
                            f"(allowed functions: {allowed})")
        fname = node.func.id
        if fname not in _SYMPY:
            why = (": it is not smooth and the checks need f and h twice differentiable"
                   if fname in _NON_SMOOTH else "")
            raise SpecError(f"{prefix}unknown function '{fname}' in {_describe(node)}{why} "
                            f"(allowed: {allowed})")
        if node.keywords or len(node.args) != 1:
            raise SpecError(f"{prefix}function '{fname}' takes exactly one argument "
                            f"in {_describe(node)}")
        arg, value = build(node.args[0])
        if value is not None:
            folded = guarded(node, fname, value)
            exact = sympy.sqrt(arg) if fname == "sqrt" else _SYMPY[fname][0](arg)
            return constant(node, exact, folded)
        if fname == "sqrt":
            return sympy.Pow(arg, sympy.Rational(1, 2), evaluate=False), None
        return _SYMPY[fname][0](arg, evaluate=False), None

    expr, _ = build(tree)
    if expr.atoms(sympy.I, sympy.zoo, sympy.nan, sympy.oo):
        raise SpecError(f"{prefix}{text!r} has a non-real value")
    return expr
