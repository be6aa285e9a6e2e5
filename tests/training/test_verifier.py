"""The training term on the prover's box bound (`training.verifier`): boxes inside X x Y at the
stated radii, the surrogate Taylor model encloses D at sampled points of its boxes, a few
optimiser steps on the term lower the prover's own sound bound over those boxes, and the
preset / CLI wiring (paper and certified: off unless asked)."""

from __future__ import annotations

import argparse
import copy

import numpy as np
import pytest
import torch

from certify.arith.taylor import TM
from certify.enclose.taylor import jcl_taylor, tm_lam_upper
from certify.errors import SettingsError
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.spec.system import load_system
from training.cegis import warm_start_network
from training.cegis_objective import CertObjective
from training.certified import cegis_settings
from training.collocation import collocation_points
from training.command import _config_from_args, add_train_arguments
from training.optim import Adam
from training.presets import make_config
from training.train import train
from training.verifier import VerifierPenalty, VerifierSettings, sample_boxes

K_VDP = torch.tensor([[14.0], [90.0]], dtype=torch.float64)
LAM = 0.5


def _curved_network(seed: int = 0) -> GainNetwork:
    system = load_system("vdp")
    net = warm_start_network(system, (8, 8), K=K_VDP, seed=seed)
    with torch.no_grad():
        g = torch.Generator().manual_seed(seed)
        net.layers[0].weight.mul_(2.0)
        net.layers[-1].weight.copy_(0.3 * torch.randn(net.layers[-1].weight.shape,
                                                      generator=g, dtype=torch.float64))
    return net


