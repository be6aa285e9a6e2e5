"""The certified preset's warm start: a memory-bounded joint LMI for the 6-state built-in
(its linear gain really makes D <= -margin on X), round 0 proves the warm start before Adam
moves it and raises the margin until it proves, and a training run whose CEGIS rounds never
prove returns the PROVED warm start instead of an unproved network."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from certify.design import metric as design_metric
from certify.model.kernels import gain_terms, mpdi_lam_max
from certify.results import Status
from certify.spec.system import load_system
from training import certified
from training.cegis import warm_start_network
from training.presets import make_config


def _box_points(system, count: int, seed: int) -> torch.Tensor:
    box = np.concatenate([system.X, system.Y])
    lo, hi = torch.as_tensor(box[:, 0]), torch.as_tensor(box[:, 1])
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(count, len(lo), generator=g, dtype=torch.float64)


def test_six_state_lmi_is_memory_bounded_and_really_certifies():
    """vdp3's default subdivision would build ~3 million vertex LMIs (past 16 GB); the bounded
    LMI uses at most MAX_SDP_VERTICES, and its gain makes lam_max(D) <= -margin at sampled
    points of X (the LMI holds on the hull of the Jacobian enclosure, so everywhere)."""
    vdp3 = load_system("vdp3")
    assert design_metric.default_vertex_count(vdp3) > design_metric.MAX_DEFAULT_VERTICES
    for name in ("vdp", "lorenz", "vdp2"):  # their preset keeps observer_lmi's subdivision
        assert design_metric.default_vertex_count(load_system(name)) <= \
            design_metric.MAX_DEFAULT_VERTICES
    margin = 4.0
    res = design_metric.bounded_observer_lmi(vdp3, vdp3.lam, margin=margin, kappa_max=1e4,
                                        gain_max=1e4)
    assert res.status is Status.PROVED, res.message
    assert res.solver["sdp_vertices"] <= design_metric.MAX_SDP_VERTICES
    assert res.solver["check_max_vertex_value"] <= -0.5 * margin
    net = warm_start_network(vdp3, (4,), K=np.asarray(res.K))
    z = _box_points(vdp3, 3000, seed=1)
    P = torch.as_tensor(res.P, dtype=torch.float64)
    values = mpdi_lam_max(vdp3, net, P, vdp3.lam, z[:, :6], z[:, 6:])
    assert float(values.detach().max()) <= -margin * (1 - 1e-9)


@pytest.mark.slow
def test_round0_tries_the_next_margin_until_the_warm_start_proves(monkeypatch):
    """When the warm start's round-0 proof ends without PROVED (here the first one is made to
    end UNKNOWN, as a budget-ended proof does), the LMI is solved at the next margin and that
    observer is proved for real; the network CEGIS starts from has the same gain."""
    import certify.prove.mpdi

    vdp3 = load_system("vdp3")
    config = make_config(vdp3, "certified")
    cs = certified.cegis_settings(config, proof_boxes=200_000)
    monkeypatch.setattr(certified, "WARM_MARGINS", (0.25, 0.5))
    monkeypatch.setattr(certified, "WARM_PROOF_SECONDS", 1e9)  # deterministic: boxes only
    real = certify.prove.mpdi.prove_mpdi
    calls: list[float] = []

    def first_ends_unknown(problem, **kw):
        calls.append(kw["max_boxes"])
        out = real(problem, **kw)
        if len(calls) == 1:
            return dataclasses.replace(out, status=Status.UNKNOWN)
        return out

    monkeypatch.setattr(certify.prove.mpdi, "prove_mpdi", first_ends_unknown)
    lines: list[str] = []
    net, P, info, proved = certified.proved_lmi_start(vdp3, vdp3.lam, config, cs,
                                                      lines.append)
    assert calls == [200_000, 200_000]
    assert [r["status"] for r in info["round0"]] == ["UNKNOWN", "PROVED"]
    assert info["margin"] == 0.5 and proved is not None
    observer, proof = proved
    assert proof.status is Status.PROVED and proof.upper <= 0
    assert len(lines) == 2 and "margin 0.5" in lines[1]
    z = _box_points(vdp3, 200, seed=2)
    r = z[:, 6:] - vdp3.h(z[:, :6])
    for gain in (net, observer):  # CEGIS's warm start and the proved observer: K (y - h)
        assert torch.equal(gain.K, net.K)
        assert torch.equal(gain_terms(vdp3, gain, z[:, :6], z[:, 6:]).k, r @ net.K.T)


def test_unproved_training_returns_the_proved_warm_start(monkeypatch):
    """CEGIS rounds that never prove (here: a stand-in that breaks the network) do not give an
    unproved checkpoint: the PROVED round-0 warm start comes back, with a note."""
    vdp = load_system("vdp")
    config = make_config(vdp, "certified", lam=2.5)

    def breaking_cegis(system, network, P, lam, *, settings, points, log):
        broken = warm_start_network(system, config.hidden, seed=1)
        with torch.no_grad():
            broken.layers[-1].weight.fill_(3.0)
        from training.cegis import CegisResult

        return CegisResult(network=broken, P=np.asarray(P), lam=lam, status=Status.UNKNOWN,
                           rounds=[], proof=None, xhat=torch.zeros(0, 2), y=torch.zeros(0, 1),
                           seconds=0.0, settings=settings)

    monkeypatch.setattr(certified, "cegis", breaking_cegis)
    out = certified.train_certified(vdp, config)
    assert out.status is Status.PROVED and out.cegis.proof is not None
    assert out.cegis.proof.status is Status.PROVED
    assert any("proved in round 0" in note for note in out.cegis.notes)
    assert float(out.network.layers[-1].weight.abs().max()) == 0.0  # MLP output zero
    assert out.start["round0"][0]["status"] == "PROVED"
    assert dataclasses.asdict(out.config)["lam"] == 2.5


@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_bounded_lmi_refuses_a_nonpositive_rate(bad):
    with pytest.raises(ValueError, match="lam must be > 0"):
        design_metric.bounded_observer_lmi(load_system("vdp3"), bad, margin=1.0, kappa_max=1e4,
                                      gain_max=1e4)
