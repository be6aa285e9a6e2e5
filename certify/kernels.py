"""Batched point kernels shared by every check: k and its Jacobians, D, lam_max, rates.

Shapes: xhat [B, n], y [B, p]; matrices [B, n, n]. No I/O, no Python loops over points.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.network import GainNetwork
from certify.system import System


@dataclass
class GainTerms:
    """k [B, n], dk/dxhat [B, n, n] and (when asked for) dk/dy [B, n, p] at a batch."""

    k: torch.Tensor
    dk_dx: torch.Tensor
    dk_dy: torch.Tensor | None


def gain_terms(system: System, net: GainNetwork, xhat: torch.Tensor, y: torch.Tensor,
               with_dy: bool = True) -> GainTerms:
    """k(xhat, y) with its Jacobians for a batch, composing the MLP with y - h(xhat)."""
    n = system.n
    z = torch.cat([xhat, y], dim=1)
    need_cols = n + system.p if (with_dy or net.structure == "structural") else n
    out, J = net.forward_with_jacobian(z, columns=need_cols)
    K = net.K.to(xhat.dtype)
    has_K = bool(torch.any(K != 0))
    needs_h = net.structure == "structural" or has_K
    if needs_h:
        r = y - system.h(xhat)  # [B, p]
        Hx = system.jac_h(xhat)  # [B, p, n]
    if net.structure == "direct":
        k, dk_dx = out, J[:, :, :n]
        dk_dy = J[:, :, n:] if with_dy else None
    else:
        B, p = z.shape[0], system.p
        G = out.reshape(B, n, p)
        dG = J.reshape(B, n, p, n + p)
        k = torch.einsum("bij,bj->bi", G, r)
        dk_dx = torch.einsum("bijm,bj->bim", dG[..., :n], r) - G @ Hx
        dk_dy = (torch.einsum("bijm,bj->bim", dG[..., n:], r) + G) if with_dy else None
    if has_K:
        k = k + r @ K.T
        dk_dx = dk_dx - K @ Hx
        if dk_dy is not None:
            dk_dy = dk_dy + K
    return GainTerms(k=k, dk_dx=dk_dx, dk_dy=dk_dy)


def sym(M: torch.Tensor) -> torch.Tensor:
    """He{M} = (M + M^T) / 2 over the last two dimensions."""
    return 0.5 * (M + M.transpose(-1, -2))


def contraction_matrix(Jf: torch.Tensor, dk_dx: torch.Tensor, P: torch.Tensor,
                       lam: float) -> torch.Tensor:
    """D = He{P (Jf + dk/dxhat)} + 2 lam P, shape [B, n, n]."""
    return sym(P @ (Jf + dk_dx)) + 2.0 * lam * P


def lam_max(S: torch.Tensor) -> torch.Tensor:
    """Largest eigenvalue of symmetric matrices [B, n, n] -> [B] (closed form for n <= 2)."""
    n = S.shape[-1]
    if n == 1:
        return S[:, 0, 0]
    if n == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        return 0.5 * (a + c) + torch.hypot(0.5 * (a - c), b)
    finite = torch.isfinite(S).all(dim=-1).all(dim=-1)
    if bool(finite.all()):
        return torch.linalg.eigvalsh(S)[..., -1]
    # LAPACK fails on NaN/Inf input: evaluate the finite ones, NaN for the rest
    safe = torch.where(finite[..., None, None], S, torch.zeros_like(S))
    return torch.where(finite, torch.linalg.eigvalsh(safe)[..., -1],
                       torch.full_like(S[..., 0, 0], float("nan")))


def generalized_lam_max(S: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """Largest eigenvalue of the pencil (S, P): max_v v^T S v / v^T P v, S [B,n,n], P [n,n]."""
    L = torch.linalg.cholesky(P)
    Linv = torch.linalg.inv(L)
    return lam_max(sym(Linv @ S @ Linv.T))


def closed_loop_jacobian(system: System, net: GainNetwork, xhat: torch.Tensor,
                         y: torch.Tensor) -> torch.Tensor:
    """Jf(xhat) + dk/dxhat(xhat, y), shape [B, n, n]."""
    terms = gain_terms(system, net, xhat, y, with_dy=False)
    return system.jac_f(xhat) + terms.dk_dx


def mpdi_lam_max(system: System, net: GainNetwork, P: torch.Tensor, lam: float,
                 xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """lam_max(D(xhat, y)) for a batch -> [B]."""
    terms = gain_terms(system, net, xhat, y, with_dy=False)
    return lam_max(contraction_matrix(system.jac_f(xhat), terms.dk_dx, P, lam))


def pointwise_rate(system: System, net: GainNetwork, P: torch.Tensor, xhat: torch.Tensor,
                   y: torch.Tensor) -> torch.Tensor:
    """-lam_max(He{P J}, P) / 2: the largest lam with D <= 0 at each point -> [B]."""
    J = closed_loop_jacobian(system, net, xhat, y)
    return -0.5 * generalized_lam_max(sym(P @ J), P)
