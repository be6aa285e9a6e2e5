"""Batched point kernels shared by every check: k and its Jacobians, D, lam_max, rates.

Shapes: xhat [B, n], y [B, p]; matrices [B, n, n]. No I/O, no Python loops over points.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.linalg import dwarfed, eigvalsh
from certify.model.gain import gain_at_points
from certify.model.network import GainNetwork
from certify.spec.system import System


@dataclass
class GainTerms:
    """k [B, n], dk/dxhat [B, n, n] and (when asked for) dk/dy [B, n, p] at a batch."""

    k: torch.Tensor
    dk_dx: torch.Tensor
    dk_dy: torch.Tensor | None


def gain_terms(system: System, net: GainNetwork, xhat: torch.Tensor, y: torch.Tensor,
               with_dy: bool = True) -> GainTerms:
    """k(xhat, y) with its Jacobians for a batch (`certify.model.gain.gain_at_points`)."""
    spec = net.spec(xhat.dtype) if net.K.dtype != xhat.dtype else net.spec()
    g = gain_at_points(spec, system, xhat, y, with_dy=with_dy)
    return GainTerms(k=g.k, dk_dx=g.dk_dx, dk_dy=g.dk_dy)


def sym(M: torch.Tensor) -> torch.Tensor:
    """He{M} = (M + M^T) / 2 over the last two dimensions."""
    return 0.5 * (M + M.transpose(-1, -2))


def contraction_matrix(Jf: torch.Tensor, dk_dx: torch.Tensor | None, P: torch.Tensor,
                       lam: float, shift: torch.Tensor | None = None) -> torch.Tensor:
    """D = He{P (Jf + dk/dxhat)} + 2 lam P (+ Q, `shift` [n, n], when given), [B, n, n]
    (`dk_dx` None: Jf is the whole Jacobian)."""
    D = sym(P @ (Jf if dk_dx is None else Jf + dk_dx)) + 2.0 * lam * P
    return D if shift is None else D + shift.to(D.dtype)


def path_jacobian(J: torch.Tensor, dk_dy: torch.Tensor) -> torch.Tensor:
    """J~ = [[J, B], [0, 0]] [N, n + p, n + p] from J [N, n, n] and B = dk/dy [N, n, p]: the
    Jacobian of the path certificate's matrix (`certify.model.problem`)."""
    N, n, p = dk_dy.shape
    bottom = torch.zeros(N, p, n + p, dtype=J.dtype, device=J.device)
    return torch.cat([torch.cat([J, dk_dy], -1), bottom], -2)


def problem_matrix(problem, lam: float, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The matrix `problem` is about at a batch -> [N, m, m]: D = He{P J_cl} + 2 lam P (+ Q),
    or with a noise input the path certificate's D~ (`certify.model.problem`)."""
    noise = problem.noise is not None
    terms = gain_terms(problem.system, problem.network, xhat, y, with_dy=noise)
    J = problem.system.jac_f(xhat) + terms.dk_dx
    if noise:
        J = path_jacobian(J, terms.dk_dy)
    return contraction_matrix(J, None, problem.P_t, lam, problem.shift_t)


def problem_lam_max(problem, lam: float, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """lam_max of `problem_matrix` at a batch -> [N] (for a problem without a noise input,
    `mpdi_lam_max` with the problem's P and constant term)."""
    return lam_max(problem_matrix(problem, lam, xhat, y))


def lam_max(S: torch.Tensor) -> torch.Tensor:
    """Largest eigenvalue of symmetric matrices [B, n, n] -> [B] (closed form for n <= 2).

    n = 2: (a + c)/2 + hypot((a - c)/2, b), except where a negative diagonal entry dwarfs the
    others (`certify.arith.linalg.dwarfed`: -1e39 beside -0.5, where that form returns 0): there
    the equal
    max(a, c) + b^2 / (d + hypot(d, b)), d = |a - c|/2, which has no cancellation. Elsewhere
    the values are the textbook form's, bit for bit."""
    n = S.shape[-1]
    if n == 1:
        return S[:, 0, 0]
    if n == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        out = 0.5 * (a + c) + torch.hypot(0.5 * (a - c), b)
        swap = dwarfed(a, b, c)
        if bool(swap.any()):  # (computed on those points only: no stray gradients)
            ac, cc, bb = a[swap], c[swap], b[swap].abs()
            d = 0.5 * (ac - cc).abs()  # > 0 there
            # b^2 / (d + hypot(d, b)) as |b| (|b| / (d + hypot)): no overflow
            out = out.clone()
            out[swap] = torch.maximum(ac, cc) + bb * (bb / (d + torch.hypot(d, bb)))
        return out
    finite = torch.isfinite(S).all(dim=-1).all(dim=-1)
    if bool(finite.all()):
        return eigvalsh(S)[..., -1]
    # LAPACK fails on NaN/Inf input: evaluate the finite ones, NaN for the rest
    safe = torch.where(finite[..., None, None], S, torch.zeros_like(S))
    return torch.where(finite, eigvalsh(safe)[..., -1],
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
                 xhat: torch.Tensor, y: torch.Tensor,
                 shift: torch.Tensor | None = None) -> torch.Tensor:
    """lam_max(D(xhat, y)) for a batch -> [B] (D with the constant term `shift`, if any)."""
    terms = gain_terms(system, net, xhat, y, with_dy=False)
    return lam_max(contraction_matrix(system.jac_f(xhat), terms.dk_dx, P, lam, shift))


def pointwise_rate(system: System, net: GainNetwork, P: torch.Tensor, xhat: torch.Tensor,
                   y: torch.Tensor) -> torch.Tensor:
    """-lam_max(He{P J}, P) / 2: the largest lam with D <= 0 at each point -> [B]."""
    J = closed_loop_jacobian(system, net, xhat, y)
    return -0.5 * generalized_lam_max(sym(P @ J), P)
