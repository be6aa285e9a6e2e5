"""The linear observer designed for the error bound (`certify.design.bound`), the `bound`
training preset (`training.bound`) and its command-line options.

Known answer: for x' = a x, y = x, the observer e' = (a - K) e - K v with V = P e^2 satisfies
V' <= -alpha V + mu v^2 iff c = 2 (K - a) - alpha > 0 and mu >= P K^2 / c (P = 1 at the
optimum: the problem is homogeneous and P >= 1). Minimising over K: for s = 2 a + alpha > 0,
K* = s and mu* = s; for s <= 0, K = 0 and mu* = 0.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.design import sdp
from certify.design.bound import (
    design_bound_observer,
    design_vertices,
    joint_values,
    required_mu,
    sampled_bound,
)
from certify.design.metric import output_matrix
from certify.results import Status
from certify.spec.system import System, load_system


def scalar_system(a: float) -> System:
    return System.from_text(f"""name = "lin1"
states = ["x"]
outputs = ["y"]
f = ["{a!r}*x"]
h = ["x"]
[box]
X = [[-1.0, 1.0]]
Y = [[-1.0, 1.0]]
[design]
lam = 0.5
P = [[1.0]]
""")


def closed_form(a: float, alpha: float) -> tuple[float, float]:
    """(mu*, K*) of the scalar problem."""
    s = 2.0 * a + alpha
    return (s, s) if s > 0 else (0.0, 0.0)


@pytest.mark.parametrize("a, alpha", [(1.0, 2.0), (0.5, 1.0), (3.0, 0.5)])
def test_scalar_design_equals_the_closed_form_optimum(a: float, alpha: float) -> None:
    d = design_bound_observer(scalar_system(a), alpha=alpha, margin=1e-7)
    mu, K = closed_form(a, alpha)
    assert d.status is Status.PROVED
    assert d.alpha == alpha
    assert d.mu == pytest.approx(mu, rel=1e-4)
    assert float(d.K[0, 0]) == pytest.approx(K, rel=1e-3)
    assert float(d.P[0, 0]) == pytest.approx(1.0, rel=1e-4)
    assert d.per_unit_noise == pytest.approx(math.sqrt(mu / alpha), rel=1e-4)
    assert d.bound(0.15) == pytest.approx(0.15 * math.sqrt(mu / alpha), rel=1e-4)
    assert d.lam() == pytest.approx(0.98 * alpha / 4)


def test_a_stable_scalar_plant_needs_no_injection() -> None:
    d = design_bound_observer(scalar_system(-2.0), alpha=1.0, margin=1e-7)
    assert d.status is Status.PROVED
    assert d.mu == pytest.approx(0.0, abs=1e-5)
    assert abs(float(d.K[0, 0])) < 1e-3


@settings(max_examples=12, deadline=None)
@given(a=st.floats(-1.0, 3.0), alpha=st.floats(0.2, 5.0))
def test_scalar_sdp_optimum_property(a: float, alpha: float) -> None:
    res = sdp.dissipation_sdp(np.array([[[a]]]), np.array([[1.0]]), alpha, margin=1e-8)
    mu, _ = closed_form(a, alpha)
    assert res.status is Status.PROVED
    assert res.value == pytest.approx(mu, rel=1e-3, abs=1e-5)
    # never below the true optimum by more than the solver's tolerance
    assert res.value >= mu - 1e-4 * (1.0 + mu)


def test_rate_search_on_the_scalar_system_follows_the_closed_form() -> None:
    # mu*/alpha = 1 + 2 a / alpha decreases in alpha for a > 0: the search ends at the top
    # of its range, and the bound it reports is the closed form's at the alpha it chose
    d = design_bound_observer(scalar_system(1.0), alpha_range=(0.1, 10.0), margin=1e-7)
    assert d.status is Status.PROVED
    assert d.alpha > 5.0
    assert d.per_unit_noise == pytest.approx(math.sqrt(1.0 + 2.0 / d.alpha), rel=1e-3)
    assert all(t["alpha"] >= 0.1 for t in d.tried)


def test_a_rate_floor_is_respected() -> None:
    d = design_bound_observer(scalar_system(-1.0), min_alpha=3.0, margin=1e-7)
    assert d.status is Status.PROVED
    assert d.alpha >= 3.0
    assert all(t["alpha"] >= 3.0 for t in d.tried)


def test_required_mu_is_the_closed_form_for_a_scalar_linear_gain() -> None:
    # D(alpha/4) = P (a - K) + alpha/2 P, B = K: mu = P K^2 / (2 (K - a) - alpha)
    a, K, P, alpha = 1.0, 5.0, 2.0, 1.5
    D = torch.tensor([[[P * (a - K) + 0.5 * alpha * P]]], dtype=torch.float64)
    B = torch.tensor([[[K]]], dtype=torch.float64)
    assert required_mu(D, B, np.array([[P]])) == pytest.approx(P * K * K / (2 * (K - a) - alpha))
    # a D that is not negative definite gives no finite mu
    assert required_mu(-D, B, np.array([[P]])) == math.inf


def test_sampled_bound_of_the_scalar_design_network() -> None:
    from training.bound import linear_network
    from training.presets import make_config

    system = scalar_system(1.0)
    d = design_bound_observer(system, alpha=2.0, margin=1e-7)
    net = linear_network(system, d, make_config(system, "bound", hidden=(4,)))
    got = sampled_bound(system, net, d.P, d.alpha, points=200)
    assert got["mu"] == pytest.approx(d.mu, rel=1e-4)  # a linear gain: the same everywhere


@pytest.fixture(scope="module")
def vdp_design():
    system = load_system("vdp")
    return system, design_bound_observer(system, subdivisions=8, grid_points=4, golden_steps=3)


def test_vdp_design_satisfies_every_vertex_lmi_with_margin(vdp_design) -> None:
    system, d = vdp_design
    assert d.status is Status.PROVED
    C = output_matrix(system)
    _, full, _ = design_vertices(system, subdivisions=8)
    vals = joint_values(full, d.P, d.K, C, d.alpha, d.mu)
    assert float(vals.max()) <= -0.5e-3
    assert float(np.linalg.eigvalsh(d.P)[0]) >= 1.0 - 1e-6
    # and at real Jacobians of points of X (inside the enclosures' hull)
    gen = torch.Generator().manual_seed(3)
    X = torch.as_tensor(system.X, dtype=torch.float64)
    x = X[:, 0] + (X[:, 1] - X[:, 0]) * torch.rand(2000, 2, generator=gen, dtype=torch.float64)
    assert float(joint_values(system.jac_f(x).numpy(), d.P, d.K, C, d.alpha, d.mu).max()) < 0
    # the bound is a real one: well inside the box's half-diagonal
    assert d.bound(0.15) < 0.5 * float(np.linalg.norm(system.X[:, 1] - system.X[:, 0]))


def test_learned_attempt_reports_its_outcome_in_one_line() -> None:
    from training.bound import LearnSettings, train_bound
    from training.presets import make_config

    system = scalar_system(1.0)
    config = make_config(system, "bound", hidden=(4,), points=64)
    res = train_bound(system, config, rate=0.5,
                      learn=LearnSettings(rounds=1, steps=3, eval_points=64, add_per_round=8),
                      prove=False)
    att = res.attempt
    assert att is not None and len(att.rounds) == 1
    if att.beat:  # a linear gain is optimal here; a win could only be a sampling artefact
        assert att.sampled_learned < att.sampled_linear
    else:
        assert res.returned == "linear"
        assert att.message.startswith("the learned gain did not beat the linear design: "
                                      "sampled bound ")
        assert att.message.endswith("returning the linear design")
    rec = res.record()
    assert rec["preset"] == "bound" and rec["learned"]["rounds"]


def test_train_help_lists_the_bound_preset_and_min_rate(capsys) -> None:
    from certify.cli.main import main

    assert main(["train", "--help"]) == 0
    text = capsys.readouterr().out
    assert "bound:" in text and "--min-rate" in text


def test_min_rate_with_another_preset_is_refused(tmp_path, capsys) -> None:
    from certify.cli.main import main

    out = tmp_path / "x.ckpt"
    code = main(["train", "vdp", "--preset", "tiny", "--min-rate", "1", "-o", str(out)])
    assert code == 2
    assert "--min-rate" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("extra, word", [(["--min-rate", "1", "--lam", "1"], "--min-rate"),
                                         (["--metric", "[[1,0],[0,1]]"], "--metric")])
def test_bound_preset_refuses_conflicting_options(tmp_path, capsys, extra, word) -> None:
    from certify.cli.main import main

    out = tmp_path / "x.ckpt"
    assert main(["train", "vdp", "--preset", "bound", *extra, "-o", str(out)]) == 2
    assert word in capsys.readouterr().err
    assert not out.exists()


def test_search_pairs_each_point_with_the_most_dangerous_gain() -> None:
    from training.bound import worst_pair_eigs

    system = scalar_system(1.0)
    d = design_bound_observer(system, alpha=2.0, margin=1e-7)
    from training.bound import linear_network
    from training.presets import make_config

    net = linear_network(system, d, make_config(system, "bound", hidden=(4,)))
    x = torch.linspace(-1, 1, 7, dtype=torch.float64)[:, None]
    got = worst_pair_eigs(system, net, d.P, d.alpha, 3.0, x, x)
    P, K = float(d.P[0, 0]), float(d.K[0, 0])
    want = P * (1.0 - K) + 0.5 * d.alpha * P + (P * K) ** 2 / 6.0  # D(alpha/4) + (PK)^2/(2 mu)
    assert torch.allclose(got, torch.full_like(got, want), rtol=1e-9)


@pytest.mark.slow
def test_bound_preset_writes_a_checkpoint_whose_contraction_is_proved(tmp_path) -> None:
    from certify.model import checkpoint
    from certify.model.problem import Problem
    from certify.prove.mpdi import prove_mpdi
    from training.bound import save_bound, train_bound
    from training.presets import make_config

    system = load_system("vdp")
    config = make_config(system, "bound", adam_iters=0, hidden=(4,))
    res = train_bound(system, config, subdivisions=8, prove=False)
    path = tmp_path / "vdp_bound.ckpt"
    save_bound(path, system, res)
    ck = checkpoint.load(path)
    assert ck.problem.lam == pytest.approx(0.98 * res.design.alpha / 4)
    assert np.allclose(ck.problem.P, res.design.P)
    assert np.allclose(ck.problem.network.K.numpy(), res.design.K)
    assert ck.training["preset"] == "bound" and ck.training["returned"] == "linear"
    out = prove_mpdi(Problem(system, ck.problem.network, ck.problem.lam, ck.problem.P),
                     estimate_points=0)
    assert out.status is Status.PROVED
