"""The sound prover: known answers, planted violations, NaN handling, n = 3 / p = 2."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from certify.model.kernels import gain_terms, mpdi_lam_max, pointwise_rate
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import ProofOutcome, RateOutcome, prove_mpdi, prove_rate
from certify.prove.side import bound_dk_dy, bound_manifold_quantity, bound_residual
from certify.results import Counterexample, ProofStats, Status
from certify.spec.system import System, load_system
from tests.planted import lam_cert_linear, linear_problem, planted_problem

# Ground truth: f = A x, h = C x, k = K (y - C x) (zero network weights). The closed-loop
# Jacobian is the constant A - K C, so lam_cert = -lam_max(He{P (A - K C)}, P) / 2 exactly.
A = np.array([[0.0, 1.0], [-2.0, -3.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [0.5]])
P_METRIC = np.array([[2.0, 0.3], [0.3, 1.0]])


@pytest.mark.parametrize("P", [None, P_METRIC], ids=["identity", "metric"])
def test_linear_ground_truth_rate(P: np.ndarray | None) -> None:
    truth = lam_cert_linear(A, C, K, P)
    prob = linear_problem(A, C, K, lam=0.1, P=P)
    out = prove_rate(prob)
    assert isinstance(out, RateOutcome)
    assert out.lower is not None
    assert out.lower <= truth + 1e-12  # sound
    assert abs(out.lower - truth) < 1e-6
    assert abs(out.upper_sampled - truth) < 1e-6


@pytest.mark.parametrize("P", [None, P_METRIC], ids=["identity", "metric"])
def test_linear_ground_truth_mpdi(P: np.ndarray | None) -> None:
    truth = lam_cert_linear(A, C, K, P)
    prob = linear_problem(A, C, K, lam=0.1, P=P)
    below = prove_mpdi(prob, lam=truth - 1e-3)
    assert isinstance(below, ProofOutcome)
    assert below.status is Status.PROVED
    assert below.upper <= 0 and below.counterexample is None
    above = prove_mpdi(prob, lam=truth + 1e-3)
    assert above.status is Status.VIOLATED
    cex = above.counterexample
    assert isinstance(cex, Counterexample) and cex.value > 0
    xh = torch.tensor([cex.xhat], dtype=torch.float64)
    y = torch.tensor([cex.y], dtype=torch.float64)
    v = float(mpdi_lam_max(prob.system, prob.network, prob.P_t, truth + 1e-3, xh, y)[0])
    assert v == pytest.approx(cex.value) and v > 0
    assert isinstance(above.stats, ProofStats) and above.stats.rounding


@pytest.mark.parametrize("kind", ["corner", "edge", "blob"])
@pytest.mark.slow
def test_planted_violations_are_found(kind: str) -> None:
    prob = planted_problem(kind)
    out = prove_mpdi(prob)  # speed is measured in bench/prove.py, not here
    assert out.status is Status.VIOLATED, out.message
    cex = out.counterexample
    assert cex is not None and cex.value > 0
    # the violating set is tiny: random sampling hardly ever sees it
    z = torch.rand(20_000, 3, dtype=torch.float64) * 2 - 1
    v = mpdi_lam_max(prob.system, prob.network, prob.P_t, prob.lam, z[:, :2], z[:, 2:])
    assert float((v > 0).double().mean()) < 1e-3
    assert out.boxes["status"].count("violated") == 1


def test_nan_weights_are_unknown_never_proved() -> None:
    prob = linear_problem(A, C, K, lam=0.1)
    with torch.no_grad():
        prob.network.layers[0].weight[0, 0] = float("nan")
    out = prove_mpdi(prob, lam=0.05, max_boxes=2000)
    assert out.status is Status.UNKNOWN
    assert out.stats.proved_volume_fraction == 0.0


def test_residual_and_dk_dy_linear() -> None:
    prob = linear_problem(A, C, K, lam=0.1)
    up, worst, stats = bound_residual(prob)
    assert up is not None and 0.0 <= up < 1e-12
    L = bound_dk_dy(prob)[0]
    assert L is not None
    assert np.linalg.norm(K, 2) <= L <= np.linalg.norm(K, 2) * (1 + 1e-9)


def test_structural_residual_is_exactly_zero() -> None:
    s = load_system("vdp")
    prob = Problem(s, GainNetwork(2, 1, (4, 4), structure="structural"), 1.0, s.P)
    up, worst, _ = bound_residual(prob)
    assert up == 0.0 and worst is None


def test_manifold_quantity_vdp() -> None:
    # P = I, y = x1: q(x) = df2/dx2 + 2 lam = 1 - x1^2 + 2 lam, max 1 + 2 lam at x1 = 0
    s = load_system("vdp")
    up, witness = bound_manifold_quantity(s, np.eye(2), 2.5)
    assert up is not None and 6.0 <= up <= 6.0 + 1e-2
    assert witness is not None and abs(witness[0]) < 0.1


def test_manifold_quantity_nonlinear_h_declines() -> None:
    spec = load_system("vdp").source.replace('h = ["x1"]', 'h = ["x1**2 + x2"]')
    s = System.from_text(spec)
    assert bound_manifold_quantity(s, np.eye(2), 1.0) == (None, None)


SPEC3 = """
name = "three"
states = ["a", "b", "c"]
outputs = ["y1", "y2"]
f = ["-a + 0.5*b", "-b + 0.2*sin(a)*c", "-2*c + 0.1*tanh(a*b)"]
h = ["a", "c + 0.1*b"]
[box]
X = [[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]]
Y = [[-1.0, 1.0], [-1.2, 1.2]]
[design]
lam = 0.1
"""


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.slow
def test_three_states_two_outputs_through_everything(structure: str) -> None:
    s = System.from_text(SPEC3, origin="test three")
    torch.manual_seed(1)
    net = GainNetwork(3, 2, (6, 6), structure=structure, K=0.1 * torch.randn(3, 2))
    with torch.no_grad():
        net.layers[-1].weight.mul_(0.05)
    prob = Problem(s, net, 0.1, s.P)
    g = torch.Generator().manual_seed(0)
    box = np.concatenate([s.X, s.Y])
    z = torch.as_tensor(box[:, 0]) + torch.as_tensor(box[:, 1] - box[:, 0]) * torch.rand(
        4000, 5, generator=g, dtype=torch.float64)

    out = prove_mpdi(prob)
    assert out.status is Status.PROVED, out.message
    vals = mpdi_lam_max(s, prob.network, prob.P_t, prob.lam, z[:, :3], z[:, 3:])
    assert float(vals.max()) <= out.upper <= 0
    assert set(out.boxes) == {"lo", "hi", "status"} and len(out.boxes["lo"][0]) == 2

    rate = prove_rate(prob, max_boxes=1024)  # ends on boxes, not the clock
    sampled = pointwise_rate(s, prob.network, prob.P_t, z[:, :3], z[:, 3:])
    assert rate.lower is not None and rate.lower <= float(sampled.min())
    assert rate.lower <= rate.upper_sampled and rate.lower > prob.lam

    up, worst, _ = bound_residual(prob)
    x = z[:, :3]
    res = gain_terms(s, prob.network, x, s.h(x)).k.norm(dim=1)
    assert up is not None and up >= float(res.max())
    if structure == "structural":
        assert up == 0.0

    L = bound_dk_dy(prob)[0]
    dky = gain_terms(s, prob.network, z[:, :3], z[:, 3:]).dk_dy
    assert L is not None and L >= float(torch.linalg.matrix_norm(dky, ord=2).max())

    q, wit = bound_manifold_quantity(s, s.P, 0.1)
    assert q is not None and q < 0 and math.isfinite(q)
