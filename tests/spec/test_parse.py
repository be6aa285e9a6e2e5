"""Hostile and undefined specs (issues 8.2, 8.4, 12.3): built exactly as written, checked on
the box, refused with exit 2 and one line; the same expressions on a box where they are
defined still work."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.errors import SpecError
from certify.spec.parse import LIMITS, parse_expression
from certify.spec.system import System

from ..cli_helpers import run_cli
from ..soak import examples

X_BAD = "[[-1.0, 1.0], [-1.0, 1.0]]"
X_GOOD = "[[0.5, 1.0], [-1.0, 1.0]]"


def spec(f: list[str], X: str = X_BAD, h: str = "x1") -> str:
    fs = ", ".join(f'"{e}"' for e in f)
    return (f'name = "t"\nstates = ["x1", "x2"]\noutputs = ["y"]\nf = [{fs}]\nh = ["{h}"]\n'
            f"[box]\nX = {X}\nY = [[-1.0, 1.0]]\n[design]\nlam = 0.5\n")


UNDEFINED = [
    (["-sqrt(x1)**2", "-x2"], "f[0]", "'x1' raised to the non-integer power", "x1 in [-1, 0"),
    (["-x1", "-x2*(x1-0.3)/(x1-0.3)"], "f[1]", "division by 'x1 - 0.3'", "x1 in [0.29"),
    (["exp(log(x1))", "-x2"], "f[0]", "log of 'x1'", "x1 in [-1, 0"),
    (["x1**2/x1", "-x2"], "f[0]", "division by 'x1'", "x1 in [-0.0"),
    (["-abs(x1)", "-x2"], "f[0]", "abs is not differentiable", "x1 in [-0.0"),
    (["-x1", "-x2 + x1**x2"], "f[1]", "needs a positive base", "x1 in [-1"),
    (["-x1", "-x2 + tan(2*x1)"], "f[1]", "tan of '2 * x1'", "x1 in ["),
]


@pytest.mark.parametrize("f, which, reason, part", UNDEFINED)
def test_undefined_on_the_box_is_refused_by_check(tmp_path, capsys, f, which, reason, part):
    path = tmp_path / "s.toml"
    path.write_text(spec(f))
    code, out, err = run_cli(capsys, "check", str(path), "--no-synthesis")
    assert code == 2, out + err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert which in err and reason in err and part in err


def test_undefined_spec_refused_by_train_before_any_work(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text(spec(["-sqrt(x1)**2", "-x2*(x1-0.3)/(x1-0.3)"]))
    code, _, err = run_cli(capsys, "train", str(path), "--preset", "tiny", "-o",
                           str(tmp_path / "o.ckpt"))
    assert code == 2 and "not defined and smooth" in err and err.count("\n") == 1
    assert not (tmp_path / "o.ckpt").exists()


def test_same_expressions_where_defined_are_kept_as_written():
    s = System.from_text(spec(["-sqrt(x1)**2", "-x2*(x1-0.3)/(x1-0.3) + exp(log(x1)) "
                               "+ x1**2/x1 - 2*x1"], X=X_GOOD))
    x = torch.tensor([[0.75, 0.5], [0.5, -1.0]], dtype=torch.float64)
    f = s.f(x)
    assert torch.allclose(f[:, 0], -x[:, 0]) and torch.allclose(f[:, 1], -x[:, 1])
    J = s.jac_f(x)
    assert torch.allclose(J, torch.tensor([[-1.0, 0.0], [0.0, -1.0]], dtype=torch.float64))
    # the tree is the one written, not a simplified one
    assert s.f_expr[0].has(sympy.Pow) and s.f_expr[0] != -sympy.Symbol("x1", real=True)


def test_abs_where_one_signed_is_resolved_and_differentiable():
    s = System.from_text(spec(["-abs(x1)*x1 - x1", "-x2 - abs(x1 - 2)"], X=X_GOOD))
    assert not any(e.has(sympy.Abs) for e in s.f_expr)
    x = torch.tensor([[0.75, 0.5]], dtype=torch.float64)
    assert torch.allclose(s.f(x), torch.tensor([[-0.75**2 - 0.75, -0.5 - 1.25]],
                                               dtype=torch.float64))
    assert torch.allclose(s.jac_f(x), torch.tensor([[[-2 * 0.75 - 1, 0.0], [1.0, -1.0]]],
                                                   dtype=torch.float64))


HOSTILE = [
    ("9**9**9", "exponent"),
    ("+".join(["x1"] * 10_000), "characters long"),
    ("+".join(["x1"] * 2500), "terms and operations"),
    ("-(" * 70 + "x1" + ")" * 70, "nested"),
    ("1" + "0" * 40 + "*x1", "larger than"),
    ("x1**1000000", "beyond"),
    ("(-1)**0.5 + x1", "no finite real value"),
    ("1/0 + x1", "divides by zero"),
    ("exp(1000) * x1", "no finite real value"),
    ("10.0**300 * 10.0**300 * x1", "beyond"),
    ("sign(x1)", "'sign' in 'sign(x1)': it is not smooth"),
    ("floor(x1)", "'floor' in 'floor(x1)': it is not smooth"),
    ("max(x1, 0)", "unknown function 'max'"),
]


@pytest.mark.parametrize("text, words", HOSTILE)
def test_hostile_expressions_are_refused_in_one_line(text, words):
    names = {"x1": sympy.Symbol("x1", real=True)}
    with pytest.raises(SpecError) as info:
        parse_expression(text, names, where="spec t.toml: f[0]")
    msg = str(info.value)
    assert words in msg and "\n" not in msg and msg.startswith("spec t.toml: f[0]")
    assert len(msg) < 300


def test_limits_are_the_documented_ones():
    assert LIMITS.max_chars <= 10_000 and LIMITS.max_nodes <= 5_000
    assert math.isfinite(LIMITS.max_constant)


def test_singularity_inside_the_box_is_never_certified(tmp_path, capsys):
    """1/(x1 - 0.3) has a pole inside X: refused up front, so nothing is ever PROVED."""
    path = tmp_path / "s.toml"
    path.write_text(spec(["-x1 + 0.001/(x1 - 0.3)", "-x2"]))
    code, _, err = run_cli(capsys, "check", str(path), "--no-synthesis")
    assert code == 2 and "division by 'x1 - 0.3'" in err


def test_enclosure_slack_is_refined_not_refused():
    """(x1 - 0.1)^2 + 0.09 > 0 everywhere, but its naive enclosure over [-1, 1] contains 0."""
    s = System.from_text(spec(["-x1 + 1/(x1**2 + 0.1 - 0.2*x1)", "-x2"]))
    assert np.isfinite(s.f(torch.zeros(1, 2, dtype=torch.float64)).numpy()).all()


def test_undefined_spec_refused_by_run_with_system(tmp_path, capsys):
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "vdp.ckpt"
    path = tmp_path / "s.toml"
    path.write_text(spec(["exp(log(x1))", "-x2"]))
    code, _, err = run_cli(capsys, "run", str(example), "--system", str(path))
    assert code == 2 and "log of 'x1', which can be <= 0" in err and err.count("\n") == 1


@pytest.mark.slow
def test_long_sums_and_products_are_flat_not_deep():
    """300 terms are one flat sum (no recursion per term), and evaluate to the right value."""
    text = " + ".join(f"{k % 7 - 3}*x1*x2" for k in range(300)) + " - x2/x1/2"
    s = System.from_text(spec([text, "-x2"], X=X_GOOD))
    assert len(s.f_expr[0].args) > 250  # flat
    x = torch.tensor([[0.75, 0.5]], dtype=torch.float64)
    coeff = sum(k % 7 - 3 for k in range(300))
    assert float(s.f(x)[0, 0]) == pytest.approx(coeff * 0.375 - 0.5 / 0.75 / 2)
    long_bad = text + " + 1/x2"
    with pytest.raises(SpecError) as info:
        System.from_text(spec([long_bad, "-x2"], X=X_GOOD))
    assert "division by 'x2'" in str(info.value) and len(str(info.value)) < 400
    with pytest.raises(SpecError, match="nested"):
        parse_expression("sin(" * 70 + "x1" + ")" * 70, {"x1": sympy.Symbol("x1")})


@settings(max_examples=examples(40), deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 4), hostile=st.booleans())
@pytest.mark.slow
def test_accepted_specs_are_finite_everywhere_and_undefined_ones_refused(seed, n, hostile):
    """Acceptance is sound: f and Jf are finite at every sampled point of X; a spec with a
    term undefined somewhere on X is refused."""
    from ..mp_reference import random_spec

    rng = np.random.default_rng(seed)
    rs = random_spec(rng, n, 1, 2.0, allow_undefined=hostile)
    if not rs.defined:
        with pytest.raises(SpecError, match="not defined and smooth"):
            System.from_text(rs.text)
        return
    s = System.from_text(rs.text)
    X = torch.as_tensor(rs.X)
    x = X[:, 0] + (X[:, 1] - X[:, 0]) * torch.rand(2000, n, dtype=torch.float64,
                                                    generator=torch.Generator().manual_seed(seed))
    x = torch.cat([x, X[:, 0][None], X[:, 1][None]])
    assert bool(torch.isfinite(s.f(x)).all()) and bool(torch.isfinite(s.jac_f(x)).all())
