"""Soundness of decisions (issue 8.1): a verdict needs a sound bound behind it.

A near-tie (exact lam_max(D) = -1.1e-17, float closed form +2.2e-16) must never be VIOLATED;
a planted real violation still is, with its sound lower bound recorded in the JSON.
"""

from __future__ import annotations

import json
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.intervals import Interval
from certify.model.kernels import mpdi_lam_max
from certify.search.witness import mpdi_lower, rayleigh_lower

from ..cli_helpers import FAST_POLICY, run_cli, save_problem
from ..planted import linear_problem
from ..soak import examples

# D = He{A} + 2 lam I with lam = 1/2 is [[d1, b], [b, d2]] exactly (every constant is a double
# and d2 - 1 + 1 is exact); det D = d1 d2 - b^2 >= 0, so lam_max(D) = -1.1e-17 <= 0 exactly,
# while the float closed form gives +2.2e-16.
D1, B, D2 = -3.3862991333007812, 0.7026252746582031, -0.14578814722351496
A_TIE = np.array([[D1 - 1.0, B], [B, D2 - 1.0]])
C_TIE = np.array([[1.0, 0.0]])


def _tie_problem():
    return linear_problem(A_TIE, C_TIE, np.zeros((2, 1)), lam=0.5)


def test_the_tie_is_a_tie():
    d1, b, d2 = (Fraction(v) for v in (D1, B, D2))
    assert d1 * d2 - b * b >= 0 and d1 < 0 and d2 < 0  # exact: D <= 0
    assert A_TIE[1, 1] + 1.0 == D2
    pr = _tie_problem()
    z = torch.tensor([[0.25, -0.5, 0.25]], dtype=torch.float64)
    assert float(mpdi_lam_max(pr.system, pr.network, pr.P_t, 0.5, z[:, :2], z[:, 2:])[0]) > 0
    assert float(mpdi_lower(pr, z)[0]) <= 0


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


@pytest.mark.slow
def test_tie_is_never_violated_through_the_cli(workdir, capsys):
    path = save_problem(workdir / "tie.ckpt", _tie_problem())
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--skip",
                             "simulation,lipschitz", "--max-boxes", "2000")
    assert code in (0, 3), out + err
    cert = json.loads((workdir / "c.json").read_text())
    mpdi, rate = cert["checks"]["mpdi"], cert["checks"]["rate"]
    assert mpdi["status"] in ("PROVED", "UNKNOWN") and not mpdi["counterexamples"]
    if mpdi["status"] == "UNKNOWN":
        assert "near-tie" in mpdi["message"]
    assert rate["status"] != "VIOLATED"
    assert "Traceback" not in err


@pytest.mark.slow
def test_planted_violation_found_with_sound_bound(workdir, capsys):
    A = np.array([[0.25, 1.0], [-1.0, -2.0]])  # He{A} + I has lam_max >= 1.25 > 0 everywhere
    path = save_problem(workdir / "bad.ckpt", linear_problem(A, C_TIE, np.zeros((2, 1)),
                                                              lam=0.5))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--skip",
                             "simulation,lipschitz")
    assert code == 1, out + err
    cert = json.loads((workdir / "c.json").read_text())
    cex = cert["checks"]["mpdi"]["counterexamples"][0]
    assert cert["checks"]["mpdi"]["status"] == "VIOLATED"
    assert 0 < cex["sound_bound"] <= cex["value"]
    assert "sound lower bound" in cert["checks"]["mpdi"]["message"]


def test_rayleigh_lower_is_below_every_member_and_nan_never_decides():
    gen = torch.Generator().manual_seed(0)
    S = torch.randn(64, 4, 4, generator=gen, dtype=torch.float64)
    S = S + S.transpose(-1, -2)
    rad = torch.rand(64, 4, 4, generator=gen, dtype=torch.float64) * 1e-3
    rad = rad + rad.transpose(-1, -2)
    A = Interval(S - rad, S + rad)
    low = rayleigh_lower(A)
    for t in (0.0, 1.0, -1.0):
        member = S + t * rad
        assert bool((torch.linalg.eigvalsh(member)[..., -1] >= low).all())
    exact_top = torch.linalg.eigvalsh(S)[..., -1]
    assert bool((exact_top - low < 1e-2).all())  # and it is tight
    bad = Interval(S.clone(), S.clone())
    bad.hi[0, 1, 2] = float("nan")
    assert torch.isnan(rayleigh_lower(bad)[0])


