"""The metric-weighted constants (L_P, eps_bar_P) and the joint dissipation certificate:
known answers on linear gains, sampled values never above the proved ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.checks.bounds import check_bounds
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.presentation import error_headline, upper_text
from certify.prove.dissipation import dk_dy_cover, prove_dissipation, upper_shift
from certify.prove.error_bound import inverse_diagonal_upper, settle_time
from certify.prove.side import bound_dk_dy, bound_residual
from certify.prove.weighted import weighting
from certify.results import DissipationResult, Status

from ..conftest import random_network
from ..planted import linear_system

A2 = np.array([[0.0, 1.0], [-2.0, -1.0]])
C2 = np.array([[1.0, 0.0]])
P2 = np.array([[3.0, 0.7], [0.7, 1.5]])


def linear_gain(K: np.ndarray, hidden=(4,)) -> GainNetwork:
    """k = K (y - h(xhat)): a structural network whose last layer is zero."""
    n, p = K.shape
    net = GainNetwork(n, p, hidden, structure="structural").double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        net.K.copy_(torch.as_tensor(K, dtype=torch.float64))
    return net.requires_grad_(False)


def sqrtm(P: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(P)
    return (V * np.sqrt(w)) @ V.T


def test_L_P_of_a_linear_gain_is_the_norm_of_P_half_K():
    K = np.array([[2.0], [1.5]])
    pb = Problem(system=linear_system(A2, C2, P=P2), network=linear_gain(K), lam=0.1, P=P2)
    w = weighting(pb)
    L_P = w.bound(bound_dk_dy(w.problem)[0], w.dy_error)
    exact = float(np.linalg.norm(sqrtm(P2) @ K))
    assert exact <= L_P <= exact * (1 + 1e-9)
    # the unweighted constant is ||K||, and ||P^(1/2)|| ||K|| is what the loose bound uses
    assert L_P < float(np.linalg.norm(sqrtm(P2), 2) * np.linalg.norm(K))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans(),
       d=st.floats(0.3, 3.0), c=st.floats(-0.9, 0.9))
def test_sampled_weighted_noise_gain_never_exceeds_L_P(seed, structural, d, c):
    P = np.array([[1.0, c], [c, d]]) * 2.0
    if np.linalg.eigvalsh(P)[0] <= 0.05:
        P = P + np.eye(2)
    net = random_network(2, 1, hidden=(5,), structure="structural" if structural else "direct",
                         seed=seed)
    pb = Problem(system=linear_system(A2, C2, P=P), network=net, lam=0.1, P=P)
    w = weighting(pb)
    L_P = w.bound(bound_dk_dy(w.problem, max_boxes=3000, rel_tol=5e-2)[0], w.dy_error)
    assert L_P is not None
    rng = np.random.default_rng(seed)
    box = np.concatenate([pb.system.X, pb.system.Y])
    z = torch.as_tensor(box[:, 0] + rng.random((2000, 3)) * (box[:, 1] - box[:, 0]))
    J = gain_terms(pb.system, pb.network, z[:, :2], z[:, 2:], with_dy=True).dk_dy.numpy()
    sampled = np.linalg.norm(np.einsum("ij,bjk->bik", sqrtm(P), J)[..., 0], axis=1).max()
    assert sampled <= L_P
    if not structural:  # eps_bar_P >= sampled ||P^(1/2) k(x, h(x))||
        eps = w.bound(bound_residual(w.problem, max_boxes=3000)[0], w.value_error)
        x = z[:, :2]
        k = gain_terms(pb.system, pb.network, x, pb.system.h(x), with_dy=False).k.numpy()
        assert np.linalg.norm(k @ sqrtm(P), axis=1).max() <= eps


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans())
def test_cover_contains_every_sampled_dk_dy(seed, structural):
    net = random_network(2, 1, hidden=(4,), structure="structural" if structural else "direct",
                         seed=seed)
    pb = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    cover = dk_dy_cover(pb, boxes=512)
    rng = np.random.default_rng(seed)
    box = np.concatenate([pb.system.X, pb.system.Y])
    z = torch.as_tensor(box[:, 0] + rng.random((3000, 3)) * (box[:, 1] - box[:, 0]))
    J = gain_terms(pb.system, pb.network, z[:, :2], z[:, 2:], with_dy=True).dk_dy.numpy()
    V = cover.vertices.reshape(len(cover.vertices), -1)
    pts = J.reshape(len(J), -1)
    # membership in conv(V) by a linear program per point (a few): max violation of the
    # polygon's edges for the 2-D case
    assert V.shape[1] == 2
    c = V.mean(0)
    ang = np.arctan2(V[:, 1] - c[1], V[:, 0] - c[0])
    V = V[np.argsort(ang)]
    for i in range(len(V)):
        a, b = V[i], V[(i + 1) % len(V)]
        cross = (b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0])
        assert cross.min() >= -1e-9 * max(1.0, np.abs(V).max())


def _linear_optimum(A, C, K, P, vbar):
    """min over alpha of vbar sqrt(mu*(alpha) / (alpha lam_min(P))) for e' = (A - K C) e - K v,
    mu*(alpha) = lam_max(K^T P (-D)^-1 P K) / 2, D = He{P (A - K C)} + alpha/2 P."""
    Acl = A - K @ C
    H = 0.5 * (P @ Acl + Acl.T @ P)
    lam_top = -np.linalg.eigvals(np.linalg.solve(P, H)).real.max()

    def bound(alpha):
        D = H + 0.5 * alpha * P
        if np.linalg.eigvalsh(D)[-1] >= 0:
            return np.inf
        M = (P @ K).T @ np.linalg.solve(-D, P @ K)
        return vbar * math.sqrt(np.linalg.eigvalsh(M)[-1] / 2 / alpha / np.linalg.eigvalsh(P)[0])
    top = 4 * min(lam_top, -np.linalg.eigvalsh(np.linalg.solve(np.linalg.cholesky(P),
                  np.linalg.solve(np.linalg.cholesky(P), H).T))[-1] / 2)
    res = scipy.optimize.minimize_scalar(bound, bounds=(1e-6 * top, top * (1 - 1e-9)),
                                         method="bounded", options={"xatol": 1e-10})
    return res.fun


@pytest.mark.slow
def test_joint_certificate_of_a_linear_observer_meets_the_sdp_optimum():
    """A linear plant with a linear gain: the proved bound is never below the exact optimum
    over alpha and within the sampled scan's resolution of it."""
    K = np.array([[1.0], [0.5]])
    pb = Problem(system=linear_system(A2, C2, P=P2), network=linear_gain(K), lam=0.1, P=P2)
    out = prove_dissipation(pb, vbar=0.15)
    assert out.status == Status.PROVED and out.vertices == 1
    proved = 0.15 * math.sqrt(out.mu / (out.alpha * np.linalg.eigvalsh(P2)[0]))
    best = _linear_optimum(A2, C2, K, P2, 0.15)
    assert best <= proved * (1 + 1e-9)
    assert proved <= best * 1.08


