"""The whitelist parser: accepted forms evaluate correctly, every other construct is refused."""

from __future__ import annotations

import math

import pytest
import sympy
import torch

from certify.errors import SpecError
from certify.spec.expr import FUNCTIONS, TORCH, evaluate, parse_expression

X, Y = sympy.symbols("x y", real=True)
NAMES = {"x": X, "y": Y}


@pytest.mark.parametrize("text,value", [
    ("x + 2*y", 1.0 + 2 * 2.0),
    ("-x**2 + y/4", -1.0 + 0.5),
    ("sin(x) + cos(y) + tan(0.3)", math.sin(1) + math.cos(2) + math.tan(0.3)),
    ("exp(x) * log(y) - sqrt(y)", math.e * math.log(2) - math.sqrt(2)),
    ("tanh(x - y) + abs(x - y)", math.tanh(-1) + 1),
    ("x**-2 + y**0.5 + pi", 1 + math.sqrt(2) + math.pi),
    ("+x - -y", 3.0),
    ("1e-3 * x", 1e-3),
])
def test_accepted_expressions_evaluate(text, value):
    expr = parse_expression(text, NAMES)
    env = {X: torch.tensor([1.0], dtype=torch.float64), Y: torch.tensor([2.0], dtype=torch.float64)}
    got = evaluate(expr, env, TORCH, env[X])
    assert got.item() == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("text,fragment", [
    ("__import__('os').system('touch pwned')", "call"),
    ("__import__('os')", "unknown function '__import__'"),
    ("x.real", "attribute access"),
    ("x[0]", "subscript"),
    ("(lambda: 1)()", "not allowed"),
    ("lambda: x", "lambda"),
    ("'abc'", "not a real number"),
    ("z + 1", "unknown name 'z'"),
    ("open('f')", "unknown function 'open'"),
    ("sin(x, y)", "exactly one argument"),
    ("sin(x=1)", "exactly one argument"),
    ("x if y else 1", "conditional"),
    ("x < y", "comparison"),
    ("x and y", "boolean operator"),
    ("[x]", "list"),
    ("x // y", "not allowed"),
    ("x % y", "not allowed"),
    ("x @ y", "not allowed"),
    ("True", "not a real number"),
    ("1j", "not a real number"),
    ("(x := 1)", "assignment"),
    ("f'{x}'", "string"),
    ("x +", "cannot parse"),
    ("", "empty"),
    ("sympy.sin(x)", "call"),
])
def test_refused_constructs_name_the_offending_piece(text, fragment):
    with pytest.raises(SpecError) as err:
        parse_expression(text, NAMES, where="spec t.toml: f[0]")
    message = str(err.value)
    assert fragment in message
    assert message.startswith("spec t.toml: f[0]")
    assert "\n" not in message


def test_refusal_does_not_execute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SpecError):
        parse_expression("__import__('os').system('touch pwned')", NAMES)
    assert not (tmp_path / "pwned").exists()


def test_function_table_covers_whitelist():
    assert set(FUNCTIONS) == {"sin", "cos", "tan", "exp", "log", "sqrt", "tanh", "abs"}


@pytest.mark.parametrize("text", ["x + 2*y", "-x**2 + y/4", "sin(x) * exp(-y) + sqrt(y)",
                                  "abs(x - y) + tanh(x) ** 3 + x**-2", "y**0.5 + pi + 2",
                                  "3.5"])
def test_compiled_closure_matches_tree_evaluation(text):
    from certify.spec.expr import compile_torch

    expr = parse_expression(text, NAMES)
    xs = torch.tensor([0.7, 1.3, -0.4], dtype=torch.float64)
    ys = torch.tensor([2.0, 0.5, 1.1], dtype=torch.float64)
    ref = evaluate(expr, {X: xs, Y: ys}, TORCH, xs)
    got = compile_torch(expr, [X, Y])([xs, ys])
    torch.testing.assert_close(torch.as_tensor(got, dtype=torch.float64).expand(3), ref)


def test_compiled_rows_equal_each_compiled_expression_bit_for_bit():
    """`compile_torch_rows` (one generated function, shared sub-expressions computed once)
    gives exactly the floats of `compile_torch` per expression; constants fill a column."""
    from certify.spec.expr import compile_torch, compile_torch_rows

    texts = ["x*(1 - x**2) + y", "sin(x*y) + sin(x*y)**2", "3.5", "y", "exp(y**0.5) / x",
             "-x + y*(1 - x**2)"]
    exprs = [parse_expression(t, NAMES) for t in texts]
    gen = torch.Generator().manual_seed(0)
    pts = 0.5 + torch.rand(257, 2, generator=gen, dtype=torch.float64)
    got = compile_torch_rows(exprs, [X, Y])(pts)
    assert got.shape == (257, len(texts))
    for i, e in enumerate(exprs):
        ref = compile_torch(e, [X, Y])([pts[:, 0], pts[:, 1]])
        assert torch.equal(got[:, i], torch.as_tensor(ref, dtype=torch.float64).expand(257))
        tree = evaluate(e, {X: pts[:, 0], Y: pts[:, 1]}, TORCH, pts[:, 0])
        torch.testing.assert_close(got[:, i], tree, rtol=1e-15, atol=0)
