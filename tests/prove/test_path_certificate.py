"""The path (differential) dissipation certificate: the matrix of a noise-input problem, its
enclosures over boxes, decisions on planted near-ties, and never worse than the cover route."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import certify.prove.dissipation as dm
from certify.enclose.mpdi import mpdi_box_bounds
from certify.enclose.options import Technique, box_bound_options
from certify.enclose.preconditioner import to_lam_max_D
from certify.model.kernels import contraction_matrix, gain_terms, lam_max, problem_lam_max
from certify.model.problem import NoiseInput, Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.witness import mpdi_lower

from ..conftest import random_network
from ..planted import linear_system

A2 = np.array([[0.0, 1.0], [-2.0, -1.0]])
C2 = np.array([[1.0, 0.0]])
P2 = np.array([[3.0, 0.7], [0.7, 1.5]])
EXAMPLES = Path(__file__).parents[2] / "examples"


def _points(problem: Problem, count: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    box = np.concatenate([problem.system.X, problem.system.Y])
    return torch.as_tensor(box[:, 0] + rng.random((count, len(box))) * (box[:, 1] - box[:, 0]))


def _path(problem: Problem, alpha: float, mu: float, scale: float | None = None) -> Problem:
    return Problem(system=problem.system, network=problem.network, lam=alpha / 4, P=problem.P,
                   noise=NoiseInput(alpha, mu, 0.5 * mu if scale is None else scale))


def _schur(problem: Problem, alpha: float, mu: float, z: torch.Tensor) -> torch.Tensor:
    """lam_max(D(alpha/4) + P B B^T P / (2 mu)) at points z: <= 0 iff the path inequality."""
    n = problem.n
    t = gain_terms(problem.system, problem.network, z[:, :n], z[:, n:], with_dy=True)
    P = torch.as_tensor(problem.P)
    D = contraction_matrix(problem.system.jac_f(z[:, :n]), t.dk_dx, P, alpha / 4)
    PB = P @ t.dk_dy
    return lam_max(D + PB @ PB.transpose(1, 2) / (2 * mu))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans(), alpha=st.floats(0.05, 3.0),
       mu=st.floats(0.01, 100.0), scale=st.floats(0.01, 100.0))
def test_noise_input_matrix_is_negative_exactly_where_the_schur_form_is(seed, structural,
                                                                       alpha, mu, scale):
    """D~ <= 0 iff D(alpha/4) + P B B^T P / (2 mu) <= 0, point by point, for every metric
    scale s (the scale only conditions the proof)."""
    net = random_network(2, 1, hidden=(5,), structure="structural" if structural else "direct",
                         seed=seed)
    base = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    z = _points(base, 400, seed)
    path = problem_lam_max(_path(base, alpha, mu, scale), alpha / 4, z[:, :2], z[:, 2:])
    schur = _schur(base, alpha, mu, z)
    clear = schur.abs() > 1e-9 * (1 + schur.abs())
    assert torch.equal((path <= 0)[clear], (schur <= 0)[clear])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans(), alpha=st.floats(0.1, 3.0),
       mu=st.floats(0.5, 50.0), width=st.floats(0.01, 1.0), plain=st.booleans())
def test_box_bounds_of_the_noise_input_matrix_contain_the_sampled_values(
        seed, structural, alpha, mu, width, plain):
    """Over random boxes, every stage's bound of lam_max(D~) is >= its value at points of
    the box (hypothesis; plain interval alone, or every stage of the prover)."""
    net = random_network(2, 1, hidden=(5,), structure="structural" if structural else "direct",
                         seed=seed, scale=1.5)
    base = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    sub = _path(base, alpha, mu)
    rng = np.random.default_rng(seed)
    box = np.concatenate([base.system.X, base.system.Y])
    span = box[:, 1] - box[:, 0]
    lo = box[:, 0] + rng.random((6, 3)) * span * (1 - width)
    hi = lo + width * span
    technique = Technique.PLAIN if plain else Technique.TAYLOR
    opts = box_bound_options(sub, alpha / 4, technique=technique, crown=not plain)
    bb = mpdi_box_bounds(opts, torch.as_tensor(lo), torch.as_tensor(hi))
    upper = to_lam_max_D(bb.upper, sub.P_t, opts.pc)
    u = torch.as_tensor(rng.random((6, 200, 3)))
    z = torch.as_tensor(lo)[:, None] + u * torch.as_tensor(hi - lo)[:, None]
    vals = problem_lam_max(sub, alpha / 4, z.reshape(-1, 3)[:, :2],
                           z.reshape(-1, 3)[:, 2:]).reshape(6, 200)
    assert torch.all(torch.isnan(upper) | (vals.max(1).values <= upper))


def _linear_mu(A, C, K, P, alpha) -> float:
    """The exact noise gain of the linear observer at rate alpha:
    lam_max(K^T P (-D)^-1 P K) / 2, D = He{P (A - K C)} + alpha/2 P."""
    Acl = A - K @ C
    D = 0.5 * (P @ Acl + Acl.T @ P) + 0.5 * alpha * P
    M = (P @ K).T @ np.linalg.solve(-D, P @ K)
    return float(np.linalg.eigvalsh(M)[-1]) / 2


@pytest.mark.parametrize("factor,proved", [(1 - 1e-3, False), (1 + 1e-2, True)])
def test_a_noise_gain_a_hair_too_small_is_never_proved(factor, proved):
    """A linear plant and gain: D~ is constant, the exact noise gain is known. Below it by
    0.1% the prover must not prove (it finds the violation); 1% above it proves."""
    K = np.array([[1.0], [0.5]])
    from tests.prove.test_error_bound import linear_gain

    base = Problem(system=linear_system(A2, C2, P=P2), network=linear_gain(K), lam=0.1, P=P2)
    alpha = 0.8
    mu = _linear_mu(A2, C2, K, P2, alpha) * factor
    out = prove_mpdi(_path(base, alpha, mu), max_boxes=20_000, seconds=math.inf,
                     estimate_points=0)
    assert (out.status == Status.PROVED) == proved
    if not proved:
        assert out.status == Status.VIOLATED
        pt = torch.as_tensor([out.counterexample.xhat + out.counterexample.y])
        assert float(mpdi_lower(_path(base, alpha, mu), pt, alpha / 4)[0]) > 0


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans())
def test_the_path_plan_never_aims_above_the_cover_plan(seed, structural):
    """At the same samples the coupled (path) noise gain is at most the cover's at every
    rate: B at a point lies in the hull the cover's vertices span."""
    net = random_network(2, 1, hidden=(4,), structure="structural" if structural else "direct",
                         seed=seed)
    pb = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)
    smp = dm._Samples.at(pb, dm._samples(pb, 512, seed))
    cover = dm.dk_dy_cover(pb, boxes=512)
    PBv = np.einsum("ij,vjk->vik", P2, cover.vertices)[:, None]
    for alpha in (0.05, 0.2, 0.5):
        D = smp.D0 + 0.5 * alpha * P2
        if np.linalg.eigvalsh(D)[:, -1].max() >= 0:
            continue
        path = dm._mu_needed(D, smp.PB[None]).max()
        cov = dm._mu_needed(D, PBv).max()
        assert path <= cov * (1 + 1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_the_path_certificate_is_never_worse_than_the_cover(seed):
    """A nonlinear structural gain: the path certificate's proved bound is at most the cover
    certificate's on the same gain (and the automatic choice is the smaller)."""
    net = random_network(2, 1, hidden=(6,), structure="structural", seed=seed, scale=0.5)
    with torch.no_grad():
        net.K.copy_(torch.as_tensor([[1.0], [0.5]]))
    pb = Problem(system=linear_system(A2, C2, P=P2), network=net, lam=0.1, P=P2)

    def bound(out):
        assert out.status == Status.PROVED
        return math.sqrt(out.mu * 0.15 ** 2 / out.alpha)

    path = dm.prove_dissipation(pb, vbar=0.15, route="path")
    cover = dm.prove_dissipation(pb, vbar=0.15, route="cover")
    auto = dm.prove_dissipation(pb, vbar=0.15)
    assert path.route == "path" and cover.route == "cover"
    assert bound(path) <= bound(cover)
    assert bound(auto) <= bound(path) * (1 + 1e-12)


@pytest.mark.slow
def test_the_shipped_learned_observer_by_the_path_certificate():
    """examples/vdp_certified.ckpt (a nonlinear structural gain): one path proof, below the
    cover route's bound, within the default box budget."""
    from certify.model import checkpoint

    pb = checkpoint.load(str(EXAMPLES / "vdp_certified.ckpt")).problem
    path = dm.prove_dissipation(pb, vbar=0.15)
    cover = dm.prove_dissipation(pb, vbar=0.15, route="cover")
    assert path.status == Status.PROVED and path.route == "path" and path.vertices == 1
    assert path.mu / path.alpha <= cover.mu / cover.alpha
    assert path.boxes <= dm.DEFAULT_BOXES
