"""The gain written once: every arithmetic and entry point against an independent reference,
for every activation; the activation through architecture, checkpoint, LipSDP and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from torch import nn

from certify.errors import CheckpointError, SettingsError
from certify.model import activations, checkpoint
from certify.model.gain import COLUMNS, ROWS, propagate
from certify.model.kernels import gain_terms, mpdi_lam_max, pointwise_rate
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.search.grid import GridKernel
from certify.simulate.integrate import GainFunction
from certify.spec.system import load_system
from training import losses
from training.collocation import collocation_points
from training.objective import Objective
from training.presets import make_config

from ..cli_helpers import FAST_POLICY, run_cli

NAMES = activations.names()
F64 = torch.float64


def _net(system, act: str, structure: str = "direct", with_K: bool = True, seed: int = 0,
         hidden=(7, 5)) -> GainNetwork:
    torch.manual_seed(seed)
    net = GainNetwork(system.n, system.p, hidden, structure=structure, activation=act).double()
    if with_K:
        net.K.copy_(torch.randn(system.n, system.p, dtype=F64) * 0.3)
    return net.requires_grad_(False)


def _reference_k(system, net: GainNetwork, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """k written independently: an nn.Sequential with the activation's torch module."""
    mods: list[nn.Module] = []
    for i, layer in enumerate(net.layers):
        mods.append(layer)
        if i < len(net.layers) - 1:
            mods.append(net.act.torch_module())
    out = nn.Sequential(*mods)(torch.cat([x, y], 1))
    r = y - system.h(x)
    k = out if net.structure == "direct" else \
        (out.reshape(-1, system.n, system.p) @ r[..., None])[..., 0]
    return k + r @ net.K.T


def _points(system, m: int = 6, seed: int = 0):
    x, y = collocation_points(system, m, seed)
    return x.to(F64), y.to(F64)