# ----- NaN / Inf never decide anything -------------------------------------------------

def test_nan_weight_in_checkpoint_is_refused_at_load(workdir, capsys):
    path = save_problem(workdir / "ok.ckpt", linear_problem(A_TIE, C_TIE, np.zeros((2, 1)),
                                                            lam=0.5))
    data = torch.load(path, weights_only=True)
    key = next(k for k in data["state_dict"] if k.endswith("weight"))
    data["state_dict"][key] = data["state_dict"][key].clone()
    data["state_dict"][key].view(-1)[0] = float("nan")
    torch.save(data, workdir / "nan.ckpt")
    code, out, err = run_cli(capsys, "run", str(workdir / "nan.ckpt"))
    assert code == 2 and "contains NaN or Inf" in err and err.count("\n") == 1


def test_spec_overflowing_inside_the_box_is_refused(workdir, capsys):
    (workdir / "s.toml").write_text(
        'name = "t"\nstates = ["x1", "x2"]\noutputs = ["y"]\n'
        'f = ["-x1 + 1e-300*exp(exp(7*x1))", "-x2"]\nh = ["x1"]\n'
        "[box]\nX = [[-1.0, 1.0], [-1.0, 1.0]]\nY = [[-1.0, 1.0]]\n[design]\nlam = 0.5\n")
    code, _, err = run_cli(capsys, "check", "s.toml", "--no-synthesis")
    assert code == 2 and "is not finite" in err and "x1 in [" in err


@pytest.mark.slow
def test_overflowing_network_is_never_proved(workdir, capsys):
    """Weights x1e307: D, k and ||dk/dy|| overflow somewhere; nothing is PROVED from Inf and
    any VIOLATED stands on a finite sound bound."""
    pr = linear_problem(A_TIE, C_TIE, np.zeros((2, 1)), lam=0.5, hidden=(6, 6))
    net = pr.network.double()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen))
        net.layers[-1].weight.mul_(1e307)
    from certify.model.problem import Problem

    path = save_problem(workdir / "inf.ckpt", Problem(pr.system, net, pr.lam, pr.P))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--skip", "simulation",
                             "--max-boxes", "2000")
    assert code in (1, 3), out + err
    checks = json.loads((workdir / "c.json").read_text())["checks"]
    assert checks["mpdi"]["status"] != "PROVED" and checks["residual"]["status"] != "PROVED"
    for cex in checks["mpdi"]["counterexamples"]:
        assert isinstance(cex["sound_bound"], float) and 0 < cex["sound_bound"] < math.inf
    assert checks["lipschitz"]["value"] is None or checks["lipschitz"]["value"] < math.inf
    assert checks["lipschitz"]["sampled"] != checks["lipschitz"]["sampled"] \
        or checks["lipschitz"]["sampled"] >= 0


# ----- the witness bounds are lower bounds (hypothesis, 40-digit reference) ---------------

@settings(max_examples=examples(15), deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 4), cond=st.floats(0.0, 6.0))
@pytest.mark.slow
def test_witness_bounds_are_below_the_40_digit_values(seed, n, cond):
    from certify.checks.lipschitz import dk_dy_norms
    from certify.checks.residual import residual_norm
    from certify.model.problem import Problem
    from certify.search.witness import dk_dy_norm_lower, manifold_lower, residual_lower
    from certify.spec.system import System

    from ..mp_reference import lam_max_D, manifold_q, network_layers, random_network, random_spec

    rng = np.random.default_rng(seed)
    spec = random_spec(rng, n, 1, cond)
    system = System.from_text(spec.text)
    net = random_network(rng, n, 1, str(rng.choice(["small", "large", "saturated", "zero"])))
    problem = Problem(system, net, spec.lam, system.P)
    box = np.vstack([spec.X, system.Y])
    z = torch.as_tensor(box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((4, n + 1)))
    low = mpdi_lower(problem, z)
    q_low = manifold_lower(system, system.P, spec.lam, z[:, :n])
    with torch.no_grad():
        res_f = residual_norm(problem, z[:, :n])
        lip_f = dk_dy_norms(problem, z)
    res_low = residual_lower(problem, z[:, :n])
    lip_low = dk_dy_norm_lower(problem, z)
    layers = network_layers(net)
    for i in range(len(z)):
        ref = lam_max_D(spec, layers, z[i, :n].tolist(), z[i, n:].tolist())
        assert not float(low[i]) > ref, (float(low[i]), ref)
        assert float(low[i]) >= float(ref) - 1e-6 * (1 + abs(float(ref)))  # and tight
        assert not float(q_low[i]) > manifold_q(spec, z[i, :n].tolist())
    # k and dk/dy: float values agree with the sound lower bounds to rounding
    assert bool((res_low <= res_f * (1 + 1e-12) + 1e-300).all())
    assert bool((lip_low <= lip_f * (1 + 1e-12) + 1e-300).all())
    assert bool((lip_low >= lip_f * (1 - 1e-6) - 1e-12).all())  # tight, up to saturation


