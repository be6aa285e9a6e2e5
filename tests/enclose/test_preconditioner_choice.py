"""The congruences M D M^T the MPDI prover chooses among: every one gives a sound bound on
lam_max(D) over boxes, the choice is deterministic, and a linear metric problem decides as
its closed form says."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.enclose.mpdi import choose_preconditioner, mpdi_box_bounds, plain_screen_pays
from certify.enclose.options import box_bound_options
from certify.enclose.preconditioner import (
    candidate_preconditioners,
    diagonal_preconditioner,
    to_lam_max_D,
)
from certify.model.kernels import mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status

from ..planted import lam_cert_linear, linear_problem, linear_system
from ..soak import examples

F64 = torch.float64


def _metric(seed: int, n: int, cond: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    Qm, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return Qm @ np.diag(np.geomspace(1.0, cond, n)) @ Qm.T


def _problem(seed: int, n: int, cond: float) -> Problem:
    A = -np.eye(n) + 0.4 * np.diag(np.ones(n - 1), 1)
    C = np.eye(1, n)
    system = linear_system(A, C, lam=0.1, P=_metric(seed, n, cond), name="chainp")
    gen = torch.Generator().manual_seed(seed)
    net = GainNetwork(n, 1, (6, 5), structure="direct", K=torch.randn(n, 1, generator=gen))
    with torch.no_grad():  # every parameter from `gen` (biases as PyTorch's default init)
        for layer in net.layers:
            fan_in = layer.weight.shape[1]
            layer.weight.copy_(2.0 * torch.randn(layer.weight.shape, generator=gen)
                               / fan_in ** 0.5)
            layer.bias.copy_((2 * torch.rand(layer.bias.shape, generator=gen) - 1)
                             / fan_in ** 0.5)
    return Problem(system, net.double(), 0.1, system.P)


@settings(max_examples=examples(10), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 4), cond=st.sampled_from([1.5, 8.0, 60.0]),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3]))
@pytest.mark.slow
def test_every_candidate_bounds_lam_max_of_D_over_boxes(seed: int, n: int, cond: float,
                                                        scale: float) -> None:
    prob = _problem(seed, n, cond)
    d = n + 1
    gen = torch.Generator().manual_seed(seed + 7)
    c = 2 * torch.rand(6, d, generator=gen, dtype=F64) - 1
    lo, hi = c - scale, c + scale
    u = torch.rand(6, 200, d, generator=gen, dtype=F64)
    u[:, 0], u[:, 1] = 0.0, 1.0
    z = (lo[:, None] + (hi - lo)[:, None] * u).reshape(-1, d)
    v = mpdi_lam_max(prob.system, prob.network, prob.P_t, prob.lam, z[:, :n], z[:, n:])
    vmax = v.reshape(6, -1).amax(1)
    cands = candidate_preconditioners(prob.P_t)
    assert [pc.kind for pc in cands] == ["cholesky", "none", "diagonal"]
    for pc in cands:
        for crown, plain_screen in ((False, True), (True, True), (True, False)):
            bb = mpdi_box_bounds(box_bound_options(prob, prob.lam, pc=pc, crown=crown,
                                                   plain_screen=plain_screen), lo, hi)
            ub = to_lam_max_D(bb.upper, prob.P_t, pc)
            assert bool((torch.isnan(ub) | (vmax <= ub)).all()), (pc.kind, crown)


@settings(max_examples=examples(20), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 5))
def test_diagonal_congruence_converts_back_soundly(seed: int, n: int) -> None:
    """A <= a I with A = M D M^T gives lam_max(D) <= to_lam_max_D(a), either sign of a."""
    g = torch.Generator().manual_seed(seed)
    R = torch.randn(n, n, generator=g, dtype=F64)
    P = R @ R.T + 0.1 * torch.eye(n, dtype=F64)
    m = torch.exp(2 * torch.randn(n, generator=g, dtype=F64))
    pc = diagonal_preconditioner(P, m)
    D = torch.randn(32, n, n, generator=g, dtype=F64)
    D = 0.5 * (D + D.transpose(1, 2)) + torch.linspace(-6, 3, 32, dtype=F64)[:, None, None] \
        * torch.eye(n, dtype=F64)
    A = pc.M @ D @ pc.M.T
    a = torch.linalg.eigvalsh(A)[:, -1]
    a = a + 1e-12 * (1 + a.abs())  # an upper bound of lam_max(A)
    ub = to_lam_max_D(a, P, pc)
    assert bool((torch.linalg.eigvalsh(D)[:, -1] <= ub + 1e-12 * (1 + ub.abs())).all())


def test_identity_metric_has_one_candidate_and_choice_is_deterministic() -> None:
    prob = _problem(3, 3, 1.0)
    prob_i = Problem(prob.system, prob.network, prob.lam, np.eye(3))
    assert choose_preconditioner(prob_i, 0.1).identity
    prob = _problem(5, 3, 30.0)
    a, b = choose_preconditioner(prob, 0.1), choose_preconditioner(prob, 0.1)
    assert a.kind == b.kind and torch.equal(a.M, b.M)


def test_linear_metric_problem_decides_as_its_closed_form() -> None:
    """f = A x, k = K (y - x1) with a metric P: PROVED just below lam_cert, VIOLATED above."""
    A = np.array([[-1.0, 2.0, 0.0], [0.0, -1.0, 1.5], [-0.5, 0.0, -1.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    K = np.array([[1.0], [0.5], [-0.3]])
    J = A - K @ C
    P = scipy.linalg.solve_continuous_lyapunov(J.T, -np.eye(3))  # J^T P + P J = -I
    lc = lam_cert_linear(A, C, K, P)
    assert lc > 0.05 and np.linalg.cond(P) > 3
    for lam, want in ((0.95 * lc, Status.PROVED), (1.05 * lc, Status.VIOLATED)):
        prob = linear_problem(A, C, K, lam=lam, P=P)
        out = prove_mpdi(prob)
        assert out.status == want, (lam, lc, out.message)


def test_each_split_rule_scores_every_dimension() -> None:
    from certify.enclose.split import split_score

    prob = _problem(2, 3, 8.0)
    root = torch.tensor([[-1.0, 1.0]] * 4, dtype=F64)
    r = torch.tensor([[0.1, 0.2, 0.05, 0.3]], dtype=F64)
    ts = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    assert int(split_score("widest", ts, r, root[:, 1] - root[:, 0], prob.network).argmax()) == 3
    assert int(split_score("taylor", ts, r, None, prob.network).argmax()) == 0
    W0 = prob.network.weights()[0][0].abs().sum(0)
    want = int((r[0] * W0 / (r[0] * W0).max() + 0.5 * ts[0]).argmax())
    assert int(split_score("sensitivity", ts, r, None, prob.network).argmax()) == want


def test_plain_screen_is_kept_where_it_closes_boxes_and_dropped_where_it_cannot() -> None:
    """`plain_screen_pays`: on a linear observer well inside its rate (the plain interval
    bound is nearly exact there) it keeps the screen; above the rate (no box can close) it
    drops it; and proofs decide the same with the screen on or off."""
    A = np.array([[-1.0, 2.0, 0.0], [0.0, -1.0, 1.5], [-0.5, 0.0, -1.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    K = np.array([[1.0], [0.5], [-0.3]])
    P = scipy.linalg.solve_continuous_lyapunov((A - K @ C).T, -np.eye(3))
    lc = lam_cert_linear(A, C, K, P)
    inside = linear_problem(A, C, K, lam=0.5 * lc, P=P)
    above = linear_problem(A, C, K, lam=1.5 * lc, P=P)
    for prob, want in ((inside, True), (above, False)):
        pc = diagonal_preconditioner(prob.P_t, torch.ones(3, dtype=F64), "none")
        assert plain_screen_pays(prob, prob.lam, pc) is want
    # the 2-layer gain-2 network with a metric: the screen never changes a bound's soundness
    prob = _problem(11, 3, 8.0)
    pc = diagonal_preconditioner(prob.P_t, torch.ones(3, dtype=F64), "none")
    gen = torch.Generator().manual_seed(3)
    c = 2 * torch.rand(32, 4, generator=gen, dtype=F64) - 1
    opts = box_bound_options(prob, prob.lam, pc=pc, screen=0.0, decide=True)
    on = mpdi_box_bounds(opts, c - 0.02, c + 0.02)
    off = mpdi_box_bounds(box_bound_options(prob, prob.lam, pc=pc, screen=0.0, decide=True,
                                            plain_screen=False), c - 0.02, c + 0.02)
    assert bool((off.plain == float("inf")).all())
    # where the plain stage did not close a box, the linear bounds are the same either way
    # (to LAPACK's sub-batch last bits), so the screen only ever adds closed boxes
    rest = ~(on.plain <= 0)
    assert bool(rest.any())
    assert torch.allclose(on.taylor[rest], off.taylor[rest], rtol=0, atol=1e-9)
    assert bool(((off.upper <= 0) <= (on.upper <= 0)).all())


def test_ties_in_closed_probes_go_to_the_smaller_bound() -> None:
    """examples/vdp2_lmi.ckpt: M ~ L^-1 and M = I both close every probe box; the proof with
    the first took 88,768 boxes (30 s), with the second 256. The tie-break by the probes'
    median bound on lam_max(D) must pick the tighter one, and the proof stays small."""
    from pathlib import Path

    from certify.model import checkpoint

    path = Path(__file__).parents[2] / "examples" / "vdp2_lmi.ckpt"
    prob = checkpoint.load(str(path)).problem
    pc = choose_preconditioner(prob, prob.lam)
    assert pc.kind == "none"
    out = prove_mpdi(prob)
    assert out.status is Status.PROVED and out.stats.boxes_processed <= 2048
