"""CEGIS in any dimension: the prover's unproved leaves become collocation points whether
they come in full dimension (n + p coordinates) or projected, and the loop runs for n = 3."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from certify.model.kernels import mpdi_lam_max
from certify.model.problem import Problem
from certify.results import Status
from tests.planted import linear_system
from training.cegis import CegisSettings, cegis, unproved_points, warm_start_network

from ..conftest import random_network


def _problem(system3) -> Problem:
    return Problem(system3, random_network(3, 2, seed=2), 0.5, np.asarray(system3.P))


def _inside(pts: torch.Tensor, lo, hi) -> bool:
    lo, hi = torch.as_tensor(lo), torch.as_tensor(hi)
    return bool(((pts >= lo - 1e-15) & (pts <= hi + 1e-15)).all())


def test_full_dimension_leaves_give_points_inside_them(system3):
    problem = _problem(system3)
    box = np.concatenate([system3.X, system3.Y])  # d = 5
    lo, hi = box[:, 0].copy(), box[:, 1].copy()
    leaf_a = (lo, lo + 0.1 * (hi - lo))  # a corner
    leaf_b = (hi - 0.05 * (hi - lo), hi)  # the opposite corner
    boxes = {"lo": [leaf_a[0].tolist(), leaf_b[0].tolist(), lo.tolist()],
             "hi": [leaf_a[1].tolist(), leaf_b[1].tolist(), hi.tolist()],
             "status": ["unknown", "violated", "proved"]}
    gen = torch.Generator().manual_seed(0)
    pts = unproved_points(problem, SimpleNamespace(boxes=boxes), 0.5, limit=10,
                          generator=gen)
    assert pts.shape == (2, 5)  # the proved leaf is skipped
    in_a = [_inside(p, *leaf_a) for p in pts]
    in_b = [_inside(p, *leaf_b) for p in pts]
    assert sorted(in_a) == [False, True] and sorted(in_b) == [False, True]
    # each point is the worst of its leaf's candidates: at least the leaf centre's value
    v = mpdi_lam_max(system3, problem.network, problem.P_t, 0.5, pts[:, :3], pts[:, 3:])
    centres = torch.tensor([[(a + b) / 2 for a, b in zip(*leaf)] for leaf in (leaf_a, leaf_b)])
    vc = mpdi_lam_max(system3, problem.network, problem.P_t, 0.5, centres[:, :3],
                      centres[:, 3:])
    assert float(v.max()) >= float(vc.max()) and float(v.min()) >= float(vc.min())


def test_projected_leaves_fix_only_their_coordinates(system3):
    problem = _problem(system3)
    box = np.concatenate([system3.X, system3.Y])
    gen = torch.Generator().manual_seed(1)
    first_two = {"lo": [[0.5, 1.0]], "hi": [[0.6, 1.2]], "status": ["unknown"]}
    pts = unproved_points(problem, SimpleNamespace(boxes=first_two), 0.5, limit=5,
                          generator=gen)
    assert _inside(pts[:, :2], [0.5, 1.0], [0.6, 1.2])
    assert _inside(pts, box[:, 0], box[:, 1])
    named = {"lo": [[-0.2, 1.0]], "hi": [[-0.1, 1.1]], "dims": [2, 4], "status": ["unknown"]}
    pts = unproved_points(problem, SimpleNamespace(boxes=named), 0.5, limit=5, generator=gen)
    assert _inside(pts[:, [2, 4]], [-0.2, 1.0], [-0.1, 1.1])
    bad = {"lo": [[0.0, 0.0]], "hi": [[1.0, 1.0]], "dims": [0, 7], "status": ["unknown"]}
    with pytest.raises(ValueError, match="name \\[0, 7\\]"):
        unproved_points(problem, SimpleNamespace(boxes=bad), 0.5, limit=5, generator=gen)


def test_cegis_runs_and_proves_in_three_states():
    """n = 3, p = 1: a stable linear plant; the zero-gain warm start is proved in round 1."""
    A = [[-1.0, 0.5, 0.0], [-0.5, -1.0, 0.2], [0.0, -0.2, -1.5]]
    system = linear_system(A=A, C=[[1.0, 0.0, 0.0]], lam=0.3)
    net = warm_start_network(system, (4,), seed=0)
    settings = CegisSettings(margin=0.1, rate_slack=0.0, lip_weight=0.0, rounds=2,
                             iters_per_round=5, grid_points=2000, adversarial_starts=2,
                             adversarial_steps=5, proof_boxes=20_000, proof_seconds=20.0,
                             budget_seconds=60.0, add_per_round=32)
    res = cegis(system, net, np.eye(3), 0.3, points=64, settings=settings)
    assert res.status is Status.PROVED and res.xhat.shape[1] == 3
