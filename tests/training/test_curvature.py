"""The verification-aware training term (`training.curvature`): zero for a linear gain,
positive for a curved one, lowered by a few optimiser steps through the training objective,
pairs at the stated distance inside the box, and the preset / CLI wiring (paper: off)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from certify.errors import SettingsError
from certify.model.network import GainNetwork
from certify.spec.system import load_system
from training.cegis import warm_start_network
from training.cegis_objective import CertObjective
from training.certified import cegis_settings
from training.collocation import collocation_points
from training.command import _config_from_args, add_train_arguments
from training.curvature import CurvaturePenalty, CurvatureSettings, sample_pairs
from training.optim import Adam
from training.presets import CERTIFIED_CURVATURE_WEIGHT, make_config
from training.train import train

K_VDP = torch.tensor([[14.0], [90.0]], dtype=torch.float64)


def _curved_network(seed: int = 0) -> GainNetwork:
    """vdp structural gain with a nonzero, visibly nonlinear MLP (and the K term)."""
    system = load_system("vdp")
    net = warm_start_network(system, (8, 8), K=K_VDP, seed=seed)
    with torch.no_grad():
        g = torch.Generator().manual_seed(seed)
        net.layers[0].weight.mul_(3.0)
        net.layers[-1].weight.copy_(torch.randn(net.layers[-1].weight.shape, generator=g,
                                                dtype=torch.float64))
    return net


def test_pairs_are_inside_the_box_at_the_stated_distance():
    system = load_system("vdp")
    z1, z2 = sample_pairs(system, 300, 0.03, seed=4)
    box = np.concatenate([system.X, system.Y])
    lo, hi = torch.as_tensor(box[:, 0]), torch.as_tensor(box[:, 1])
    for z in (z1, z2):
        assert bool(((z >= lo) & (z <= hi)).all())
    dist = ((z2 - z1) / (hi - lo)).norm(dim=1)
    np.testing.assert_allclose(dist.numpy(), 0.03, rtol=1e-12)
    a, _ = sample_pairs(system, 300, 0.03, seed=4)
    assert torch.equal(a, z1)  # seeded


def test_zero_for_a_linear_gain_positive_for_a_curved_one():
    system = load_system("vdp")  # h = x1 is linear, so K (y - h) has a constant Jacobian
    pen = CurvaturePenalty(system, CurvatureSettings(weight=1.0, pairs=128), 0,
                           torch.float64)
    linear = warm_start_network(system, (8, 8), K=K_VDP, seed=0)  # zero MLP output
    assert float(pen.value(linear.spec()).detach()) == 0.0
    curved = _curved_network()
    c = float(pen.value(curved.spec()).detach())
    assert c > 1.0
    # ... and it is the finite difference it claims: ||J(z1) - J(z2)||_F^2 / r^2, averaged
    from certify.model.kernels import gain_terms
    z1, z2 = sample_pairs(system, 128, 0.02, 0)
    with torch.no_grad():
        j1 = gain_terms(system, curved, z1[:, :2], z1[:, 2:]).dk_dx
        j2 = gain_terms(system, curved, z2[:, :2], z2[:, 2:]).dk_dx
    ref = float(((j1 - j2) ** 2).sum(dim=(1, 2)).mean()) / 0.02 ** 2
    assert c == pytest.approx(ref, rel=1e-9)
    # the tolerance removes what lies below it
    lenient = CurvaturePenalty(system, CurvatureSettings(weight=1.0, pairs=128, tol=1e12), 0,
                               torch.float64)
    assert float(lenient.value(curved.spec()).detach()) == 0.0


def test_a_few_steps_through_the_training_objective_lower_it():
    torch.set_num_threads(1)
    system = load_system("vdp")
    net = _curved_network().float()
    params = [t for layer in net.layers for t in (layer.weight, layer.bias)]
    for prm in params:
        prm.requires_grad_(True)
    xhat, y = collocation_points(system, 64, 0)
    pen = CurvaturePenalty(system, CurvatureSettings(weight=1.0, pairs=64), 1)
    # the term alone (the eigenvalue loss weighted 0): its gradient reaches the weights
    obj = CertObjective(system, net, xhat, y, lam=2.5, P=torch.eye(2, dtype=torch.float64),
                        margin=0.2, mpdi_weight=0.0, workers=1, curvature=pen)
    first = obj.evaluate(grad=False)
    assert first.curv > 0 and first.total == pytest.approx(first.curv, rel=1e-6)
    opt = Adam(params, lr=1e-2)
    for _ in range(10):
        obj.evaluate(grad=True)
        opt.step()
    assert obj.evaluate(grad=False).curv < 0.7 * first.curv
    obj.close()


def test_weight_zero_leaves_the_objective_unchanged():
    system = load_system("vdp")
    net = _curved_network().float()
    xhat, y = collocation_points(system, 64, 0)
    off = CurvaturePenalty(system, CurvatureSettings(weight=0.0, pairs=16), 0)
    obj = CertObjective(system, net, xhat, y, lam=2.5, P=torch.eye(2, dtype=torch.float64),
                        margin=0.2, workers=1, curvature=off)
    assert obj.curvature is None and obj.evaluate(grad=False).curv == 0.0


def test_presets_and_flags():
    system = load_system("vdp")
    assert make_config(system, "paper").curvature_weight == 0.0
    assert make_config(system, "tiny").curvature_weight == 0.0
    cert = make_config(system, "certified")
    assert cert.curvature_weight == CERTIFIED_CURVATURE_WEIGHT > 0
    cs = cegis_settings(cert)
    assert (cs.curv_weight, cs.curv_radius) == (cert.curvature_weight, cert.curvature_radius)
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    args = parser.parse_args(["vdp", "-o", "x.ckpt", "--preset", "certified",
                              "--curvature-weight", "0", "--curvature-radius", "0.05"])
    c = _config_from_args(args, system)
    assert (c.curvature_weight, c.curvature_radius) == (0.0, 0.05)
    with pytest.raises(SettingsError, match=r"curvature_weight \(--curvature-weight\)"):
        make_config(system, "certified", curvature_weight=-1.0)
    with pytest.raises(SettingsError, match=r"curvature_radius \(--curvature-radius\)"):
        make_config(system, "certified", curvature_radius=0.7)


def test_plain_training_records_the_term_when_on():
    system = load_system("vdp")
    cfg = make_config(system, "tiny", adam_iters=5, lbfgs_iters=0, points=64, hidden=(6,),
                      curvature_weight=1e-3)
    res = train(system, cfg)
    assert len(res.history["adam"]["curv"]) == 5 and res.history["adam"]["curv"][0] > 0
    assert res.final["curv"] > 0
    off = train(system, make_config(system, "tiny", adam_iters=5, lbfgs_iters=0, points=64,
                                    hidden=(6,)))
    assert off.final["curv"] == 0.0
