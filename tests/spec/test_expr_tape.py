"""The compiled spec evaluators (`certify.spec.expr.compile_torch*`): a tape built from the parsed
tree, no code generation; the same floats as the exec-based evaluator it replaced.

`tests/data/expr_reference.json` holds f, h, df/dx and dh/dx of every built-in system at 24
seeded points of X, computed by the exec-based evaluator (certify/expr.py at commit 8443f66)
and written with Python's float repr (exact round trip); the tape must give the same bits.
"""

from __future__ import annotations

import ast
import json
import random
from pathlib import Path

import pytest
import sympy
import torch

from certify.errors import SpecError
from certify.spec.expr import TORCH, compile_torch, compile_torch_rows, evaluate, parse_expression
from certify.spec.system import load_system

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = json.loads((ROOT / "tests" / "data" / "expr_reference.json").read_text())
X, Y, Z = sympy.symbols("x y z", real=True)
NAMES = {"x": X, "y": Y, "z": Z}
FUNCS = ("sin", "cos", "tan", "exp", "log", "sqrt", "tanh", "abs")


def _bits(t: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(t, dtype=torch.float64).contiguous().view(torch.int64)


@pytest.mark.parametrize("name", sorted(REFERENCE))
def test_builtin_systems_match_the_exec_evaluator_bit_for_bit(name: str) -> None:
    system = load_system(name)
    ref = REFERENCE[name]
    pts = torch.tensor(ref["points"], dtype=torch.float64)
    got = {"f": system.f(pts), "h": system.h(pts),
           "jf": system.jac_f(pts).reshape(len(pts), -1),
           "jh": system.jac_h(pts).reshape(len(pts), -1)}
    for key, value in got.items():
        assert torch.equal(_bits(value), _bits(torch.tensor(ref[key], dtype=torch.float64))), key
    fh = system.f_and_h(pts)
    assert torch.equal(_bits(fh), _bits(torch.cat([got["f"], got["h"]], dim=1)))


def _random_expression(rng: random.Random, depth: int) -> str:
    """A random expression of the whitelisted grammar (may be refused by the parser)."""
    if depth <= 0 or rng.random() < 0.25:
        return rng.choice(["x", "y", "z", "x", str(rng.randint(0, 9)),
                           f"{rng.uniform(-3, 3):.3f}", "pi"])
    r = rng.random()
    if r < 0.45:
        return (f"({_random_expression(rng, depth - 1)} {rng.choice('+-*/')} "
                f"{_random_expression(rng, depth - 1)})")
    if r < 0.6:
        k = rng.choice(["2", "3", "-1", "-2", "0.5", "1.5", "0", "(-3)"])
        return f"({_random_expression(rng, depth - 1)})**{k}"
    if r < 0.65:
        return f"({_random_expression(rng, depth - 1)})**({_random_expression(rng, depth - 2)})"
    if r < 0.72:
        return f"-{_random_expression(rng, depth - 1)}"
    return f"{rng.choice(FUNCS)}({_random_expression(rng, depth - 1)})"


def _random_specs(seed: int, count: int, rows: int):
    """(points [rows, 3], then `count` times (expressions e and de/dx, de/dy, de/dz, their
    torch tape's values [rows, 4])): random whitelisted expressions that compile (sympy
    writes some derivatives with functions outside the table (atan2) or complex constants
    (log of a negative number): refused at build time, skipped). The first 4 points are 0:
    poles and 0**negative, the inf / nan paths."""
    rng = random.Random(seed)
    gen = torch.Generator().manual_seed(seed)
    pts = 2.0 * torch.randn(rows, 3, generator=gen, dtype=torch.float64)
    pts[:4] = 0.0
    yield pts
    tried = 0
    while tried < count:
        try:
            e = parse_expression(_random_expression(rng, rng.randint(1, 4)), NAMES)
        except Exception:
            continue
        exprs = [e, *(sympy.diff(e, s) for s in (X, Y, Z))]
        try:
            values = compile_torch_rows(exprs, [X, Y, Z])(pts)
        except (SpecError, TypeError):
            continue
        tried += 1
        yield exprs, values


@pytest.mark.slow
def test_random_specs_rows_equal_single_expressions_and_the_tree_walk() -> None:
    """Random whitelisted expressions and their derivatives (sign, general powers): one tape
    for all rows gives the bits of one tape per expression, and both agree with the plain
    tree walk `evaluate` (which folds no constants) to rounding, NaN where it is NaN."""
    specs = _random_specs(7, 100, 300)
    pts = next(specs)
    cols = list(pts.unbind(1))
    for exprs, rows in specs:
        assert rows.shape == (300, 4)
        for i, ex in enumerate(exprs):
            one = torch.as_tensor(compile_torch(ex, [X, Y, Z])(cols), dtype=torch.float64)
            assert torch.equal(_bits(rows[:, i]), _bits(one.expand(300))), ex
            tree = evaluate(ex, {X: cols[0], Y: cols[1], Z: cols[2]}, TORCH, cols[0])
            ok = torch.isfinite(tree) & (tree.abs() < 1e200)
            torch.testing.assert_close(rows[ok, i], tree[ok], rtol=1e-9, atol=1e-12)


def test_numpy_rows_agree_with_torch_rows_on_random_specs() -> None:
    """The simulation's NumPy tape (`compile_numpy_rows`) gives the torch tape's values on
    random whitelisted expressions and their derivatives, up to the libraries' rounding of
    powers, sin, exp, ... (a few ulps); NaN and inf exactly where the torch tape has them
    (poles and 0**negative at the zero rows)."""
    import numpy as np

    from certify.spec.expr import compile_numpy_rows

    specs = _random_specs(11, 60, 200)
    pts = next(specs)
    for exprs, want in specs:
        with np.errstate(all="ignore"):
            got = torch.from_numpy(compile_numpy_rows(exprs, [X, Y, Z])(pts.numpy()))
        assert got.shape == want.shape
        assert torch.equal(torch.isnan(got), torch.isnan(want)), exprs[0]
        assert torch.equal(torch.isinf(got), torch.isinf(want)), exprs[0]
        ok = torch.isfinite(want) & (want.abs() < 1e200)
        torch.testing.assert_close(got[ok], want[ok], rtol=1e-12, atol=1e-14)


def test_constant_base_power_evaluates() -> None:
    """2**x (a constant base: the exec evaluator called torch.log on a float and crashed)."""
    e = parse_expression("2**x + y", NAMES)
    xs = torch.tensor([0.0, 1.0, -2.0, 0.5], dtype=torch.float64)
    ys = torch.zeros(4, dtype=torch.float64)
    got = compile_torch(e, [X, Y])([xs, ys])
    torch.testing.assert_close(got, torch.tensor([1.0, 2.0, 0.25, 2.0 ** 0.5],
                                                 dtype=torch.float64), rtol=1e-15, atol=0)


@pytest.mark.slow
def test_no_eval_or_exec_in_the_package() -> None:
    """Spec text never reaches eval/exec: none is called anywhere in the package (the
    evaluators are built from the parsed tree); sympify is not called either."""
    offenders = []
    for folder in ("certify", "training", "reports"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                        and node.func.id in ("eval", "exec", "sympify"):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.func.id}")
    assert offenders == []