def test_dissipation_bound_in_the_headline():
    """A proved dissipation result enters the bounds as 'dissipation', with its curve, the
    headline and per-component bounds; a better ISS bound would win instead."""
    K = np.array([[1.0], [0.5]])
    pb = Problem(system=linear_system(A2, C2, P=P2), network=linear_gain(K), lam=0.1, P=P2)
    d = DissipationResult(Status.PROVED, "test", alpha=1.0, mu=4.0)
    r = check_bounds(pb, lam_cert=None, eps_bar=None, L=None, vbar=0.15, dissipation=d)
    lam_min = np.linalg.eigvalsh(P2)[0]
    want = math.sqrt(4.0 * 0.15 ** 2 / 1.0 / lam_min)
    assert r.status == Status.PROVED and r.best == "dissipation"
    assert want <= r.ultimate <= want * (1 + 1e-9)
    assert r.headline == pytest.approx(1.1 * r.ultimate)
    # per component: sqrt(V_inf (P^-1)_ii), below the norm bound
    Pinv = np.linalg.inv(P2)
    for i, v in enumerate(r.per_component):
        assert math.sqrt(4.0 * 0.15 ** 2 * Pinv[i, i]) <= v * (1 + 1e-9)
        assert v <= r.ultimate
    # the settle time: the curve from the worst start reaches the headline there
    assert r.settle_time > 0
    assert settle_time(r, "dissipation", 1e-3, r.headline) == 0.0
    # the check's line says what the headline says, rounded outward (never below the proof)
    head = error_headline(r)
    assert r.message.startswith(f"||e|| <= {upper_text(r.headline)} for noise <= 0.15 after "
                                f"t >= {upper_text(r.settle_time, 2)} s")
    assert head.sentence(unicode=False).replace("||e||", "") in r.message.replace("||e||", "")
    assert "ultimate bounds (t -> infinity): " in r.message


