"""Non-finite training: the ||dk/dy|| penalty at the zero gain, and every training loop stops
on a non-finite loss term, weight or gradient with one line and no checkpoint."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import training.cegis_objective as cegis_objective
import training.certified as certified
from certify.model import checkpoint
from certify.spec.system import load_system
from tests.cli_helpers import run_cli
from tests.planted import linear_system
from training.cegis import CegisSettings, cegis, warm_start_network
from training.cegis_objective import CertObjective, power_mean_norm
from training.collocation import collocation_points
from training.objective import NonFiniteGradient, TrainingDiverged, check_finite
from training.optim import Adam
from training.presets import make_config
from training.train import train

ROOT = Path(__file__).resolve().parents[2]


# ----- the penalty at zero ------------------------------------------------------------------

def test_penalty_is_zero_with_zero_gradient_at_the_zero_field():
    v = torch.zeros(5, 2, 1, requires_grad=True)
    lip = power_mean_norm((v * v).sum(dim=(1, 2)), 8.0)
    (g,) = torch.autograd.grad(lip, [v])
    assert float(lip.detach()) == 0.0
    assert torch.equal(g, torch.zeros_like(v))


@pytest.mark.parametrize("q", [1.0, 2.5, 8.0])
def test_penalty_is_the_power_mean_of_the_norms_with_finite_gradient(q):
    v = torch.randn(7, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    v[2] = 0.0  # one point with dk/dy = 0 among nonzero ones
    v.requires_grad_(True)
    lip = power_mean_norm((v * v).sum(dim=(1, 2)), q)
    norms = v.detach().flatten(1).norm(dim=1)
    assert float(lip.detach()) == pytest.approx(float((norms ** (2 * q)).mean() ** (1 / (2 * q))),
                                       rel=1e-12)
    (g,) = torch.autograd.grad(lip, [v])
    assert bool(torch.isfinite(g).all()) and torch.equal(g[2], torch.zeros_like(g[2]))
    assert float(g.abs().max()) > 0


def test_zero_warm_start_with_lip_penalty_trains_to_finite_weights():
    """K = 0 and the MLP's last layer zero: dk/dy = 0 at every point (the case that turned
    every weight to NaN)."""
    system = load_system("vdp")
    net = warm_start_network(system, (6,), seed=0).float()
    x, y = collocation_points(system, 64, 0)
    obj = CertObjective(system, net, x, y, lam=1.0, P=torch.eye(2, dtype=torch.float64),
                        margin=0.2, lip_weight=0.05, lip_power=8.0, workers=1)
    opt = Adam(obj.params, lr=1e-2)
    first = obj.evaluate(grad=True)
    assert obj.last_lip == 0.0 and obj.last_lip_max == 0.0
    assert all(bool(torch.isfinite(p.grad).all()) for p in obj.params)
    for _ in range(10):
        obj.evaluate(grad=True)
        opt.step()
    last = obj.evaluate(grad=False)
    obj.close()
    assert all(bool(torch.isfinite(p).all()) for p in obj.params)
    assert obj.last_lip > 0  # the gain moved off zero, and the penalty sees it
    assert last.mpdi < first.mpdi


# ----- the check ---------------------------------------------------------------------------

def test_check_finite_names_where_and_what():
    params = [torch.ones(2, 2), torch.ones(2)]
    check_finite({"total": 1.0, "mpdi": 0.5}, params, "here")  # all finite: no error
    with pytest.raises(TrainingDiverged, match=r"at adam iteration 3: the loss term bc is inf"):
        check_finite({"total": float("inf"), "bc": float("inf")}, params, "adam iteration 3")
    params[1][0] = float("nan")
    with pytest.raises(TrainingDiverged, match=r"at step 2: the layer 0 bias has a non-finite"):
        check_finite({"total": 1.0}, params, "step 2")
    params[1][0] = 1.0
    params[0].grad = torch.tensor([[0.0, float("nan")], [0.0, 0.0]])
    with pytest.raises(NonFiniteGradient, match=r"gradient of the layer 0 weight is NaN"):
        check_finite({"total": 1.0}, params, "step 2")
    params[0].grad[0, 1] = float("inf")
    with pytest.raises(TrainingDiverged, match=r"gradient of the layer 0 weight overflowed"):
        check_finite({"total": 1.0}, params, "step 2")
    check_finite({"total": 1.0}, params, "step 2", grad=False)  # gradients not checked


def _stiff_system(scale: float = 1e25):
    """A spec whose Jacobian entry `scale` squares past the training dtype's range in the
    MPDI loss (1e25: float32, 1e200: float64); rates large enough to do that are refused as
    input (`certify.spec.system.MAX_LAM`). The damping -2 keeps the pre-flight out of the way
    (q = -2 + 2 lam < 0 along ker C): what fails is the arithmetic, not the design."""
    return linear_system(A=[[0.0, 1.0], [-scale, -2.0]], C=[[1.0, 0.0]], lam=0.5,
                         name="stiff")


def test_plain_training_stops_on_overflow_naming_the_iteration():
    system = _stiff_system()
    with pytest.raises(TrainingDiverged, match=r"adam iteration 0: the loss term mpdi is"):
        train(system, make_config(system, "tiny", points=50))


def test_lbfgs_phase_is_checked_too():
    system = _stiff_system()
    with pytest.raises(TrainingDiverged, match=r"lbfgs iteration 0: the loss term mpdi is"):
        train(system, make_config(system, "tiny", points=50, adam_iters=0))


def _tiny_cegis(**kw) -> CegisSettings:
    base = dict(margin=0.2, mpdi_weight=1.0, rate_slack=0.0, lip_weight=0.05, lip_power=8.0,
                rounds=1, iters_per_round=5, lr=0.01, grid_points=500, adversarial_starts=2,
                adversarial_steps=2, proof_boxes=200, proof_seconds=5.0, budget_seconds=30.0,
                add_per_round=16, seed=0)
    base.update(kw)
    return CegisSettings(**base)


def test_cegis_stops_on_overflow_naming_round_and_step():
    system = linear_system(A=[[1.0]], C=[[1.0]], lam=0.5)
    with pytest.raises(TrainingDiverged, match=r"CEGIS round 1, Adam step 0: the loss term"):
        cegis(system, warm_start_network(system, (4,)), np.eye(1), 1e39, points=20,
              settings=_tiny_cegis())


def _old_penalty(s, q):
    """The penalty as it was: its gradient at the zero field is 0 * inf = NaN."""
    scale = s.detach().max().clamp_min(1e-30)
    return torch.sqrt(scale) * ((s / scale) ** q).mean() ** (1.0 / (2.0 * q))


def test_cegis_stops_on_a_nan_gradient_as_an_internal_error(monkeypatch):
    """The old penalty put back: the loop stops at the first step instead of writing NaN
    weights."""
    monkeypatch.setattr(cegis_objective, "power_mean_norm", _old_penalty)
    system = linear_system(A=[[1.0]], C=[[1.0]], lam=0.5)
    with pytest.raises(NonFiniteGradient, match=r"CEGIS round 1, Adam step 0: the gradient"):
        cegis(system, warm_start_network(system, (4,)), np.eye(1), 0.5, points=20,
              settings=_tiny_cegis())


# ----- through the command line ------------------------------------------------------------

@pytest.mark.slow
def test_cli_train_overflow_exits_2_with_one_line_and_no_checkpoint(tmp_path):
    out = tmp_path / "x.ckpt"
    spec = tmp_path / "stiff.toml"
    spec.write_text(_stiff_system().source)
    proc = subprocess.run([sys.executable, "-m", "certify", "train", str(spec), "--preset",
                           "tiny", "--points", "50", "-o", str(out), "--quiet"],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "training diverged at adam iteration 0: the loss term mpdi" in lines[0]
    assert not out.exists()


#: a metric that passes vdp's pre-flight at lam 2.5: q = P21 + P22 (1 - x1^2 + 2 lam) <= -0.6
#: (P = I fails it: q = 6 at the origin, and `certify train` stops before training)
VDP_METRIC = "[[146,-12],[-12,1.9]]"


def _small_certified(monkeypatch, **kw):
    small = dataclasses.replace(certified.DEFAULT_CEGIS, rounds=1, grid_points=500,
                                adversarial_starts=2, adversarial_steps=2, proof_boxes=200,
                                proof_seconds=5.0, improve_rounds=0, **kw)
    real = certified.cegis_settings
    monkeypatch.setattr(certified, "cegis_settings",
                        lambda config, base=small, **o: real(config, base, **o))


def test_cli_certified_with_a_metric_trains_from_the_zero_gain(monkeypatch, capsys, tmp_path):
    """--metric: no warm start (K = 0, dk/dy = 0 everywhere) and the ||dk/dy|| penalty on;
    this used to write a checkpoint of NaN weights."""
    _small_certified(monkeypatch)
    out = tmp_path / "m.ckpt"
    code, _, err = run_cli(capsys, "train", "vdp", "--preset", "certified", "--metric",
                           VDP_METRIC, "--points", "64", "--hidden", "6",
                           "--adam-iters", "5", "--curvature-weight", "0", "-o", str(out),
                           "--quiet")
    assert code in (0, 1), err
    net = checkpoint.load(out).problem.network
    assert all(bool(torch.isfinite(p).all()) for p in net.parameters())
    assert any(bool(p.abs().max() > 0) for p in net.layers[-1].parameters())  # it moved


def test_cli_certified_overflow_exits_2_and_writes_nothing(monkeypatch, capsys, tmp_path):
    _small_certified(monkeypatch)
    out = tmp_path / "m.ckpt"
    spec = tmp_path / "stiff.toml"
    spec.write_text(_stiff_system(1e200).source)
    code, _, err = run_cli(capsys, "train", str(spec), "--preset", "certified", "--metric",
                           "[[1,0],[0,1]]", "--points", "64", "--hidden", "6",
                           "--adam-iters", "5", "--curvature-weight", "0", "-o", str(out),
                           "--quiet")
    assert code == 2
    assert err.count("\n") == 1 and "CEGIS round 1, Adam step 0" in err
    assert not out.exists()


def test_cli_nan_gradient_is_an_internal_error_exit_4(monkeypatch, capsys, tmp_path):
    """A defect of the objective's derivative (the old penalty put back) is exit 4 with one
    line naming the round and step, and no checkpoint."""
    _small_certified(monkeypatch)
    monkeypatch.setattr(cegis_objective, "power_mean_norm", _old_penalty)
    out = tmp_path / "m.ckpt"
    code, _, err = run_cli(capsys, "train", "vdp", "--preset", "certified", "--metric",
                           VDP_METRIC, "--points", "64", "--hidden", "6",
                           "--adam-iters", "5", "--curvature-weight", "0", "-o", str(out),
                           "--quiet")
    assert code == 4
    assert err.count("\n") == 1 and "CEGIS round 1, Adam step 0: the gradient" in err
    assert not out.exists()
