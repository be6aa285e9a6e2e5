"""bench/tree_size.py's random descents follow the proof's own tree: each point ends in a
leaf the decision proof itself closes, at the same depth, and the leaf estimate is near the
proof's leaf count."""

from __future__ import annotations

import math

import torch

from bench.instances import InstanceSpec, make_instance
from bench.tree_size import estimate, leaf_depths, random_points
from certify.bnb import branch_and_bound
from certify.prover import mpdi_decision


def test_random_descents_end_in_the_proofs_own_leaves() -> None:
    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    setup = mpdi_decision(problem, float(problem.lam))
    closed: list[tuple[torch.Tensor, torch.Tensor]] = []

    def recording(lo: torch.Tensor, hi: torch.Tensor):
        out = setup.evaluate(lo, hi)
        shut = (out.upper <= 0.0) & torch.isfinite(out.upper)
        closed.append((lo[shut], hi[shut]))
        return out

    proof = branch_and_bound(setup.lo, setup.hi, recording, threshold=0.0, seconds=120.0,
                             first_round=setup.first_round)
    assert proof.complete
    leaf_lo = torch.cat([c[0] for c in closed])
    leaf_hi = torch.cat([c[1] for c in closed])
    root_volume = float((setup.hi - setup.lo).prod())
    leaf_depth = torch.round(torch.log2(root_volume / (leaf_hi - leaf_lo).prod(-1))).long()
    z = random_points(problem, 256, seed=1)
    depth, evaluations = leaf_depths(problem, z)
    assert bool((depth >= 0).all()) and evaluations >= len(z)
    inside = ((z[:, None] >= leaf_lo[None]) & (z[:, None] <= leaf_hi[None])).all(-1)
    same = (inside & (leaf_depth[None] == depth[:, None])).any(-1)
    assert bool(same.all()), int((~same).sum())
    est = estimate(depth)
    assert 0.5 < est["est_leaves"] / len(leaf_lo) < 2.0, (est, len(leaf_lo))
    assert math.isfinite(est["rel_stderr"])
