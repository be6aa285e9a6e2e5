"""Fast no-grad lam_max(D) for dense grids (the falsifier's inner loop).

The general kernel (`certify.kernels`) keeps points in rows, which suits autograd. For a dense
grid the work is many tiny 30 x 30 products and elementwise tanh; storing points in columns
(feature-major, [width, batch]) lets every layer be one large matrix product with contiguous
elementwise passes, several times faster. Only the n tangent directions of xhat are propagated
(D needs dk/dxhat, not dk/dy). It covers the `direct` structure with or without the linear term
K; other structures use the general kernel.
"""

from __future__ import annotations

import torch

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
        self.W = [layer.weight.detach().to(dtype).contiguous() for layer in net.layers]
        self.b = [layer.bias.detach().to(dtype)[:, None].contiguous() for layer in net.layers]
        self.K = net.K.detach().to(dtype)
        self.has_K = bool(torch.any(self.K != 0))
        self.P = problem.P_t.to(dtype)
        self.n = problem.n

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        problem, n = self.problem, self.n
        if not self.fast:
            z64 = z.to(torch.float64)
            return mpdi_lam_max(problem.system, problem.network, problem.P_t, self.lam,
                                z64[:, :n], z64[:, n:]).to(self.dtype)
        z = z.to(self.dtype)
        B = z.shape[0]
        pre = torch.addmm(self.b[0], self.W[0], z.T)  # [h, B]
        tang = self.W[0][:, :n, None].expand(-1, n, B)  # [h, n, B]: d pre / d xhat
        for W, b in zip(self.W[1:], self.b[1:]):
            t = torch.tanh(pre)
            s = t * t
            s.neg_().add_(1.0)  # tanh' = 1 - tanh^2
            scaled = (tang * s[:, None, :]).reshape(-1, n * B)
            tang = torch.mm(W, scaled).view(W.shape[0], n, B)  # one product for all tangents
            pre = torch.addmm(b, W, t)
        dk_dx = tang.permute(2, 0, 1)  # [B, n_out, n]
        xhat = z[:, :n]
        Jf = problem.system.jac_f(xhat)
        if self.has_K:
            dk_dx = dk_dx - self.K @ problem.system.jac_h(xhat)
        return lam_max(contraction_matrix(Jf, dk_dx, self.P, self.lam))
