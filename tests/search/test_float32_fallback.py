"""Numbers beyond float32's range: the float32 grid screen falls back to float64 (it only ever
selects points; it never decides and never crashes), and a spec the parser accepts with such
a constant is verified end to end: certified where the system plainly contracts, at worst
UNKNOWN where float64 itself cannot resolve it, never ERROR. The n = 2 eigenvalue forms
(point and sound) stay exact where a huge diagonal entry would cancel them."""

from __future__ import annotations

import json
import math

import mpmath
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import _lam2_upper
from certify.checks.mpdi import falsify_mpdi, joint_box
from certify.checks.rate import check_rate
from certify.model import checkpoint
from certify.model.kernels import lam_max, pointwise_rate
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.search.falsify import screen_tolerance
from certify.search.grid import (
    GridKernel,
    float32_misfit,
    float32_rate_screen,
    float32_screen,
)
from certify.settings import VerifySettings
from certify.spec.system import System

from ..cli_helpers import FAST_POLICY, run_cli

SPEC = """
name = "huge"
states = ["x1", "x2"]
outputs = ["y"]
f = [{f}]
h = [{h}]
[box]
X = [[-1, 1], [-1, 1]]
Y = [[-1, 1]]
[design]
lam = 0.25
"""


def huge_problem(f: str = '"-1e39*x1", "-x2"', h: str = '"x1"',
                 weight: float | None = None, structure: str = "direct") -> Problem:
    """D = diag(-1e39 + 0.5, -0.5) for the default spec: lam_max(D) = -0.5 everywhere. A
    zero network, except one first-layer weight `weight` (with zero layers after it: k = 0)."""
    system = System.from_text(SPEC.format(f=f, h=h), origin="test spec huge")
    net = GainNetwork(2, 1, (4, 4), structure=structure).double()
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.zero_()
            layer.bias.zero_()
        if weight is not None:
            net.layers[0].weight[0, 0] = weight
    return Problem(system, net.requires_grad_(False), 0.25, np.eye(2))


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def _run(workdir, capsys, problem: Problem, *extra: str) -> tuple[int, dict]:
    path = workdir / "huge.ckpt"
    checkpoint.save(path, system=problem.system, network=problem.network, lam=problem.lam,
                    P=problem.P)
    code, out, err = run_cli(capsys, "run", str(path), "--json", "cert.json", "--quiet",
                             *extra)
    assert "Traceback" not in out + err
    return code, json.loads((workdir / "cert.json").read_text())


@pytest.mark.slow
def test_the_float32_overflow_spec_is_certified_and_no_check_errs(workdir, capsys):
    code, cert = _run(workdir, capsys, huge_problem())
    assert code == 0, cert["checks"]["mpdi"]["message"]
    assert cert["verdict"] == "CERTIFIED"
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] == "PROVED" and mpdi["upper"] <= 0
    assert mpdi["lower"] == -0.5  # the sampled max is exact, not lost to cancellation
    for name, check in cert["checks"].items():
        assert check["status"] != "ERROR", (name, check["message"])


@pytest.mark.parametrize("f, h, weight", [
    ('"-x1", "-x2"', '"1e39*x1"', None),  # a huge constant in h (dh/dx)
    ('"-exp(100)*x1", "-x2"', '"x1"', None),  # a folded constant beyond float32
    ('"-x1 - 1e39*x1**3", "-x2"', '"x1"', None),  # a huge coefficient of a product
    ('"-x1", "-x2"', '"x1"', 1e39),  # a network weight beyond float32
])
def test_values_beyond_float32_are_certified(workdir, capsys, f, h, weight):
    code, cert = _run(workdir, capsys, huge_problem(f, h, weight),
                      "--skip", "necessary,rate,residual,lipschitz,bounds,simulation")
    assert code == 0, cert["checks"]["mpdi"]["message"]
    assert cert["checks"]["mpdi"]["status"] == "PROVED"


