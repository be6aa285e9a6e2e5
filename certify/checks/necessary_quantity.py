"""The quantities of the necessary condition (METHOD §3.5), batched over points.

With S(xhat) = He{P Jf(xhat)} + 2 lam P, the part of D that no gain changes along ker dh:

- q(xhat) = lam_max(Z^T S Z), Z an orthonormal basis of ker dh(xhat) (`q_values`,
  `manifold_quantity`): > 0 anywhere on the output manifold means no gain can pass;
- the largest rate any gain with exact BC could have at a point (`rate_values`);
- for linear h, the residual eps_bar any gain satisfying the MPDI everywhere must pay,
  from chords along ker C (`residual_price`).

Float64 point evaluations (the sampled side of `certify.checks.necessary`); the sound side is
`certify.checks.necessary_bound`.
"""

from __future__ import annotations

import math

import torch

from certify.checks.metric import kernel_basis, output_matrix
from certify.model.kernels import lam_max
from certify.spec.system import System

_F64 = torch.float64


def gain_free_D(system: System, P: torch.Tensor, lam: float, x: torch.Tensor,
                with_lam: bool = True) -> torch.Tensor:
    """S(x) = He{P Jf(x)} + 2 lam P [B, n, n] (without 2 lam P unless `with_lam`): the part of
    D that no gain changes along ker dh, at x [B, n]."""
    PJ = P @ system.jac_f(x)
    S = 0.5 * (PJ + PJ.transpose(-1, -2))
    return S + 2.0 * lam * P if with_lam else S


def manifold_quantity(system: System, P, lam: float, x: torch.Tensor) -> torch.Tensor:
    """q(xhat) [B] at points x [B, n], for any h (constant kernel basis when h is linear)."""
    Z = None
    if system.h_is_linear:
        Z = torch.as_tensor(kernel_basis(output_matrix(system)), dtype=_F64)
    return q_values(system, torch.as_tensor(P, dtype=_F64), lam, x, Z)


def q_values(system: System, P: torch.Tensor, lam: float, x: torch.Tensor,
             Z: torch.Tensor | None) -> torch.Tensor:
    """q(x) [B] (differentiable). Z: constant kernel basis (linear h) or None (nonlinear h).

    Nonlinear h: with the projector Pi onto ker dh(x), q = lam_max(Pi S Pi - c (I - Pi)),
    c > ||S||, which equals the kernel-restricted lam_max; NaN where dh loses rank.
    """
    S = gain_free_D(system, P, lam, x)
    if Z is not None:
        return lam_max(Z.T @ S @ Z)
    Jh = system.jac_h(x)  # [B, p, n]
    G = Jh @ Jh.transpose(-1, -2)
    n = system.n
    eye = torch.eye(n, dtype=_F64)
    try:
        Pi = eye - Jh.transpose(-1, -2) @ torch.linalg.solve(G, Jh)
    except RuntimeError:
        return torch.full((x.shape[0],), float("nan"), dtype=_F64)
    c = torch.linalg.matrix_norm(S).detach() + 1.0
    return lam_max(Pi @ S @ Pi - c[:, None, None] * (eye - Pi))


def kernel_bases_at(system: System, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point kernel bases for nonlinear h: Z [B, n, n-p] and a validity mask [B]."""
    Jh = system.jac_h(x)
    _, sv, Vh = torch.linalg.svd(Jh, full_matrices=True)
    p = Jh.shape[1]
    ok = sv[:, -1] > 1e-9 * (1.0 + sv[:, 0])
    return Vh[:, p:, :].transpose(-1, -2), ok


def rate_values(system: System, P: torch.Tensor, x: torch.Tensor, Z: torch.Tensor | None
                ) -> torch.Tensor:
    """-lam_max(Z^T He{P Jf} Z, Z^T P Z) / 2 at x [B] (the largest rate any exact-BC gain
    could have at that point); NaN where the kernel basis is unavailable."""
    S0 = gain_free_D(system, P, 0.0, x, with_lam=False)
    if Z is not None:
        A, Bm = Z.T @ S0 @ Z, Z.T @ P @ Z
        L = torch.linalg.cholesky(Bm)
        Li = torch.linalg.inv(L)
        return -0.5 * lam_max(Li @ A @ Li.T)
    Zb, ok = kernel_bases_at(system, x)
    A = Zb.transpose(-1, -2) @ S0 @ Zb
    Bm = Zb.transpose(-1, -2) @ P @ Zb
    L, info = torch.linalg.cholesky_ex(Bm)
    Li = torch.linalg.inv(torch.where((info == 0)[:, None, None], L,
                                      torch.eye(L.shape[-1], dtype=_F64)))
    r = -0.5 * lam_max(Li @ A @ Li.transpose(-1, -2))
    return torch.where(ok & (info == 0), r, torch.full_like(r, float("nan")))


def residual_price(system: System, P: torch.Tensor, lam: float, directions: torch.Tensor,
                   bases: torch.Tensor, samples: int = 201) -> tuple[float, list[float] | None]:
    """max over chords z + s v in X (v in ker C unit, h(z) in Y) of the best sub-segment
    integral of v^T (He{P Jf} + 2 lam P) v, divided by 2 ||P v||.

    If D <= 0 held on all of X x Y, eps_bar would be at least this (METHOD §3.5); trapezoid
    quadrature on `samples` points per chord. Returns (price, [chord start..end as x0, x1]).
    """
    X = torch.as_tensor(system.X, dtype=_F64)
    best, where = 0.0, None
    for v in directions:  # a handful of kernel directions
        v = v / torch.linalg.vector_norm(v)
        a = (X[:, 0] - bases) / v  # inf/nan where v_i = 0: masked just below
        b = (X[:, 1] - bases) / v
        lo_s = torch.where(v.abs() > 1e-15, torch.minimum(a, b), torch.full_like(a, -math.inf))
        hi_s = torch.where(v.abs() > 1e-15, torch.maximum(a, b), torch.full_like(a, math.inf))
        s0, s1 = lo_s.max(1).values, hi_s.min(1).values  # [Nz]
        frac = torch.linspace(0.0, 1.0, samples, dtype=_F64)
        s = s0[:, None] + (s1 - s0)[:, None] * frac[None]  # [Nz, S]
        pts = bases[:, None, :] + s[..., None] * v  # [Nz, S, n]
        pts = torch.maximum(torch.minimum(pts, X[:, 1]), X[:, 0])
        S = gain_free_D(system, P, lam, pts.reshape(-1, system.n))
        qv = torch.einsum("i,bij,j->b", v, S, v).reshape(len(bases), samples)
        ds = ((s1 - s0) / (samples - 1))[:, None]
        seg = 0.5 * (qv[:, 1:] + qv[:, :-1]) * ds
        cum = torch.cat([torch.zeros(len(bases), 1, dtype=_F64), seg.cumsum(1)], 1)
        run_min, arg_min = torch.cummin(cum, dim=1)
        gain = cum - run_min  # best segment ending at each sample
        j = torch.argmax(gain, dim=1)
        g = gain[torch.arange(len(bases)), j]
        i_best = int(torch.argmax(g))
        val = float(g[i_best]) / (2.0 * float(torch.linalg.vector_norm(P @ v)))
        if val > best:
            jb = int(j[i_best])
            ib = int(arg_min[i_best, jb])
            best = val
            where = pts[i_best, ib].tolist() + pts[i_best, jb].tolist()
    return best, where
