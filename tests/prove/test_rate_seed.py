"""Side proofs seeded with their grid's worst point (rate, residual): same bound, fewer boxes.

A seed only sets the closing level early; the proved lam_cert must stay below every sampled
pointwise rate (soundness), meet the asked relative gap, and the seeded proof must need fewer
boxes than the unseeded one for the same gap on a genuinely nonlinear network.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from certify.model.kernels import pointwise_rate
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import prove_rate
from certify.search.falsify import maximize_over_box
from certify.spec.system import load_system

F64 = torch.float64


def _problem() -> Problem:
    torch.manual_seed(4)
    s = load_system("vdp")
    net = GainNetwork(2, 1, (10, 10), structure="direct", K=torch.tensor([[3.0], [2.0]]))
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(2.0)
        net.layers[-1].weight.mul_(0.05)
    return Problem(system=s, network=net.double(), lam=0.1, P=np.eye(2))


@pytest.mark.slow
def test_seeded_rate_proof_is_sound_and_needs_fewer_boxes() -> None:
    problem = _problem()
    n = problem.n
    s = problem.system
    box = torch.as_tensor(np.concatenate([s.X, s.Y]))

    def neg_rate(z: torch.Tensor) -> torch.Tensor:
        return -pointwise_rate(s, problem.network, problem.P_t, z[:, :n], z[:, n:])

    search = maximize_over_box(neg_rate, box[:, 0], box[:, 1], grid_points=20_000, starts=8,
                               steps=50, top_k=1, seed=0)
    worst_rate = -search.best_value
    seed = torch.as_tensor(search.top_points, dtype=F64)[:1].tolist()
    plain = prove_rate(problem, rel_tol=1e-4)
    seeded = prove_rate(problem, rel_tol=1e-4, seeds=seed)
    for out in (plain, seeded):
        assert out.lower is not None and out.stats.proved_volume_fraction == 1.0
        assert out.lower <= worst_rate  # sound: never above a rate the network attains
        assert out.lower >= worst_rate - 2e-4 * abs(worst_rate) - 1e-9  # the asked gap
    assert seeded.upper_sampled <= worst_rate + 1e-12  # the seed's value was seen
    assert seeded.stats.boxes_processed < plain.stats.boxes_processed


def test_seeded_residual_proof_is_sound_and_needs_no_more_boxes() -> None:
    from certify.checks.residual import residual_norm
    from certify.prove.side import bound_residual

    problem = _problem()
    X = torch.as_tensor(problem.system.X)
    search = maximize_over_box(lambda x: residual_norm(problem, x), X[:, 0], X[:, 1],
                               grid_points=20_000, starts=8, steps=50, top_k=1, seed=0)
    worst = search.best_point.tolist()
    plain, _, plain_stats = bound_residual(problem)
    seeded, _, seeded_stats = bound_residual(problem, seeds=[worst])
    for upper in (plain, seeded):
        assert upper is not None
        assert search.best_value <= upper <= search.best_value * (1 + 2e-3)
    assert seeded_stats.boxes_processed <= plain_stats.boxes_processed