@pytest.mark.parametrize("act", NAMES)
@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_gain_and_jacobians_match_an_independent_autograd_reference(system3, act, structure):
    net = _net(system3, act, structure)
    x, y = _points(system3)
    terms = gain_terms(system3, net, x, y)
    torch.testing.assert_close(terms.k, _reference_k(system3, net, x, y), rtol=1e-12,
                               atol=1e-13)
    for i in range(len(x)):
        xi, yi = x[i:i + 1], y[i:i + 1]
        jx = torch.autograd.functional.jacobian(
            lambda v, yi=yi: _reference_k(system3, net, v[None], yi)[0], x[i])
        jy = torch.autograd.functional.jacobian(
            lambda v, xi=xi: _reference_k(system3, net, xi, v[None])[0], y[i])
        torch.testing.assert_close(terms.dk_dx[i], jx, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(terms.dk_dy[i], jy, rtol=1e-10, atol=1e-12)
    sim = GainFunction(system3, net)(x, y)
    torch.testing.assert_close(torch.from_numpy(sim), terms.k, rtol=1e-13, atol=1e-14)
    torch.testing.assert_close(net(torch.cat([x, y], 1)),
                               propagate(net.spec(), COLUMNS, torch.cat([x, y], 1), 0).value)


@pytest.mark.parametrize("act", NAMES)
def test_second_order_propagation_matches_autograd_hessian(act):
    torch.manual_seed(2)
    net = GainNetwork(2, 1, (5, 4), activation=act).double().requires_grad_(False)
    z = torch.randn(3, 3, dtype=F64)
    out = propagate(net.spec(), ROWS, z, 3, order=2, second_cols=2)
    assert out.hess.shape == (3, 2, 2, 3)
    for b in range(3):
        H = torch.autograd.functional.hessian(lambda v: net(v[None])[0, 1], z[b])
        torch.testing.assert_close(out.hess[b, 1], H[:2], rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.parametrize("act", NAMES)
def test_grid_kernel_columns_equal_rows_in_float64_and_float32(act, structure):
    system = load_system("vdp")
    net = _net(system, act, structure=structure, seed=1, hidden=(6, 6))
    problem = Problem(system, net, 1.0, np.array([[2.0, 0.3], [0.3, 1.0]]))
    x, y = _points(system, 50, 1)
    ref = mpdi_lam_max(system, net, problem.P_t, 1.0, x, y)
    z = torch.cat([x, y], 1)
    torch.testing.assert_close(GridKernel(problem)(z), ref, rtol=1e-11, atol=1e-11)
    v32 = GridKernel(problem, dtype=torch.float32)(z)
    assert v32.dtype == torch.float32
    torch.testing.assert_close(v32.double(), ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("act", ["silu", "gelu", "sigmoid", "elu"])
def test_training_objective_gradient_matches_autograd_for_other_activations(system3, act):
    torch.manual_seed(1)
    net = GainNetwork(3, 2, (7, 6), activation=act).double()
    x, y = collocation_points(system3, 23, 3)
    P = torch.as_tensor(system3.P)
    w = losses.LossWeights(0.7, 1.3, (0.5, 1.5, 2.5))
    obj = Objective(system3, net, x, y, lam=2.0, P=P, weights=w, loss="eigen", margin=0.1,
                    chunk_points=10, workers=2)
    values = obj.evaluate(grad=True)
    obj.close()
    from certify.model.kernels import contraction_matrix

    terms = gain_terms(system3, net, x, y, with_dy=False)
    D = contraction_matrix(system3.jac_f(x), terms.dk_dx, P, 2.0)
    mpdi = losses.eigen_loss(D, 0.1)
    bc = losses.bc_loss(gain_terms(system3, net, x, system3.h(x), with_dy=False).k)
    total = losses.total_loss(mpdi, bc, w)
    assert values.total == pytest.approx(total.item(), rel=1e-12, abs=1e-14)
    for got, ref in zip(obj.params, torch.autograd.grad(total, obj.params)):
        torch.testing.assert_close(got.grad, ref, rtol=1e-10, atol=1e-12)


def test_activation_travels_through_architecture_and_checkpoint(tmp_path):
    system = load_system("vdp")
    net = _net(system, "gelu")
    arch = net.architecture()
    assert arch["activation"] == "gelu"
    assert GainNetwork.from_architecture(arch).act is activations.get("gelu")
    old = {k: v for k, v in arch.items() if k != "activation"}  # written before activations
    assert GainNetwork.from_architecture(old).activation == "tanh"
    path = tmp_path / "g.ckpt"
    checkpoint.save(path, system=system, network=net, lam=1.0, P=np.eye(2))
    loaded = checkpoint.load(path).problem.network
    assert loaded.activation == "gelu"
    x, y = _points(system)
    torch.testing.assert_close(gain_terms(system, loaded, x, y).dk_dx,
                               gain_terms(system, net, x, y).dk_dx, rtol=0, atol=0)


def test_relu_checkpoint_and_config_are_refused_with_the_reason(tmp_path):
    system = load_system("vdp")
    with pytest.raises(ValueError, match="Theorem 1 needs a C\\^1 gain"):
        GainNetwork(2, 1, (4,), activation="relu")
    data_path = tmp_path / "t.ckpt"
    checkpoint.save(data_path, system=system, network=_net(system, "tanh"), lam=1.0,
                    P=np.eye(2))
    data = torch.load(data_path, weights_only=True)
    data["architecture"]["activation"] = "relu"
    torch.save(data, data_path)
    with pytest.raises(CheckpointError, match="bad architecture.*'relu' is refused.*discontinuous"):
        checkpoint.load(data_path)
    with pytest.raises(SettingsError, match=r"activation \(--activation\).*unknown activation"):
        make_config(system, "tiny", activation="mish")


@pytest.mark.parametrize("act", ["silu", "elu"])
@pytest.mark.slow
def test_prover_entry_points_bound_every_sampled_value_for_any_activation(act):
    """The prover reads the activation: every entry point runs on a non-tanh network and its
    sound upper bounds lie above the sampled values (mpdi, ||dk/dy||, ||k(x, h(x))||)."""
    from certify.checks.lipschitz import dk_dy_norms
    from certify.prove import mpdi as prover
    from certify.prove import side as side_proofs

    system = load_system("vdp")
    net = _net(system, act)
    problem = Problem(system, net, 1.0, np.eye(2))
    x, y = _points(system, 20, 3)
    # each proof ends on its 200 boxes; the time limit is only a safety net
    out = prover.prove_mpdi(problem, max_boxes=200)
    sampled = mpdi_lam_max(system, net, problem.P_t, 1.0, x, y)
    assert out.status.value in ("PROVED", "VIOLATED", "UNKNOWN")
    assert math.isfinite(out.upper) and out.upper >= float(sampled.max())
    dky = side_proofs.bound_dk_dy(problem, max_boxes=200)[0]
    assert dky is not None and dky >= float(dk_dy_norms(problem, torch.cat([x, y], 1)).max())
    res, _, _ = side_proofs.bound_residual(problem, max_boxes=200)
    k_on = gain_terms(system, net, x, system.h(x), with_dy=False).k
    assert res >= float(torch.linalg.vector_norm(k_on, dim=-1).max())
    rate = prover.prove_rate(problem, max_boxes=200)
    pointwise = pointwise_rate(system, net, problem.P_t, x, y)
    assert rate.lower is not None and rate.lower <= float(pointwise.min())


@pytest.mark.parametrize("act", ["silu", "sigmoid", "tanh"])
def test_lipsdp_in_the_activation_sector_bounds_every_sampled_gradient(act):
    from certify.checks.lipschitz import dk_dy_norms, lipsdp_for

    system = load_system("vdp")
    torch.manual_seed(4)
    net = GainNetwork(2, 1, (6, 6), activation=act).double().requires_grad_(False)
    with torch.no_grad():
        for prm in net.parameters():
            prm.mul_(2.0)
    problem = Problem(system, net, 1.0, np.eye(2))
    res = lipsdp_for(problem, method="clarabel" if act == "silu" else "ipm")
    assert res is not None and res.verified, res.message
    z = torch.cat(_points(system, 4000, 7), 1) * 3.0  # any xhat, y: LipSDP is global
    assert float(dk_dy_norms(problem, z).max()) <= res.value
    if act == "silu":  # the [0, 1] sector would be unsound for SiLU: it needs alpha < 0
        lo, hi = net.act.slope_bounds
        assert lo < 0 < 1 < hi


@pytest.mark.slow
def test_train_silu_then_run_end_to_end(tmp_path, capsys, monkeypatch):
    """`certify train --activation silu --preset tiny`, then `certify run`: the certificate
    names silu, its verdict and exit code agree, and its worst point is a real violation of
    the silu network (recomputed by the independent reference)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    code, out, err = run_cli(capsys, "train", "vdp", "--preset", "tiny", "--activation",
                             "silu", "-o", "silu.ckpt", "--quiet")
    assert code == 0, err
    ck = checkpoint.load(tmp_path / "silu.ckpt")
    assert ck.problem.network.activation == "silu"
    assert ck.training["config"]["activation"] == "silu"
    code, out, err = run_cli(capsys, "run", "silu.ckpt", "--json", "c.json", "--quiet")
    cert = json.loads((tmp_path / "c.json").read_text())
    assert cert["network"]["activation"] == "silu"
    expected = {"CERTIFIED": 0, "NOT CERTIFIED": 1, "INCONCLUSIVE": 3}[cert["verdict"]]
    assert code == expected, (code, cert["verdict"], err)
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] in ("VIOLATED", "PROVED", "UNKNOWN")  # the prover encloses silu
    lip = cert["checks"]["lipschitz"]  # its local bound comes from the prover, on silu
    assert lip["local_upper"] is not None and lip["sampled"] <= lip["local_upper"]
    if mpdi["status"] == "VIOLATED":
        assert code == 1
        w = mpdi["worst"]
        assert 0 < w["sound_bound"] <= w["value"]
        net, system = ck.problem.network, ck.problem.system
        x = torch.tensor([w["xhat"]], dtype=F64)
        y = torch.tensor([w["y"]], dtype=F64)
        J = torch.autograd.functional.jacobian(
            lambda v: _reference_k(system, net, v[None], y)[0], x[0])
        D = ck.problem.P_t @ (system.jac_f(x)[0] + J)
        D = 0.5 * (D + D.T) + 2.0 * ck.problem.lam * ck.problem.P_t
        assert float(torch.linalg.eigvalsh(D)[-1]) == pytest.approx(w["value"], rel=1e-9)
    if mpdi["status"] == "PROVED":  # no sampled violation
        assert code in (0, 3) and (mpdi["lower"] is None or mpdi["lower"] <= 0)
