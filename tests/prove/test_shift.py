"""The constant term Q of D = He{P J} + 2 lam P + Q: known answers through every route.

For a linear system with a linear gain D is constant, so lam_max(D + Q) is known exactly: the
prover must prove it when it is below 0 and find a sound witness when it is above, whatever
the congruence, in process and on Dask workers; the point kernels and witnesses see Q too.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from certify.model.kernels import contraction_matrix
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.witness import mpdi_lower
from tests.planted import linear_problem

A = np.array([[0.0, 1.0], [-2.0, -1.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [0.5]])
P = np.array([[3.0, 0.5], [0.5, 1.0]])
LAM = 0.2


def _base():
    return linear_problem(A, C, K, lam=LAM, P=P)


def _d0() -> np.ndarray:
    J = A - K @ C
    return 0.5 * (P @ J + (P @ J).T) + 2 * LAM * P


def _shift_to(level: float) -> np.ndarray:
    """A PSD rank-one Q = c u u^T with lam_max(D0 + Q) = level (bisection on c)."""
    D0 = _d0()
    u = P @ np.array([1.0, -0.7])
    lo, hi = 0.0, 1e3
    for _ in range(200):
        c = 0.5 * (lo + hi)
        top = np.linalg.eigvalsh(D0 + c * np.outer(u, u))[-1]
        lo, hi = (c, hi) if top < level else (lo, c)
    return lo * np.outer(u, u)


@pytest.mark.parametrize("level", [-1e-3, 1e-3])
def test_shifted_constant_matrix_is_decided_exactly(level):
    base = _base()
    assert np.linalg.eigvalsh(_d0())[-1] < -0.05  # the MPDI alone holds with room
    Q = _shift_to(level)
    problem = dataclasses.replace(base, shift=Q)
    out = prove_mpdi(problem, max_boxes=20_000)
    if level < 0:
        assert out.status == Status.PROVED and out.upper <= 0
    else:
        assert out.status == Status.VIOLATED
        z = torch.zeros(1, problem.n + problem.p, dtype=torch.float64)
        assert float(mpdi_lower(problem, z)[0]) > 0  # a sound witness anywhere (D constant)
    # without Q the same network proves
    assert prove_mpdi(base, max_boxes=20_000).status == Status.PROVED


def test_point_kernel_adds_the_shift():
    Q = _shift_to(0.3)
    Jf = torch.as_tensor(A)[None]
    dk = torch.as_tensor(-K @ C)[None]
    D = contraction_matrix(Jf, dk, torch.as_tensor(P), LAM, torch.as_tensor(Q))[0].numpy()
    assert np.allclose(D, _d0() + Q, atol=1e-12)
    assert abs(np.linalg.eigvalsh(D)[-1] - 0.3) < 1e-9


def test_the_rate_proof_refuses_a_shift():
    from certify.prove.mpdi import prove_rate

    problem = dataclasses.replace(_base(), shift=_shift_to(-0.01))
    with pytest.raises(ValueError, match="constant term"):
        prove_rate(problem)


@pytest.mark.slow
@pytest.mark.slow
def test_dask_workers_see_the_shift():
    pytest.importorskip("distributed")
    from certify.search.distributed.executor import DaskExecutor

    ex = DaskExecutor(workers=1)
    try:
        for level, status in ((1e-3, Status.VIOLATED), (-1e-3, Status.PROVED)):
            problem = dataclasses.replace(_base(), shift=_shift_to(level))
            out = prove_mpdi(problem, max_boxes=20_000, executor=ex)
            assert out.status == status
    finally:
        ex.close()
