"""Fast no-grad lam_max(D) for dense grids (the falsifier's inner loop).

The general kernel (`certify.model.kernels`) keeps points in rows, which suits autograd. For a dense
grid the work is many tiny 30 x 30 products and elementwise activations; storing points in columns
(feature-major, `certify.model.gain.ColumnArithmetic`) lets every layer be one large matrix product
with contiguous elementwise passes, several times faster (`bench/verify.py`, "grid"). Only the n
tangent directions of xhat are propagated (D needs dk/dxhat, not dk/dy). It covers the `direct`
structure with or without the linear term K, and the structural one (k = G (y - h(xhat))) for
the float32 screen; a structural kernel in float64 (the values a check reports) is the general
kernel's, bit for bit.

A float32 kernel is only ever a screen (`certify.search.falsify.maximize_over_box`: it selects the
points that are evaluated again in float64, it decides nothing). It is built only where every
number it combines fits float32's normal range (`float32_misfit`: the spec's constants, the
network's weights, P and lam); otherwise the kernel computes in float64 and says why in
`fallback`, and `float32_screen` gives no screen at all. A value that overflows to Inf or NaN
inside a float32 evaluation is a candidate for the float64 re-check, never a result.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from certify.model.gain import COLUMNS, compose, propagate
from certify.model.kernels import contraction_matrix, lam_max, mpdi_lam_max, pointwise_rate
from certify.model.problem import Problem

#: float32's normal range: a nonzero number outside it overflows or loses its precision
F32 = torch.finfo(torch.float32)


def _misfit(values, what: str) -> str | None:
    for v in values:
        a = abs(float(v))
        if math.isfinite(a) and a != 0.0 and not F32.tiny <= a <= F32.max:
            return f"{what} {float(v):.6g} is outside float32's range"
    return None


def float32_misfit(problem: Problem, lam: float | None = None) -> str | None:
    """Why lam_max(D) cannot be evaluated in float32 on this problem (None: it can): a
    nonzero constant of df/dx or dh/dx as the compiled tape uses it
    (`certify.spec.expr.folded_constants`), a network weight, bias or K entry, an entry of P, or
    2 lam, above float32's largest value or below its smallest normal one. (NaN/Inf entries
    are NaN/Inf in float64 too: they are not a reason to fall back.)"""
    from certify.spec.expr import folded_constants

    lam = problem.lam if lam is None else float(lam)
    system, net = problem.system, problem.network
    checks = [(folded_constants(list(system.jf_expr), system.symbols), "a constant of df/dx"),
              (folded_constants(list(system.jh_expr), system.symbols), "a constant of dh/dx"),
              ([2.0 * lam], "2 lam")]
    if net.structure != "direct":  # the structural kernel evaluates h itself
        checks.append((folded_constants(list(system.h_expr), system.symbols),
                       "a constant of h"))
    checks.append((problem.P_t.detach().reshape(-1).tolist(), "an entry of P"))
    if problem.shift is not None:
        checks.append((problem.shift_t.reshape(-1).tolist(), "an entry of the constant term Q"))
    for i, (W, b) in enumerate(net.layer_weights()):
        checks.append((W.detach().reshape(-1).tolist(), f"a weight of layer {i + 1}"))
        checks.append((b.detach().reshape(-1).tolist(), f"a bias of layer {i + 1}"))
    checks.append((net.K.detach().reshape(-1).tolist(), "an entry of K"))
    for values, what in checks:
        why = _misfit(values, what)
        if why is not None:
            return why
    return None


class GridKernel:
    """lam_max(D) at z = (xhat, y) [B, n+p] -> [B], in the dtype chosen at construction, or in
    float64 where float32 was asked for but the problem's numbers do not fit it (`fallback`
    then says why; module docstring)."""

    def __init__(self, problem: Problem, lam: float | None = None,
                 dtype: torch.dtype = torch.float64) -> None:
        self.problem = problem
        self.lam = problem.lam if lam is None else float(lam)
        self.fallback: str | None = None
        if dtype == torch.float32:
            self.fallback = float32_misfit(problem, self.lam)
            if self.fallback is not None:
                dtype = torch.float64
        self.dtype = dtype
        net = problem.network
        self.structural = net.structure != "direct"
        self.fast = not self.structural or dtype == torch.float32
        self.spec = net.spec(dtype, detach=True)
        self.P = problem.P_t.to(dtype)
        self.shift = None if problem.shift is None else problem.shift_t.to(dtype)
        self.n = problem.n

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        problem, n = self.problem, self.n
        if not self.fast:
            z64 = z.to(torch.float64)
            return mpdi_lam_max(problem.system, problem.network, problem.P_t, self.lam,
                                z64[:, :n], z64[:, n:], problem.shift_t).to(self.dtype)
        z = z.to(self.dtype)
        xhat = z[:, :n]
        net = propagate(self.spec, COLUMNS, z, n)
        system = problem.system
        Hx = system.jac_h(xhat) if self.spec.has_K or self.structural else None
        r = z[:, n:] - system.h(xhat) if self.structural else None
        dk_dx = compose(self.spec, COLUMNS, net, r, Hx, with_dy=False, with_k=False).dk_dx
        return lam_max(contraction_matrix(problem.system.jac_f(xhat), dk_dx, self.P, self.lam,
                                          self.shift))


def float32_screen(problem: Problem, lam: float | None = None) -> GridKernel | None:
    """The float32 screen of the grid sweep, or None where the problem's numbers do not fit
    float32 (`float32_misfit`: the sweep then runs in float64 alone)."""
    screen = GridKernel(problem, lam, dtype=torch.float32)
    return screen if screen.fallback is None else None


def float32_rate_screen(problem: Problem) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The float32 screen of the rate grid: z = (xhat, y) [B, n+p] -> -pointwise_rate [B]
    (`certify.model.kernels.pointwise_rate`, the score the rate check maximises) in float32;
    or None where the problem's numbers do not fit float32 (`float32_misfit`) or P has no
    float32 Cholesky factor (the pencil's). Like the MPDI screen, it only selects the points
    evaluated again in float64 (`certify.search.falsify.maximize_over_box`)."""
    if float32_misfit(problem) is not None:
        return None
    P32 = problem.P_t.detach().to(torch.float32)
    if bool(torch.linalg.cholesky_ex(P32).info.any()):
        return None
    system, net, n = problem.system, problem.network, problem.n

    def screen(z: torch.Tensor) -> torch.Tensor:
        z = z.to(torch.float32)
        return -pointwise_rate(system, net, P32.to(z.device), z[:, :n], z[:, n:])

    return screen

