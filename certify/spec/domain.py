"""Domain check of a spec: every sub-expression defined and smooth over the whole box.

The checks need f and h twice continuously differentiable on X. The parser
(`certify.spec.parse`) keeps the tree exactly as written; here every node is enclosed over
sub-boxes of X with the interval rules of `certify.arith.intervals` (outward rounding), and a node
is refused where it may be undefined or non-smooth:

- a division (negative integer power) whose denominator may be 0;
- a non-integer power (sqrt included) or a power with a state-dependent exponent whose base
  may be <= 0 (at 0 such powers are not differentiable);
- log of an argument that may be <= 0; tan of an argument that may reach a pole;
- abs of an argument that may be 0 (abs is smooth only where its argument keeps one sign;
  there it is resolved to +u or -u before differentiation);
- any enclosure that is NaN or infinite (overflow).

An interval enclosure over a big box over-approximates, so flagged sub-boxes are bisected
(widest side first) up to a budget; only what stays flagged is refused, with one line naming
the expression, the offending sub-expression and the part of the box where it happens. A
refusal can be conservative (a sub-expression that is defined but whose enclosure cannot
show it within the budget); an acceptance is sound.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import sympy
import torch

from certify.arith.intervals import Interval, const_interval, imul, ipow_int, ipow_real
from certify.errors import SpecError
from certify.spec.interval_rules import contains_point, enclose_function

MAX_ROUNDS = 40  # bisection rounds
MAX_BOXES = 4096  # flagged sub-boxes kept per round

_F64 = torch.float64


@dataclass
class _Issue:
    mask: torch.Tensor  # [B] sub-boxes where the node may be undefined / non-smooth
    certain: torch.Tensor  # [B] sub-boxes where it surely is (no refinement can help)
    reason: str


class _Walker:
    """Encloses a tree over a batch of boxes and records every domain issue."""

    def __init__(self, env: dict[sympy.Symbol, Interval],
                 sources: dict[sympy.Expr, str] | None = None) -> None:
        self.env = env
        self.sources = sources or {}
        self.issues: list[_Issue] = []
        self.abs_sign: dict[sympy.Expr, torch.Tensor] = {}
        any_iv = next(iter(env.values()))
        self.like = any_iv.lo

    def flag(self, mask: torch.Tensor, reason: str, certain: torch.Tensor | None = None) -> None:
        if bool(mask.any()):
            self.issues.append(_Issue(mask, mask & certain if certain is not None
                                      else torch.zeros_like(mask), reason))

    def name(self, e: sympy.Expr) -> str:
        """How the user wrote sub-expression e (sympy's short form if unknown)."""
        return _short(self.sources.get(e) or sympy.sstr(e, full_prec=False))

    def walk(self, e: sympy.Expr) -> Interval:
        out = self._walk(e)
        bad = ~(torch.isfinite(out.lo) & torch.isfinite(out.hi))
        self.flag(bad, f"'{self.name(e)}' is not finite (overflow or undefined)")
        # keep going with a harmless value where it failed, so that parents still run
        return Interval(torch.where(bad, torch.zeros_like(out.lo), out.lo),
                        torch.where(bad, torch.zeros_like(out.hi), out.hi))

    def _walk(self, e: sympy.Expr) -> Interval:
        if e.is_Symbol:
            return self.env[e]
        if not e.free_symbols:
            value = float(e)
            return const_interval(value, self.like)
        if e.is_Add or e.is_Mul:
            parts = [self.walk(a) for a in e.args]
            out = parts[0]
            for p in parts[1:]:
                out = out + p if e.is_Add else imul(out, p)
            return out
        if e.is_Pow:
            base, ex = e.args
            b = self.walk(base)
            if ex.is_Integer:
                k = int(ex)
                if k < 0:
                    zero = (b.lo <= 0) & (b.hi >= 0)
                    self.flag(zero, f"division by '{self.name(base)}', which can be 0",
                              (b.lo == 0) & (b.hi == 0))
                    b = _away_from_zero(b, zero)
                return ipow_int(b, k)
            if not ex.free_symbols:
                self.flag(b.lo <= 0, f"'{self.name(base)}' raised to the non-integer power "
                          f"{self.name(ex)} can be <= 0 (undefined or not differentiable "
                          "there)", b.hi <= 0)
                return ipow_real(_positive(b), float(ex))
            self.flag(b.lo <= 0, f"'{self.name(base)}' raised to the power '{self.name(ex)}' "
                      "can be <= 0 (a state-dependent exponent needs a positive base)",
                      b.hi <= 0)
            x = self.walk(ex)
            return enclose_function("exp", imul(x, enclose_function("log", _positive(b))))
        if isinstance(e, sympy.Function) and len(e.args) == 1:
            name = _NAMES.get(e.func)
            if name is None:
                raise SpecError(f"function {e.func} is not supported")
            a = self.walk(e.args[0])
            if name == "log":
                self.flag(a.lo <= 0, f"log of '{self.name(e.args[0])}', which can be <= 0",
                          a.hi <= 0)
                a = _positive(a)
            elif name == "tan":
                pole = contains_point(a, math.pi / 2, math.pi) | ((a.hi - a.lo) >= math.pi)
                self.flag(pole, f"tan of '{self.name(e.args[0])}', which can reach a pole")
            elif name == "abs":
                zero = (a.lo <= 0) & (a.hi >= 0)
                self.flag(zero, f"abs of '{self.name(e.args[0])}', which can be 0: abs is not "
                          "differentiable there and the checks need f and h twice "
                          "differentiable (use abs only where its argument keeps one sign)",
                          (a.lo == 0) & (a.hi == 0))
                self.abs_sign[e] = torch.where(a.lo > 0, 1, torch.where(a.hi < 0, -1, 0))
            return enclose_function(name, a)
        raise SpecError(f"cannot check expression node {e.func.__name__}: {e}")


_NAMES = {sympy.sin: "sin", sympy.cos: "cos", sympy.tan: "tan", sympy.exp: "exp",
          sympy.log: "log", sympy.tanh: "tanh", sympy.Abs: "abs"}


def _positive(a: Interval) -> Interval:
    """The part of `a` above 0 (for enclosing the rest of the tree after a flag)."""
    tiny = torch.full_like(a.lo, 1e-300)
    lo = torch.maximum(a.lo, tiny)
    return Interval(lo, torch.maximum(a.hi, lo))


def _away_from_zero(a: Interval, zero: torch.Tensor) -> Interval:
    one = torch.ones_like(a.lo)
    return Interval(torch.where(zero, one, a.lo), torch.where(zero, one, a.hi))


def _short(text: str, limit: int = 80) -> str:
    """Long expressions are quoted by their start and end (messages stay one short line)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else f"{text[:limit // 2 - 2]} ... {text[-limit // 2 + 3:]}"


def _describe_box(lo: np.ndarray, hi: np.ndarray, names: Sequence[str]) -> str:
    return ", ".join(f"{n} in [{a:.4g}, {b:.4g}]" for n, a, b in zip(names, lo, hi))


def check_domain(exprs: Sequence[sympy.Expr], texts: Sequence[str],
                 symbols: Sequence[sympy.Symbol], box: np.ndarray, where: Sequence[str],
                 sources: dict[sympy.Expr, str] | None = None) -> list[sympy.Expr]:
    """Refuse (SpecError, one line) any expression not defined and smooth on all of `box`.

    `exprs[i]` was parsed from `texts[i]` and is named `where[i]` in messages (e.g.
    "spec s.toml: f[0]"); `sources` maps sub-trees to the text the user wrote. Returns the
    expressions with every abs(u) resolved to u or -u
    (its argument keeps one sign on the box).
    """
    names = [str(s) for s in symbols]
    box = np.asarray(box, dtype=np.float64)
    lo = torch.as_tensor(box[:, 0], dtype=_F64)[None]
    hi = torch.as_tensor(box[:, 1], dtype=_F64)[None]
    width0 = (hi - lo)[0]
    out: list[sympy.Expr] = []
    for expr, text, label in zip(exprs, texts, where):
        blo, bhi = lo, hi
        for _ in range(MAX_ROUNDS):
            walker = _Walker({s: Interval(blo[:, i], bhi[:, i]) for i, s in enumerate(symbols)},
                             sources)
            walker.walk(expr)
            bad = torch.zeros(blo.shape[0], dtype=torch.bool)
            for issue in walker.issues:
                if bool(issue.certain.any()):
                    _refuse(label, text, issue, issue.certain, blo, bhi, names)
                bad |= issue.mask
            if not bool(bad.any()):
                break
            last = (walker, bad, blo, bhi)
            blo, bhi = blo[bad], bhi[bad]
            if blo.shape[0] > MAX_BOXES // 2:
                break
            blo, bhi = _bisect(blo, bhi, width0)
        else:
            bad = torch.ones(1, dtype=torch.bool)
        if bool(bad.any()):
            walker, mask, blo_l, bhi_l = last
            issue = next(i for i in walker.issues if bool(i.mask.any()))
            _refuse(label, text, issue, issue.mask, blo_l, bhi_l, names)
        out.append(_resolve_abs(expr, symbols, box))
    return out


def _bisect(lo: torch.Tensor, hi: torch.Tensor, width0: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Split every box in two along its widest side (relative to the original box)."""
    k = torch.argmax((hi - lo) / width0, dim=1)
    rows = torch.arange(lo.shape[0])
    mid = 0.5 * (lo[rows, k] + hi[rows, k])
    hi1, lo2 = hi.clone(), lo.clone()
    hi1[rows, k] = mid
    lo2[rows, k] = mid
    return torch.cat([lo, lo2]), torch.cat([hi1, hi])


def _refuse(label: str, text: str, issue: _Issue, mask: torch.Tensor, lo: torch.Tensor,
            hi: torch.Tensor, names: Sequence[str]) -> None:
    part_lo = lo[mask].min(0).values.numpy()
    part_hi = hi[mask].max(0).values.numpy()
    raise SpecError(f"{label}: {_short(text)!r} is not defined and smooth on all of the box: "
                    f"{issue.reason}, for {_describe_box(part_lo, part_hi, names)}")


def _resolve_abs(expr: sympy.Expr, symbols: Sequence[sympy.Symbol], box: np.ndarray
                 ) -> sympy.Expr:
    """Replace abs(u) by u or -u: the domain check showed u keeps one sign on the box (it is
    continuous and non-zero on the connected box), so the sign at the centre is the sign."""
    nodes = [a for a in sympy.preorder_traversal(expr) if isinstance(a, sympy.Abs)]
    if not nodes:
        return expr
    centre = torch.as_tensor(box.mean(1), dtype=_F64)[None]
    walker = _Walker({s: Interval(centre[:, i], centre[:, i]) for i, s in enumerate(symbols)})
    walker.walk(expr)
    repl = {}
    for node in nodes:
        sign = int(walker.abs_sign.get(node, torch.zeros(1))[0])
        if sign == 0:  # pragma: no cover - excluded by the domain check
            raise SpecError(f"abs of '{node.args[0]}' has no certain sign at the box centre")
        arg = node.args[0]
        repl[node] = arg if sign > 0 else sympy.Mul(sympy.Integer(-1), arg, evaluate=False)
    return _resolve_nested(expr, repl)


def _resolve_nested(expr: sympy.Expr, repl: dict) -> sympy.Expr:
    if isinstance(expr, sympy.Abs) and expr in repl:
        inner = _resolve_nested(expr.args[0], repl)
        return inner if repl[expr] == expr.args[0] else sympy.Mul(sympy.Integer(-1), inner,
                                                                   evaluate=False)
    if not expr.args:
        return expr
    return expr.func(*[_resolve_nested(a, repl) for a in expr.args], evaluate=False)