def test_manifold_lower_with_a_nonlinear_output_is_below_the_exact_q():
    """h = x1 + x2^2/4: ker dh(x) = span(-x2/2, 1); q = v^T S v / v^T v exactly (mpmath)."""
    import mpmath

    from certify.search.witness import manifold_lower
    from certify.spec.system import System

    text = ('name = "t"\nstates = ["x1", "x2"]\noutputs = ["y"]\n'
            'f = ["-x1 + 0.5*x2", "0.25*x1*x2 - 0.125*x2"]\nh = ["x1 + 0.25*x2**2"]\n'
            "[box]\nX = [[-1.0, 1.0], [-1.0, 1.0]]\nY = [[-2.0, 2.0]]\n[design]\nlam = 0.25\n"
            "P = [[2.0, 0.5], [0.5, 1.0]]\n")
    system = System.from_text(text)
    P = mpmath.matrix([[2, 0.5], [0.5, 1]])
    pts = torch.tensor([[0.5, -0.75], [-0.25, 0.5], [0.0, 0.0]], dtype=torch.float64)
    low = manifold_lower(system, system.P, 0.25, pts)
    for (x1, x2), lo in zip(pts.tolist(), low.tolist()):
        with mpmath.workdps(40):
            J = mpmath.matrix([[-1, 0.5], [0.25 * mpmath.mpf(x2), 0.25 * mpmath.mpf(x1) - 0.125]])
            S = (P * J + (P * J).T) / 2 + mpmath.mpf(0.5) * P
            v = mpmath.matrix([-mpmath.mpf(x2) / 2, 1])
            q = (v.T * S * v)[0] / (v.T * v)[0]
        assert lo <= q and lo >= q - 1e-9, (lo, q)


# ----- the float32 screen can only ask for a float64 look, never decide ---------------------

class _LyingScreen:
    """A float32 'screen' that hides everything (-1000 at every point)."""

    def __init__(self, problem, lam=None, dtype=None, **kw):
        from certify.search.grid import GridKernel

        self.real = GridKernel(problem, lam, **kw) if dtype is None else None
        self.lam = self.real.lam if self.real is not None else lam

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        if self.real is not None:
            return self.real(z)
        return torch.full((z.shape[0],), -1000.0, dtype=torch.float32, device=z.device)


@pytest.mark.parametrize("which", ["tie", "corner"])
def test_a_lying_float32_screen_never_decides(monkeypatch, which):
    import certify.checks.mpdi as mpdi_module
    from certify.settings import VerifySettings

    from ..planted import planted_problem

    monkeypatch.setattr(mpdi_module, "GridKernel", _LyingScreen)
    problem = _tie_problem() if which == "tie" else planted_problem("corner")
    settings = VerifySettings(grid_points=5000, adversarial_starts=4, adversarial_steps=10,
                              max_boxes=400_000, float32_screen=True)
    r = mpdi_module.check_mpdi(problem, settings)
    if which == "tie":
        assert r.status.value in ("PROVED", "UNKNOWN")
    else:  # a real violation in 1e-6 of the volume: the prover still finds it, soundly
        assert r.status.value == "VIOLATED" and r.counterexamples[0].sound_bound > 0