def _prover_bounds(system, net: GainNetwork, zc: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """The prover's first-order Taylor-model bound of lam_max(D), D = He{Jcl} + 2 LAM I
    (metric I), over the boxes zc +- r [B] (`jcl_taylor`, `tm_lam_upper`)."""
    net64 = copy.deepcopy(net).double()
    with torch.no_grad():
        J = jcl_taylor(system, net64, zc - r, zc + r)
        n = J.c.shape[-1]
        D = TM(J.c + J.c.transpose(1, 2) + 2 * LAM * torch.eye(n, dtype=torch.float64),
               J.g + J.g.transpose(1, 2), J.e + J.e.transpose(1, 2))
        return tm_lam_upper(D, r)[0]


def test_boxes_lie_inside_at_the_stated_radii():
    system = load_system("vdp")
    zc, r = sample_boxes(system, (0.25, 0.05), 40, seed=3)
    box = torch.as_tensor(np.concatenate([system.X, system.Y]))
    side = box[:, 1] - box[:, 0]
    assert zc.shape == r.shape == (80, 3)
    assert bool(((zc - r >= box[:, 0] - 1e-12) & (zc + r <= box[:, 1] + 1e-12)).all())
    torch.testing.assert_close(r[:40], (0.25 * side).expand(40, -1))
    torch.testing.assert_close(r[40:], (0.05 * side).expand(40, -1))
    assert torch.equal(sample_boxes(system, (0.25, 0.05), 40, seed=3)[0], zc)  # seeded


def test_the_surrogate_encloses_d_at_points_of_its_boxes():
    """The surrogate is not trusted, but it is the prover's formulas: at random points of each
    box, D lies in c + sum g u +- e (up to float64 rounding)."""
    system = load_system("vdp")
    net = _curved_network()
    pen = VerifierPenalty(system, VerifierSettings(weight=1.0, boxes=16), 0, lam=LAM,
                          P=torch.eye(2, dtype=torch.float64), K=K_VDP, dtype=torch.float64)
    M = pen.model(net.spec(torch.float64, detach=True))
    gen = torch.Generator().manual_seed(5)
    for _ in range(8):
        u = torch.rand(pen.zc.shape, generator=gen, dtype=torch.float64) * 2 - 1
        z = pen.zc + u * pen.r
        with torch.no_grad():
            Jk = gain_terms(system, net, z[:, :2], z[:, 2:]).dk_dx
            Jf = system.jac_f(z[:, :2])
        A = Jf + Jk  # P = I: D = A + 2 lam I in the model's (unsymmetrised) form
        D = A + 2 * LAM * torch.eye(2, dtype=torch.float64)
        lin = M.c + torch.einsum("bijd,bd->bij", M.g, u)
        assert bool(((D - lin).abs() <= M.e + 1e-9 * (1 + D.abs())).all())


def test_a_few_steps_on_the_term_lower_the_provers_bound():
    torch.set_num_threads(1)
    system = load_system("vdp")
    net = _curved_network().float()
    params = [t for layer in net.layers for t in (layer.weight, layer.bias)]
    for prm in params:
        prm.requires_grad_(True)
    xhat, y = collocation_points(system, 64, 0)
    st = VerifierSettings(weight=1.0, margin=0.05, boxes=32)
    pen = VerifierPenalty(system, st, 1, lam=LAM, P=torch.eye(2, dtype=torch.float64),
                          K=K_VDP)
    zc, r = sample_boxes(system, st.radii, st.boxes, 1)
    before = _prover_bounds(system, net, zc, r)
    obj = CertObjective(system, net, xhat, y, lam=LAM, P=torch.eye(2, dtype=torch.float64),
                        margin=0.05, mpdi_weight=0.0, workers=1, verifier=pen)
    first = obj.evaluate(grad=False)
    assert first.verifier > 0 and first.total == pytest.approx(first.verifier, rel=1e-6)
    opt = Adam(params, lr=1e-2)
    for _ in range(30):
        obj.evaluate(grad=True)
        opt.step()
    last = obj.evaluate(grad=False)
    obj.close()
    after = _prover_bounds(system, net, zc, r)
    assert last.verifier < 0.7 * first.verifier
    assert bool(torch.isfinite(after).all())
    assert float(after.median()) < float(before.median())
    assert float(after.mean()) < float(before.mean())


def test_weight_zero_is_off_and_the_flags_reach_the_settings():
    system = load_system("vdp")
    net = _curved_network().float()
    xhat, y = collocation_points(system, 32, 0)
    off = VerifierPenalty(system, VerifierSettings(weight=0.0, boxes=4), 0, lam=LAM,
                          P=torch.eye(2, dtype=torch.float64), K=K_VDP)
    obj = CertObjective(system, net, xhat, y, lam=LAM, P=torch.eye(2, dtype=torch.float64),
                        margin=0.05, workers=1, verifier=off)
    assert obj.verifier is None and obj.evaluate(grad=False).verifier == 0.0
    obj.close()
    assert make_config(system, "paper").verifier_weight == 0.0
    assert make_config(system, "certified").verifier_weight == 0.0
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    args = parser.parse_args(["vdp", "-o", "x.ckpt", "--preset", "certified",
                              "--verifier-weight", "0.3"])
    cfg = _config_from_args(args, system)
    assert cfg.verifier_weight == 0.3 and cegis_settings(cfg).verifier_weight == 0.3
    with pytest.raises(SettingsError, match=r"verifier_weight \(--verifier-weight\)"):
        make_config(system, "certified", verifier_weight=-1.0)
    with pytest.raises(ValueError, match="radii"):
        VerifierSettings(radii=(0.7,))


def test_plain_training_records_the_term_when_on():
    system = load_system("vdp")
    cfg = make_config(system, "tiny", adam_iters=4, lbfgs_iters=0, points=64, hidden=(6,),
                      verifier_weight=1e-2)
    res = train(system, cfg)
    assert len(res.history["adam"]["verifier"]) == 4
    assert res.history["adam"]["verifier"][0] > 0 and res.final["verifier"] > 0
    off = train(system, make_config(system, "tiny", adam_iters=4, lbfgs_iters=0, points=64,
                                    hidden=(6,)))
    assert off.final["verifier"] == 0.0
