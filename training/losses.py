"""Training losses on the contraction matrix D and the boundary-condition residual.

- `minor_loss`: the source method's Sylvester-minor MPDI loss with the sign fix: for every
  leading principal minor Delta_i of D, the penalty `relu((-1)^(i+1) Delta_i)`, weighted by
  rho_i and averaged over points. It is zero exactly when the non-strict Sylvester signs hold,
  which is necessary for D <= 0 but not sufficient (D = diag(0, 1) gives zero): the verifier
  never relies on it.
- `eigen_loss`: `relu(lam_max(D) + margin)` (or its square), zero only when D <= -margin I.
- `bc_loss`: mean ||k(x, h(x))||^2.

Shapes: D [B, n, n], k [B, n]. Everything is differentiable with autograd.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class LossWeights:
    """Weights of L = mu1 * L_MPDI + mu2 * L_BC, and rho_i per leading minor."""

    mu1: float
    mu2: float
    rho: tuple[float, ...]


def leading_minors(D: torch.Tensor) -> torch.Tensor:
    """Leading principal minors det(D[:, :i, :i]), i = 1..n, of a batch [B, n, n] -> [B, n].

    Closed forms for i <= 3 (cheap, with well-behaved gradients at singular blocks);
    `torch.linalg.det` of the leading block beyond.
    """
    n = D.shape[-1]
    out = [D[:, 0, 0]]
    if n >= 2:
        out.append(D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0])
    if n >= 3:
        a, b, c = D[:, 0, 0], D[:, 0, 1], D[:, 0, 2]
        d, e, f = D[:, 1, 0], D[:, 1, 1], D[:, 1, 2]
        g, h, i = D[:, 2, 0], D[:, 2, 1], D[:, 2, 2]
        out.append(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))
    for k in range(4, n + 1):
        out.append(torch.linalg.det(D[:, :k, :k]))
    return torch.stack(out, dim=-1)


def minor_penalties(D: torch.Tensor) -> torch.Tensor:
    """relu((-1)^(i+1) Delta_i) per point and minor, [B, n]: zero iff the Sylvester signs
    of a negative semidefinite matrix (non-strict) hold."""
    minors = leading_minors(D)
    n = D.shape[-1]
    sign = torch.tensor([1.0 if i % 2 == 1 else -1.0 for i in range(1, n + 1)],
                        dtype=D.dtype, device=D.device)
    return torch.relu(minors * sign)


def minor_loss(D: torch.Tensor, rho: Sequence[float], reduce: str = "mean") -> torch.Tensor:
    """L_MPDI = mean_j sum_i rho_i relu((-1)^(i+1) Delta_i(D_j)); `reduce="sum"` sums over j."""
    w = torch.as_tensor(list(rho), dtype=D.dtype, device=D.device)
    if w.shape != (D.shape[-1],):
        raise ValueError(f"rho needs {D.shape[-1]} weights (one per leading minor); "
                         f"got {len(list(rho))}")
    per_point = minor_penalties(D) @ w
    return per_point.sum() if reduce == "sum" else per_point.mean()


def lam_max_for_training(D: torch.Tensor) -> torch.Tensor:
    """lam_max of symmetric [B, n, n] -> [B], with finite gradients everywhere.

    For n = 2 the closed form 0.5 (a + c) + hypot(0.5 (a - c), b) has a 0/0 gradient where the
    two eigenvalues coincide; there the radius term gets gradient 0 (a valid subgradient).
    For n >= 3 `eigvalsh`, whose eigenvalue gradients stay finite.
    """
    n = D.shape[-1]
    if n == 1:
        return D[:, 0, 0]
    if n == 2:
        a, b, c = D[:, 0, 0], 0.5 * (D[:, 0, 1] + D[:, 1, 0]), D[:, 1, 1]
        d = 0.5 * (a - c)
        pos = torch.hypot(d, b).detach() > 0
        r = torch.hypot(torch.where(pos, d, torch.ones_like(d)),
                        torch.where(pos, b, torch.zeros_like(b)))
        return 0.5 * (a + c) + torch.where(pos, r, torch.zeros_like(r))
    return torch.linalg.eigvalsh(0.5 * (D + D.transpose(-1, -2)))[..., -1]


def eigen_loss(D: torch.Tensor, margin: float = 0.0, squared: bool = False,
               reduce: str = "mean") -> torch.Tensor:
    """mean_j relu(lam_max(D_j) + margin) (or its square): zero iff D_j <= -margin I for all j."""
    v = torch.relu(lam_max_for_training(D) + margin)
    if squared:
        v = v * v
    return v.sum() if reduce == "sum" else v.mean()


def bc_loss(k_bc: torch.Tensor, reduce: str = "mean") -> torch.Tensor:
    """L_BC = mean_j ||k(x_j, h(x_j))||^2 for k_bc [B, n]."""
    per_point = (k_bc * k_bc).sum(dim=-1)
    return per_point.sum() if reduce == "sum" else per_point.mean()


def total_loss(mpdi: torch.Tensor, bc: torch.Tensor, weights: LossWeights) -> torch.Tensor:
    """L = mu1 * L_MPDI + mu2 * L_BC."""
    return weights.mu1 * mpdi + weights.mu2 * bc


def minor_loss_sum_and_grad(D: torch.Tensor, rho: Sequence[float]
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """sum_j sum_i rho_i relu((-1)^(i+1) Delta_i(D_j)) and its gradient w.r.t. D [B, n, n].

    Closed form for n <= 2 (the training hot path: no autograd graph); autograd beyond.
    At a kink (a minor exactly 0) the gradient of relu is taken as 0, as torch does.
    """
    n = D.shape[-1]
    w = [float(r) for r in rho]
    if n > 2:
        Dl = D.detach().requires_grad_(True)
        with torch.enable_grad():
            value = minor_loss(Dl, w, reduce="sum")
            (grad,) = torch.autograd.grad(value, [Dl])
        return value.detach(), grad
    grad = torch.zeros_like(D)
    a = D[:, 0, 0]
    on1 = (a > 0).to(D.dtype)
    value = w[0] * (a * on1).sum()
    grad[:, 0, 0] = w[0] * on1
    if n == 2:
        b, c, d = D[:, 0, 1], D[:, 1, 0], D[:, 1, 1]
        delta2 = a * d - b * c
        on2 = (delta2 < 0).to(D.dtype) * w[1]
        value = value - (delta2 * on2).sum()
        grad[:, 0, 0] -= on2 * d
        grad[:, 1, 1] = -on2 * a
        grad[:, 0, 1] = on2 * c
        grad[:, 1, 0] = on2 * b
    return value, grad