@pytest.mark.slow
def test_what_float64_cannot_resolve_is_unknown_never_an_error(workdir, capsys):
    """Entries of 1e39 that cancel to the system's -0.5 (x-dependent): no float64 value or
    interval bound resolves the sign; the run says UNKNOWN (exit 3) instead of crashing."""
    problem = huge_problem('"-1e39*x1", "-x2 - 1e39*x2*x1**2"')
    code, cert = _run(workdir, capsys, problem, "--max-boxes", "50000", "--skip",
                      "necessary,rate,residual,lipschitz,bounds,simulation")
    assert code in (0, 3)
    assert cert["checks"]["mpdi"]["status"] in ("PROVED", "UNKNOWN")


@pytest.mark.parametrize("f, h, weight, why", [
    ('"-1e39*x1", "-x2"', '"x1"', None, "constant of df/dx"),
    ('"-exp(100)*x1", "-x2"', '"x1"', None, "constant of df/dx"),
    ('"-x1", "-x2"', '"1e39*x1"', None, "constant of dh/dx"),
    ('"-x1 + 1e-45*x2", "-x2"', '"x1"', None, "constant of df/dx"),  # below float32's normals
    ('"-x1", "-x2"', '"x1"', 1e39, "weight of layer 1"),
])
def test_the_screen_falls_back_where_a_number_does_not_fit(f, h, weight, why):
    problem = huge_problem(f, h, weight)
    assert why in float32_misfit(problem)
    kernel = GridKernel(problem, dtype=torch.float32)
    assert kernel.dtype == torch.float64 and why in kernel.fallback
    assert float32_screen(problem) is None
    z = torch.tensor([[0.3, -0.2, 0.1], [-1.0, 1.0, 1.0]], dtype=torch.float64)
    assert torch.equal(kernel(z), GridKernel(problem)(z))


def test_a_structural_gain_falls_back_on_a_constant_of_h_alone():
    """The structural kernel evaluates h itself: a constant dh/dx never sees still counts."""
    h = '"x1 + 1e39"'
    assert float32_misfit(huge_problem('"-x1", "-x2"', h)) is None  # direct: only dh/dx
    problem = huge_problem('"-x1", "-x2"', h, structure="structural")
    assert "constant of h" in float32_misfit(problem)
    assert float32_screen(problem) is None


def test_the_rate_screen_falls_back_like_the_mpdi_screen():
    assert float32_rate_screen(huge_problem()) is None  # a constant of df/dx
    fits = huge_problem('"-x1", "-x2"')
    assert float32_rate_screen(fits) is not None
    # P positive definite in float64, not in float32 (its Cholesky factor): no screen
    thin = Problem(fits.system, fits.network, 0.25, np.array([[1.0, 1.0], [1.0, 1.0 + 1e-9]]))
    assert float32_misfit(thin) is None and float32_rate_screen(thin) is None


def test_the_rate_grid_gives_the_same_numbers_with_its_screen():
    """A contracting system (rates 0.2 to 0.8, far from 0: the screen is used, not skipped)."""
    system = System.from_text(SPEC.format(f='"-2*x1 + x2", "-x1 - 2*x2 + x1**2*x2"',
                                          h='"x1"'), origin="test spec contracting")
    torch.manual_seed(3)
    net = GainNetwork(2, 1, (6, 6), structure="structural").double().requires_grad_(False)
    with torch.no_grad():
        net.layers[-1].weight.mul_(0.3)
    problem = Problem(system, net, 0.25, np.array([[2.0, 0.3], [0.3, 1.0]]))
    lo, hi = (torch.as_tensor(b) for b in joint_box(problem))
    _, near = screen_tolerance(lambda z: -pointwise_rate(system, net, problem.P_t, z[:, :2],
                                                         z[:, 2:]),
                               float32_rate_screen(problem), lo, hi, seed=0)
    assert near < 0.25  # the sweep keeps its screen
    kw = dict(grid_points=8000, adversarial_starts=4, adversarial_steps=10)
    with_screen = check_rate(problem, VerifySettings(float32_screen=True, **kw), prove=False)
    plain = check_rate(problem, VerifySettings(float32_screen=False, **kw), prove=False)
    assert with_screen.sampled_upper == plain.sampled_upper
    assert with_screen.worst == plain.worst


