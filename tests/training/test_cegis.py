"""Counterexample-guided certified training: the loss removes a planted violation, the loop
feeds counterexamples back, the warm start is the LMI gain exactly, a tiny run ends PROVED,
and the shipped certified example proves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from certify.model import checkpoint
from certify.model.kernels import gain_terms, mpdi_lam_max
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.spec.system import load_system
from tests.planted import linear_system
from training.cegis import CegisSettings, cegis, warm_start_network
from training.cegis_objective import CertObjective
from training.optim import Adam
from training.presets import make_config

ROOT = Path(__file__).resolve().parents[2]

# f = x, h = x on [-1, 1]: unstable, fully observed. With the zero gain,
# D = He{1 + dk/dxhat} + 2 lam = 2 > 0 at lam = 0.5 everywhere: a planted violation that a
# structural gain k = G (y - xhat) with G > 1.5 removes.
TINY = dict(A=[[1.0]], C=[[1.0]], lam=0.5)


def _tiny_settings(**kw: object) -> CegisSettings:
    base = dict(margin=0.2, mpdi_weight=1.0, rate_slack=0.0, lip_weight=0.0, rounds=6,
                iters_per_round=150, lr=0.02, grid_points=2000, adversarial_starts=4,
                adversarial_steps=10, proof_boxes=20_000, proof_seconds=10.0,
                budget_seconds=30.0, add_per_round=64, seed=0)
    base.update(kw)
    return CegisSettings(**base)  # type: ignore[arg-type]


@pytest.mark.slow
def test_eigen_loss_drives_a_planted_violation_away():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _planted_violation_goes_away()
    finally:
        torch.set_num_threads(threads)


def _planted_violation_goes_away() -> None:
    system = linear_system(**TINY)
    net = warm_start_network(system, (4,), seed=0).float()
    axis = torch.linspace(-1, 1, 16, dtype=torch.float64)
    grid = torch.cartesian_prod(axis, axis)
    xhat, y = grid[:, :1], grid[:, 1:]
    P = torch.eye(1, dtype=torch.float64)
    obj = CertObjective(system, net, xhat, y, lam=0.5, P=P, margin=0.2, workers=1)
    params = [t for layer in net.layers for t in (layer.weight, layer.bias)]
    for prm in params:
        prm.requires_grad_(True)
    first = obj.evaluate(grad=False)
    assert first.mpdi == pytest.approx(2.2, rel=1e-5)  # relu(2 + 0.2) at every point
    opt = Adam(params, lr=0.02)
    for _ in range(300):
        obj.evaluate(grad=True)
        opt.step()
    assert obj.evaluate(grad=False).mpdi == 0.0
    # ... and the violation is gone at fresh points, not just the training ones
    net64 = net.double().eval().requires_grad_(False)
    z = torch.rand(2000, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    z = 2 * z - 1
    v = mpdi_lam_max(system, net64, P, 0.5, z[:, :1], z[:, 1:])
    assert float(v.max()) < 0


@pytest.mark.slow
def test_loop_adds_the_counterexamples_it_finds():
    system = linear_system(**TINY)
    net = warm_start_network(system, (4,), seed=0)
    res = cegis(system, net, np.eye(1), 0.5, points=50,
                settings=_tiny_settings(rounds=1, iters_per_round=0))
    rnd = res.rounds[0]
    assert rnd.status == "VIOLATED" and rnd.max_lam_found == pytest.approx(2.0)
    assert rnd.added > 0
    assert res.xhat.shape[0] == 50 + rnd.added  # the set grew by what was added
    # the falsifier's point is among them: with no training, lam_max(D) there is the max found
    added = torch.cat([res.xhat, res.y], 1)[50:]
    vals = mpdi_lam_max(system, res.network, torch.eye(1, dtype=torch.float64), 0.5,
                        added[:, :1], added[:, 1:])
    assert float(vals.max()) == pytest.approx(rnd.max_lam_found, abs=1e-12)


@pytest.mark.slow
def test_tiny_certified_run_ends_proved():
    system = linear_system(**TINY)
    net = warm_start_network(system, (4,), seed=0)
    lines: list[str] = []
    res = cegis(system, net, np.eye(1), 0.5, points=100, settings=_tiny_settings(),
                log=lines.append)
    assert res.status is Status.PROVED
    assert res.proof is not None and res.proof.status is Status.PROVED
    assert lines and "round  1" in lines[0] and "proof" in lines[0]
    # an independent sound proof of the returned network
    out = prove_mpdi(Problem(system, res.network, 0.5, np.eye(1)), seconds=10)
    assert out.status is Status.PROVED


@pytest.mark.slow
def test_cegis_is_deterministic():
    system = linear_system(**TINY)
    a = cegis(system, warm_start_network(system, (4,)), np.eye(1), 0.5, points=100,
              settings=_tiny_settings(rounds=2, iters_per_round=20))
    b = cegis(system, warm_start_network(system, (4,)), np.eye(1), 0.5, points=100,
              settings=_tiny_settings(rounds=2, iters_per_round=20))
    for (ka, va), (kb, vb) in zip(a.network.state_dict().items(),
                                  b.network.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)


@pytest.mark.slow
def test_warm_start_is_exactly_the_lmi_gain():
    from training.baseline import make_lmi_baseline

    system = load_system("vdp")
    base, P, _ = make_lmi_baseline(system, 2.5)
    K = base.K.detach().clone()
    net = warm_start_network(system, (16, 16), K=K, structure="structural", seed=3)
    g = torch.Generator().manual_seed(0)
    box = np.concatenate([system.X, system.Y])
    lo, hi = torch.as_tensor(box[:, 0]), torch.as_tensor(box[:, 1])
    z = lo + (hi - lo) * torch.rand(500, 3, generator=g, dtype=torch.float64)
    t = gain_terms(system, net, z[:, :2], z[:, 2:])
    r = z[:, 2:] - system.h(z[:, :2])
    assert torch.equal(t.k, r @ K.T)
    C = system.jac_h(z[:, :2])
    assert torch.equal(t.dk_dx, -(K @ C))
    # ... so the warm start is certified before any training
    out = prove_mpdi(Problem(system, net, 2.5, P), seconds=20)
    assert out.status is Status.PROVED


def test_certified_preset_is_registered_and_paper_untouched():
    system = load_system("vdp")
    c = make_config(system, "certified")
    assert (c.structure, c.loss, c.hidden, c.lbfgs_iters) == ("structural", "eigen", (16, 16), 0)
    p = make_config(system, "paper")
    assert (p.structure, p.loss, p.hidden, p.points) == ("direct", "minors", (30,) * 5, 4000)


@pytest.mark.slow
def test_shipped_certified_example_proves():
    ck = checkpoint.load(ROOT / "examples" / "vdp_certified.ckpt")
    pb = ck.problem
    assert pb.system.name == "vdp" and pb.lam == 2.5 and pb.structural
    np.testing.assert_array_equal(pb.system.X, [[-2, 2], [-3, 3]])
    np.testing.assert_array_equal(pb.system.Y, [[-2, 2]])
    assert float(np.linalg.eigvalsh(pb.P)[0]) > 0 and not np.allclose(pb.P, np.eye(2))
    assert ck.training.get("preset") == "certified" and ck.training.get("status") == "PROVED"
    with torch.random.fork_rng(devices=[]):
        before = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            out = prove_mpdi(pb, seconds=60)
        finally:
            torch.set_num_threads(before)
    assert out.status is Status.PROVED and out.upper <= 0