def test_inverse_diagonal_upper_bounds():
    rng = np.random.default_rng(1)
    for _ in range(20):
        M = rng.normal(size=(4, 4))
        P = M @ M.T + 0.01 * np.eye(4)
        up = inverse_diagonal_upper(P)
        exact = np.diag(np.linalg.inv(P))
        assert np.all(exact <= up) and np.all(up <= exact * (1 + 1e-6) + 1e-12)


def test_upper_shift_dominates_in_the_psd_order():
    rng = np.random.default_rng(2)
    for _ in range(20):
        P = rng.normal(size=(3, 3))
        b = rng.normal(size=(3, 1))
        Q = (P @ b) @ (P @ b).T
        U = upper_shift(Q, (np.abs(P) @ np.abs(b)) @ (np.abs(P) @ np.abs(b)).T, 14)
        assert np.linalg.eigvalsh(U - Q)[0] > 0


def test_a_wrong_gain_never_gets_a_smaller_bound():
    """A planted gain with a large dk/dy spike on part of the box: the proved mu must cover
    the spike (the cover contains every enclosure, not just sampled points)."""
    K = np.array([[1.0], [0.5]])
    net = linear_gain(K)
    spiky = random_network(2, 1, hidden=(4,), structure="structural", seed=3, scale=2.0)
    with torch.no_grad():
        spiky.K.copy_(torch.as_tensor(K))
    pb0 = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    pb1 = Problem(system=linear_system(A2, C2, P=P2), network=spiky, lam=0.1, P=P2)
    c0, c1 = dk_dy_cover(pb0), dk_dy_cover(pb1)
    assert len(c0.vertices) == 1
    spread = np.abs(c1.vertices.reshape(len(c1.vertices), -1) - K.reshape(1, -1)).max()
    assert spread > 0.1


def test_residual_share_covers_the_steady_error_it_forces():
    """A direct gain k = c + K (y - h(xhat)): the residual r = k(x, h(x)) = c is a constant
    input, which holds the error at e* = (A - K C)^-1 c without noise. The proved bound
    (noise 0, eps_bar_P = ||P^(1/2) c||) may not be below ||e*||."""
    K = np.array([[1.0], [0.5]])
    c = np.array([0.03, -0.02])
    net = GainNetwork(2, 1, (4,), structure="direct").double()
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.zero_()
            layer.bias.zero_()
        net.layers[-1].bias.copy_(torch.as_tensor(c))
        net.K.copy_(torch.as_tensor(K))
    net.requires_grad_(False)
    pb = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    eps_P = float(np.linalg.norm(sqrtm(P2) @ c)) * (1 + 1e-12)
    out = prove_dissipation(pb, vbar=0.0, eps_P=eps_P)
    assert out.status == Status.PROVED and out.mu_residual
    proved = math.sqrt(out.mu_residual * eps_P ** 2 / out.alpha / np.linalg.eigvalsh(P2)[0])
    e_star = np.linalg.solve(A2 - K @ C2, c)
    assert np.linalg.norm(e_star) <= proved


def test_one_costly_piece_of_the_cover_may_use_the_whole_attempt(monkeypatch):
    """Every piece must be proved for a candidate, so a piece is given all the boxes the
    attempt has left, not a share: a first piece that needs half the attempt's boxes is
    proved, and the candidate with it. A fake prover: each piece costs what is listed,
    proved if its box budget covers that, else UNKNOWN."""
    import types
    from pathlib import Path

    import certify.prove.dissipation as dm
    from certify.model import checkpoint

    problem = checkpoint.load(str(Path(__file__).parents[2] / "examples"
                                  / "vdp_certified.ckpt")).problem
    boxes = 80_000
    attempt = int(boxes * dm.SCHEDULE[0][2])  # the first attempt's share
    given: list[int] = []

    def fake_prove(sub, *, lam, max_boxes, deadline, estimate_points, task):
        cost = attempt // 2 if not given else 10
        given.append(max_boxes)
        status = Status.PROVED if cost <= max_boxes else Status.UNKNOWN
        return types.SimpleNamespace(status=status, counterexample=None,
                                     stats=types.SimpleNamespace(
                                         boxes_processed=min(cost, max_boxes),
                                         stopped_by_cap=False))

    monkeypatch.setattr(dm, "prove_mpdi", fake_prove)
    out = prove_dissipation(problem, vbar=0.15, max_boxes=boxes, route="cover")
    assert out.vertices > 2 and len(given) == out.vertices  # every piece, one attempt
    assert out.status == Status.PROVED and len(out.candidates) == 1
    assert given[0] == attempt and given[1] == attempt - attempt // 2
