"""Fast no-grad lam_max(D) for dense grids (the falsifier's inner loop).

The general kernel (`certify.kernels`) keeps points in rows, which suits autograd. For a dense
grid the work is many tiny 30 x 30 products and elementwise activations; storing points in
columns (feature-major, `certify.gain.ColumnArithmetic`) lets every layer be one large matrix
product with contiguous elementwise passes, several times faster. Only the n tangent
directions of xhat are propagated (D needs dk/dxhat, not dk/dy). It covers the `direct`
structure with or without the linear term K; other structures use the general kernel.
"""

from __future__ import annotations

import torch

from certify.gain import COLUMNS, compose, propagate
from certify.kernels import contraction_matrix, lam_max, mpdi_lam_max
from certify.problem import Problem


class GridKernel:
    """lam_max(D) at z = (xhat, y) [B, n+p] -> [B], in the dtype chosen at construction."""

    def __init__(self, problem: Problem, lam: float | None = None,
                 dtype: torch.dtype = torch.float64) -> None:
        self.problem = problem
        self.lam = problem.lam if lam is None else float(lam)
        self.dtype = dtype
        net = problem.network
        self.fast = net.structure == "direct"
        self.spec = net.spec(dtype, detach=True)
        self.P = problem.P_t.to(dtype)
        self.n = problem.n

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        problem, n = self.problem, self.n
        if not self.fast:
            z64 = z.to(torch.float64)
            return mpdi_lam_max(problem.system, problem.network, problem.P_t, self.lam,
                                z64[:, :n], z64[:, n:]).to(self.dtype)
        z = z.to(self.dtype)
        xhat = z[:, :n]
        net = propagate(self.spec, COLUMNS, z, n)
        Hx = problem.system.jac_h(xhat) if self.spec.has_K else None
        dk_dx = compose(self.spec, COLUMNS, net, None, Hx, with_dy=False, with_k=False).dk_dx
        return lam_max(contraction_matrix(problem.system.jac_f(xhat), dk_dx, self.P, self.lam))
