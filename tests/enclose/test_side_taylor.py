"""The Taylor-model bound of ||dk/dy|| (side proof of the Lipschitz check) is sound and tight.

Property: over random networks (both structures, every activation, with and without K), boxes
and points inside, the bound is >= the float64 norm of dk/dy at every sampled point; and on
small boxes it is tighter than the interval bound, which is what makes the branch and bound
of `certify.prove.side.bound_dk_dy` close near its maximum.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.enclose.side import dk_dy_box_upper, dk_dy_box_upper_taylor
from certify.model import activations
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.side import bound_dk_dy
from certify.spec.system import load_system

from ..soak import examples

F64 = torch.float64


def _net(structure: str, act: str, seed: int, g: float, with_K: bool) -> GainNetwork:
    torch.manual_seed(seed)
    K = torch.randn(2, 1) if with_K else None
    net = GainNetwork(2, 1, (7, 7), structure=structure, K=K, activation=act)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(g)
    return net.double()


def _points(lo: torch.Tensor, hi: torch.Tensor, S: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed + 1)
    u = torch.rand(lo.shape[0], S, lo.shape[1], generator=gen, dtype=F64)
    u[:, :2] = torch.stack([torch.zeros_like(lo), torch.ones_like(lo)], 1)  # two corners
    return lo[:, None] + (hi - lo)[:, None] * u


@pytest.mark.parametrize("act", activations.names())
@pytest.mark.parametrize("structure", ["structural", "direct"])
@settings(max_examples=examples(3), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-6, 1e-2, 0.1, 0.5]),
       g=st.sampled_from([1.0, 3.0]), with_K=st.booleans())
def test_taylor_dk_dy_bound_contains_sampled_norms(act: str, structure: str, seed: int,
                                                   scale: float, g: float,
                                                   with_K: bool) -> None:
    s = load_system("vdp")
    net = _net(structure, act, seed, g, with_K)
    gen = torch.Generator().manual_seed(seed)
    box = torch.as_tensor(np.concatenate([s.X, s.Y]))
    c = box[:, 0] + torch.rand(8, 3, generator=gen, dtype=F64) * (box[:, 1] - box[:, 0])
    lo, hi = c - scale, c + scale
    ub, _ = dk_dy_box_upper_taylor(s, net, lo, hi)
    assert bool((ub >= 0).all())
    z = _points(lo, hi, 200, seed).reshape(-1, 3)
    dky = gain_terms(s, net, z[:, :2], z[:, 2:]).dk_dy  # [N, 2, 1]
    nrm = torch.linalg.matrix_norm(dky, ord=2).reshape(8, -1).amax(1)
    # the point value itself is a float evaluation: allow its rounding, nothing more
    assert bool((nrm <= ub * (1 + 1e-12)).all()), (nrm - ub).max()


def test_taylor_dk_dy_bound_is_second_order_where_intervals_are_first() -> None:
    s = load_system("vdp")
    net = _net("structural", "tanh", 3, 2.0, True)
    c = torch.tensor([[0.3, -0.4, 0.2]], dtype=F64)
    excess_t, excess_i = [], []
    for r in (0.02, 0.01, 0.005):
        lo, hi = c - r, c + r
        z = _points(lo, hi, 4000, 0).reshape(-1, 3)
        dky = gain_terms(s, net, z[:, :2], z[:, 2:]).dk_dy
        true = float(torch.linalg.matrix_norm(dky, ord=2).max())
        excess_t.append(float(dk_dy_box_upper_taylor(s, net, lo, hi)[0][0]) - true)
        excess_i.append(float(dk_dy_box_upper(s, net, lo, hi)[0][0]) - true)
    # a box 4x smaller: the interval excess drops ~4x, the Taylor excess ~16x
    assert excess_i[2] > 0.15 * excess_i[0]
    assert excess_t[2] < 0.1 * excess_t[0]
    assert excess_t[2] < 0.1 * excess_i[2]


@pytest.mark.slow
def test_structural_dk_dy_proof_is_sound_and_closes() -> None:
    s = load_system("vdp")
    net = _net("structural", "tanh", 5, 2.0, True)
    problem = Problem(system=s, network=net, lam=0.1, P=np.eye(2))
    upper = bound_dk_dy(problem, rel_tol=1e-3)[0]
    gen = torch.Generator().manual_seed(0)
    box = torch.as_tensor(np.concatenate([s.X, s.Y]))
    z = box[:, 0] + torch.rand(200_000, 3, generator=gen, dtype=F64) * (box[:, 1] - box[:, 0])
    dky = gain_terms(s, net, z[:, :2], z[:, 2:]).dk_dy
    sampled = float(torch.linalg.matrix_norm(dky, ord=2).max())
    assert upper is not None and sampled <= upper <= sampled * 1.01


def test_entrywise_fallback_is_sound_and_looser(monkeypatch: pytest.MonkeyPatch) -> None:
    import certify.enclose.side as side

    s = load_system("vdp")
    net = _net("structural", "tanh", 7, 2.0, True)
    c = torch.tensor([[0.3, -0.4, 0.2], [-1.0, 2.0, -1.5]], dtype=F64)
    lo, hi = c - 0.05, c + 0.05
    vertex, _ = side.dk_dy_box_upper_taylor(s, net, lo, hi)
    monkeypatch.setattr(side, "MAX_VERTEX_ENTRIES", 0)
    entrywise, _ = side.dk_dy_box_upper_taylor(s, net, lo, hi)
    z = _points(lo, hi, 2000, 7).reshape(-1, 3)
    dky = gain_terms(s, net, z[:, :2], z[:, 2:]).dk_dy
    nrm = torch.linalg.matrix_norm(dky, ord=2).reshape(2, -1).amax(1)
    assert bool((nrm <= vertex).all()) and bool((vertex <= entrywise).all())
