"""SDP layer: LipSDP-Neuron (verified), metric synthesis, the LMI observer and its baseline."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from certify.checks.lipschitz import (
    LOCAL_ROOM,
    check_lipschitz,
    lipsdp_for,
    mlp_in_y,
    naive_bound,
    sampled_lower,
)
from certify.design import lipsdp, sdp
from certify.design.metric import (
    enclosure_vertices,
    kernel_basis,
    observer_lmi,
    observer_values,
    output_matrix,
    sub_boxes,
    synthesize_metric,
)
from certify.model import checkpoint
from certify.model.kernels import mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.results import (
    LipschitzResult,
    MetricResult,
    ProofStats,
    Status,
    from_jsonable,
    to_jsonable,
)
from certify.spec.system import load_system
from tests.conftest import random_network


def _problem(net: GainNetwork, name: str = "vdp", P: np.ndarray | None = None) -> Problem:
    system = load_system(name)
    return Problem(system, net, 2.5, np.eye(system.n) if P is None else P)


# ----- LipSDP ---------------------------------------------------------------------------

@pytest.mark.parametrize("hidden,seed", [((6, 5), 0), ((4, 4, 4), 1), ((7,), 2), ((5, 3), 3)])
def test_lipsdp_between_sampled_and_naive_and_recheck_passes(hidden, seed):
    net = random_network(2, 1, hidden=hidden, seed=seed, scale=2.0)
    pr = _problem(net)
    res = lipsdp_for(pr)
    assert res.status is Status.PROVED and res.verified
    assert res.check_max_eig <= -res.check_tolerance
    lower, _ = sampled_lower(pr, points=4000, steps=30)
    naive = naive_bound(pr.network, 2)
    assert lower <= res.value * (1 + 1e-9)
    assert res.value <= naive * (1 + 1e-9)
    # the re-check is independent: rebuild the LMI at the returned multipliers
    Ws, Wo = mlp_in_y(pr.network, 2)
    K = pr.network.K.numpy()
    M = lipsdp.lipsdp_lmi(Ws, Wo, K, res.variables["t"], res.variables["rho_verified"])
    assert np.linalg.eigvalsh(M)[-1] < 0
    assert all(np.all(t >= 0) for t in res.variables["t"])


@pytest.mark.slow
def test_lipsdp_5x30_within_budget_and_bounds():
    net = random_network(2, 1, hidden=(30,) * 5, seed=4)
    pr = _problem(net)
    res = lipsdp_for(pr)
    assert res.status is Status.PROVED and res.verified  # speed: bench/lipsdp.py
    lower, _ = sampled_lower(pr, points=2000, steps=20)
    assert lower <= res.value <= naive_bound(pr.network, 2)


@pytest.mark.parametrize("widths", [(1,), (1, 1), (1, 1, 1)])
def test_lipsdp_exact_on_scalar_chain(widths):
    """k(y) = w_out tanh(... tanh(w1 y)): L = |w1 ... w_H| ||w_out|| exactly (slopes 1 at 0)."""
    rng = np.random.default_rng(len(widths))
    Ws = [rng.uniform(0.5, 2.0, size=(1, 1)) * rng.choice([-1, 1]) for _ in widths]
    Wo = rng.normal(size=(2, 1))
    exact = float(np.prod([abs(W[0, 0]) for W in Ws]) * np.linalg.norm(Wo))
    res = lipsdp.lipsdp_neuron(Ws, Wo, None)
    assert res.status is Status.PROVED
    assert res.value == pytest.approx(exact, rel=1e-5)
    assert res.value >= exact * (1 - 1e-12)  # an upper bound, never below the truth


def test_lipsdp_with_linear_skip_beats_triangle_inequality():
    net = random_network(2, 1, hidden=(6, 5), seed=5, scale=2.0)
    with torch.no_grad():
        net.K.copy_(torch.tensor([[1.0], [2.0]], dtype=torch.float64))
    pr = _problem(net)
    joint = lipsdp_for(pr).value
    Ws, Wo = mlp_in_y(pr.network, 2)
    alone = lipsdp.lipsdp_neuron(Ws, Wo, None).value
    assert joint <= alone + math.sqrt(5.0) + 1e-9
    lower, _ = sampled_lower(pr, points=4000, steps=30)
    assert lower <= joint * (1 + 1e-9)


@pytest.mark.slow
def test_ipm_agrees_with_clarabel_chordal_form():
    net = random_network(2, 1, hidden=(8, 6, 5), seed=6, scale=1.5)
    Ws, Wo = mlp_in_y(net.double(), 2)
    K = net.K.numpy()
    a = lipsdp.lipsdp_neuron(Ws, Wo, K, method="ipm")
    b = lipsdp.lipsdp_neuron(Ws, Wo, K, method="clarabel")
    assert a.status is b.status is Status.PROVED
    assert b.solver == "CLARABEL" and b.iterations and b.raw_status == "optimal"
    assert a.value == pytest.approx(b.value, rel=1e-5)


def test_recheck_inflates_rho_and_refuses_bad_multipliers():
    rng = np.random.default_rng(7)
    Ws = [rng.normal(size=(4, 1)), rng.normal(size=(3, 4))]
    Wo = rng.normal(size=(2, 3))
    res = lipsdp.lipsdp_neuron(Ws, Wo, None)
    t, rho = res.variables["t"], res.variables["rho"]
    rho_ok, top, tol = lipsdp.check_lipsdp_lmi(Ws, Wo, None, t, 0.5 * rho)  # rho too small
    assert rho_ok is not None and rho_ok >= rho * (1 - 1e-6) and top <= -tol
    # zero multipliers: the hidden block is W_out^T W_out >= 0, no rho can verify it
    assert lipsdp.check_lipsdp_lmi(Ws, Wo, None, [np.zeros(4), np.zeros(3)], 1e6)[0] is None
    # negative multipliers are clipped (they would void the S-procedure)
    neg = [-np.abs(ti) for ti in t]
    assert lipsdp.check_lipsdp_lmi(Ws, Wo, None, neg, 1e6)[0] is None


def test_lipsdp_refuses_nonfinite_weights():
    res = lipsdp.lipsdp_neuron([np.array([[np.nan]])], np.ones((1, 1)))
    assert res.status is Status.ERROR and res.value is None


@pytest.mark.slow
def test_check_lipschitz_direct_and_structural():
    pr = _problem(random_network(2, 1, hidden=(6, 5), seed=8))
    r = check_lipschitz(pr, sample_points=2000)
    assert r.status is Status.PROVED and r.which in ("lipsdp", "naive")
    assert r.lipsdp_verified and r.sampled <= r.value <= r.naive * (1 + 1e-12)
    assert r.lipsdp_P == r.lipsdp  # P = I
    again = from_jsonable(LipschitzResult, to_jsonable(r))
    assert again.value == r.value
    # a passed local bound smaller than LipSDP is used, and named
    r2 = check_lipschitz(pr, sample_points=2000, local_upper=r.sampled * 1.0001)
    assert r2.which == "local" and r2.value == pytest.approx(r.sampled * 1.0001)
    # structural: LipSDP does not apply
    ps = _problem(random_network(2, 1, hidden=(6, 5), seed=9, structure="structural"))
    rs = check_lipschitz(ps, sample_points=2000)
    assert rs.lipsdp is None and rs.which == "local" and rs.status is Status.PROVED
    assert rs.sampled <= rs.value
    assert "not applicable" in rs.message


@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_networks_without_hidden_layers_get_sound_lipschitz_bounds(structure):
    """N(z) = W0 z + b (no hidden layer, no activation): for the direct form k is affine in
    y and L = ||W0y + K||_2 exactly (closed form); the structural bound reads |G| from W0
    and the box, not from the activation's range. Small weights used to expose the old
    reading of W0 as a hidden layer followed by an output layer W0 (naive ||W0y|| ||W0||,
    below the true constant when ||W0|| < 1)."""
    net = random_network(2, 1, hidden=(), seed=3, structure=structure, scale=0.1)
    with torch.no_grad():
        net.K.zero_()
    pr = _problem(net)
    r = check_lipschitz(pr, sample_points=2000)
    assert r.status is Status.PROVED
    assert r.sampled <= r.value * (1 + 1e-12) and r.sampled <= r.naive * (1 + 1e-12)
    if structure == "direct":
        W = net.layers[0].weight.detach().numpy()
        exact = np.linalg.norm(W[:, 2:], 2)
        assert r.which == "lipsdp" and r.lipsdp == pytest.approx(exact, rel=1e-11)
        assert r.sampled == pytest.approx(exact, rel=1e-9)


def test_local_lipschitz_proof_runs_only_where_the_global_bound_leaves_room():
    """k affine in y: LipSDP is exact (= the sampled value), so the local dk/dy proof is not
    run (it could lower L by < LOCAL_ROOM, and its entry-magnitude bound, exact only for
    p = 1, would spend the whole budget); a deep network whose LipSDP is well above the
    sampled value gets the local proof, and its smaller bound is used."""
    calls = []

    def local(value: float):
        def run() -> tuple[float, ProofStats]:
            calls.append(value)
            return value, ProofStats(boxes_processed=1)
        return run

    affine = _problem(random_network(2, 1, hidden=(), seed=3))
    r = check_lipschitz(affine, sample_points=2000, local=local(1e9))
    assert calls == [] and r.which == "lipsdp" and r.local_upper is None
    assert r.value <= r.sampled * (1 + LOCAL_ROOM) and "local proof not run" in r.message
    deep = _problem(random_network(2, 1, hidden=(6, 5), seed=8, scale=2.0))
    g = check_lipschitz(deep, sample_points=2000)
    assert g.value > g.sampled * (1 + LOCAL_ROOM)  # room for a local bound
    target = g.sampled * (1 + LOCAL_ROOM / 2)
    r2 = check_lipschitz(deep, sample_points=2000, local=local(target))
    assert calls == [target] and r2.which == "local" and r2.value == target


def test_lipschitz_metric_weighted_variant():
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    pr = _problem(random_network(2, 1, hidden=(6, 5), seed=10), P=P)
    r = check_lipschitz(pr, sample_points=2000)
    R = np.linalg.cholesky(P)  # ||P^(1/2) v|| = ||R^T v||
    nP = math.sqrt(np.linalg.eigvalsh(P)[-1])
    assert r.lipsdp_P is not None and r.lipsdp_P <= nP * r.lipsdp * (1 + 1e-6)
    assert R is not None


# ----- metric synthesis ------------------------------------------------------------------

def test_metric_vdp_found_with_cond_at_least_146():
    r = synthesize_metric(load_system("vdp"), 2.5)
    assert r.status is Status.PROVED
    P = np.array(r.P)
    assert 146.0 <= r.condition_number <= 150.0
    # the kernel condition P21 + P22 (1 - x1^2 + 2 lam) <= -margin, worst at x1 = 0
    assert P[1, 0] + P[1, 1] * 6.0 <= -0.5 * r.margin  # solver tolerance: re-check at margin/2
    assert np.linalg.eigvalsh(P)[0] >= 1 - 1e-6
    assert from_jsonable(MetricResult, to_jsonable(r)).condition_number == r.condition_number


def test_metric_duffing_no_constant_P_with_witness():
    r = synthesize_metric(load_system("duffing"), 2.5)
    assert r.status is Status.VIOLATED and r.P is None
    xw, yw = r.witness, r.witness_y
    assert xw[1] == 0.0 and yw == [xw[0]]  # ((c, 0), c)
    assert "not detectable" in r.message or "does not see" in r.message


def test_metric_sdp_status_mapping_infeasible():
    system = load_system("duffing")
    lo, hi = sub_boxes(system, 4)
    Z = kernel_basis(output_matrix(system))
    verts = enclosure_vertices(system, lo, hi)
    res = sdp.metric_sdp(verts.pruned, Z, 2.5, margin=0.01, kappa_max=1e4)
    assert res.status is Status.VIOLATED and res.value is None and res.raw_status == "infeasible"


def test_enclosure_vertices_contain_sampled_jacobians():
    system = load_system("vdp")
    lo, hi = sub_boxes(system, 4, manifold=False)
    v = enclosure_vertices(system, lo, hi)
    x = torch.rand(500, 2, dtype=torch.float64) * 4 - 2
    x[:, 1] *= 1.5
    J = system.jac_f(x).numpy()
    lo_v, hi_v = v.all.min(0), v.all.max(0)
    assert np.all(J >= lo_v - 1e-12) and np.all(J <= hi_v + 1e-12)
    assert len(v.pruned) <= len(v.all)


@pytest.mark.slow
def test_observer_lmi_vdp_and_three_state(system3):
    r = observer_lmi(load_system("vdp"), 2.5)
    assert r.status is Status.PROVED and r.K is not None
    assert r.solver["check_max_vertex_value"] <= -0.5 * r.margin
    r3 = observer_lmi(system3, 0.5, subdivisions=6)
    assert r3.status is Status.PROVED and np.array(r3.K).shape == (3, 2)


def test_metric_refuses_bad_lam():
    with pytest.raises(ValueError):
        synthesize_metric(load_system("vdp"), 0.0)


# ----- the certified LMI baseline ------------------------------------------------------

@pytest.mark.slow
def test_lmi_baseline_network_and_checkpoint(tmp_path):
    from training.baseline import make_lmi_baseline, save_lmi_baseline

    system = load_system("vdp")
    net, P, info = make_lmi_baseline(system, 2.5)
    assert net.structure == "direct"
    z = torch.randn(64, 3, dtype=torch.float64)
    assert torch.all(net(z) == 0)  # the MLP output is exactly zero
    path = tmp_path / "base.ckpt"
    out = save_lmi_baseline(path, system, 2.5)
    ck = checkpoint.load(path)
    assert ck.training["preset"] == "lmi-baseline"
    pr = ck.problem
    assert np.allclose(pr.P, out["P"])
    # pointwise on a dense grid of X x Y: max lam_max(D) < 0 (the proof is the prover's)
    axes = [torch.linspace(float(a), float(b), 61, dtype=torch.float64)
            for a, b in np.vstack([system.X, system.Y])]
    g = torch.cartesian_prod(*axes)
    with torch.no_grad():
        v = mpdi_lam_max(system, pr.network, pr.P_t, 2.5, g[:, :2], g[:, 2:])
    assert float(v.max()) < 0
    # and at every vertex of the enclosure (what makes it provable)
    lo, hi = sub_boxes(system, 16, manifold=False)
    verts = enclosure_vertices(system, lo, hi)
    C = output_matrix(system)
    assert observer_values(verts.all, pr.P, pr.network.K.numpy(), C, 2.5).max() < 0


def test_a_network_too_wide_for_the_fallback_is_unknown_not_a_crash():
    """The interior point is skipped (method clarabel) and the chordal form would be too large:
    an UNKNOWN result at once, saying why, instead of a solver that exhausts memory."""
    rng = np.random.default_rng(0)
    Ws = [rng.normal(size=(128, 2))] + [rng.normal(size=(128, 128)) / 11 for _ in range(5)]
    Wo = rng.normal(size=(4, 128)) / 11
    assert lipsdp.largest_clique(Ws) == 2 + 256
    res = lipsdp.lipsdp_neuron(Ws, Wo, None, method="clarabel")
    assert res.status == Status.UNKNOWN and res.value is None
    assert "not tried" in res.message