def test_a_problem_that_fits_keeps_its_float32_screen():
    problem = huge_problem('"-x1", "-x2"')
    assert float32_misfit(problem) is None
    screen = float32_screen(problem)
    assert screen is not None and screen.dtype == torch.float32


def test_the_sweep_without_its_screen_gives_the_float64_numbers():
    """The fallback sweep is the float64 sweep: the same numbers as with no screen asked."""
    problem = huge_problem()
    kw = dict(grid_points=4000, adversarial_starts=4, adversarial_steps=10)
    with_screen = falsify_mpdi(problem, VerifySettings(float32_screen=True, **kw))
    plain = falsify_mpdi(problem, VerifySettings(float32_screen=False, **kw))
    assert with_screen.best_value == plain.best_value == -0.5
    assert with_screen.above_threshold == plain.above_threshold == 0
    assert with_screen.nonfinite == 0


def _exact_lam2(a: float, b: float, c: float) -> mpmath.mpf:
    with mpmath.workdps(2000):
        a, b, c = mpmath.mpf(a), mpmath.mpf(b), mpmath.mpf(c)
        return (a + c) / 2 + mpmath.sqrt(((a - c) / 2) ** 2 + b * b)


_scaled = st.builds(lambda m, e: m * 10.0**e, st.floats(-1.0, 1.0),
                    st.integers(-40, 200))


@settings(max_examples=400, deadline=None)
@given(_scaled, _scaled, _scaled)
@pytest.mark.slow
def test_the_sound_two_by_two_bound_holds_at_every_scale(a, b, c):
    t = torch.tensor([a], dtype=torch.float64)
    ub = float(_lam2_upper(t, torch.tensor([abs(b)], dtype=torch.float64),
                           torch.tensor([c], dtype=torch.float64))[0])
    assert mpmath.mpf(ub) >= _exact_lam2(a, b, c)


@settings(max_examples=300, deadline=None)
@given(_scaled, _scaled, _scaled)
@pytest.mark.slow
def test_the_point_two_by_two_eigenvalue_is_accurate_at_every_scale(a, b, c):
    S = torch.tensor([[[a, b], [b, c]]], dtype=torch.float64)
    got = mpmath.mpf(float(lam_max(S)[0]))
    exact = _exact_lam2(a, b, c)
    big, small = max(abs(a), abs(c)), max(min(abs(a), abs(c)), abs(b))
    # within a few ulps of the entries; where a negative diagonal entry dwarfs the others
    # (-1e39 beside -0.5), within a few ulps of the others and of the value itself
    dwarfs = (a if abs(a) >= abs(c) else c) < 0 and 0 < small and big > 2.0**26 * small
    allowed = 2.0**-49 * max(abs(exact), small if dwarfs else big)
    assert abs(got - exact) <= max(allowed, 1e-300), (float(got), float(exact))


def test_two_by_two_forms_unchanged_where_no_entry_dwarfs_the_rest():
    """Where no negative diagonal entry dwarfs the others (near-ties included: there
    certify.search.witness decides), the textbook forms are returned bit for bit."""
    gen = torch.Generator().manual_seed(0)
    a, b, c = (torch.randn(10_000, generator=gen, dtype=torch.float64) * 3 for _ in range(3))
    S = torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], -2)
    sa, sb, sc = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]  # the same strided views as lam_max's
    textbook = 0.5 * (sa + sc) + torch.hypot(0.5 * (sa - sc), sb)
    assert torch.equal(lam_max(S), textbook)
    from certify.arith.intervals import up, widen_up

    sound = up(up(0.5 * up(a + c)) + widen_up(torch.hypot(up((a - c).abs()) * 0.5, b.abs())))
    assert torch.equal(_lam2_upper(a, b.abs(), c), sound)
    assert math.isfinite(float(sound.max()))
