"""Enclosures over boxes of a system's f, h, their Jacobians and second derivatives.

Each entry of f, h, Jf, dh/dx (the system's sympy expressions) and of the second derivatives
(sympy, cached per system) is evaluated over the boxes by `certify.spec.expr.evaluate` in the
interval algebra `certify.spec.interval_rules.INTERVAL`: outward rounding throughout
(`certify.arith.intervals.ROUNDING`), NaN where an expression is undefined somewhere in a box.
Boxes: lo, hi [B, n] (float64).
"""

from __future__ import annotations

import weakref
from typing import Any

import sympy
import torch

from certify.arith.intervals import Interval
from certify.spec.expr import evaluate
from certify.spec.interval_rules import INTERVAL

_DERIV_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _derivatives(system: Any) -> dict[str, list[sympy.Expr]]:
    """Sympy second derivatives of f and h, cached per system."""
    cached = _DERIV_CACHE.get(system)
    if cached is None:
        xs = system.symbols
        cached = {
            "hf": [sympy.diff(e, a, b) for e in system.f_expr for a in xs for b in xs],
            "hh": [sympy.diff(e, a, b) for e in system.h_expr for a in xs for b in xs],
        }
        _DERIV_CACHE[system] = cached
    return cached


def enclose_list(system: Any, exprs: list[sympy.Expr], lo: torch.Tensor, hi: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    if lo.ndim != 2 or lo.shape[1] != system.n or lo.shape != hi.shape:
        raise ValueError(f"expected boxes lo, hi of shape [batch, {system.n}]; got "
                         f"{list(lo.shape)} and {list(hi.shape)}")
    lo, hi = lo.to(torch.float64), hi.to(torch.float64)
    env = {s: Interval(lo[:, i], hi[:, i]) for i, s in enumerate(system.symbols)}
    like = Interval(lo[:, 0], hi[:, 0])
    outs = [evaluate(e, env, INTERVAL, like) for e in exprs]
    return torch.stack([o.lo for o in outs], -1), torch.stack([o.hi for o in outs], -1)


def f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """f over boxes: lo, hi [B, n] -> [B, n] each."""
    return enclose_list(system, system.f_expr, lo, hi)


def h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """h over boxes: lo, hi [B, n] -> [B, p] each."""
    return enclose_list(system, system.h_expr, lo, hi)


def jacobian_f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic Jf over boxes: lo, hi [B, n] -> Jlo, Jhi [B, n, n]."""
    a, b = enclose_list(system, list(system.jf_expr), lo, hi)
    n = system.n
    return a.reshape(-1, n, n), b.reshape(-1, n, n)


def jacobian_h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic dh/dx over boxes -> [B, p, n] each."""
    a, b = enclose_list(system, list(system.jh_expr), lo, hi)
    return a.reshape(-1, system.p, system.n), b.reshape(-1, system.p, system.n)


def hessian_f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """d^2 f_i / dx_j dx_k over boxes -> [B, n, n, n] (index order i, j, k)."""
    a, b = enclose_list(system, _derivatives(system)["hf"], lo, hi)
    n = system.n
    return a.reshape(-1, n, n, n), b.reshape(-1, n, n, n)


def hessian_h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """d^2 h_l / dx_j dx_k over boxes -> [B, p, n, n]."""
    a, b = enclose_list(system, _derivatives(system)["hh"], lo, hi)
    n = system.n
    return a.reshape(-1, system.p, n, n), b.reshape(-1, system.p, n, n)


def hessian_f_point(system: Any, x: torch.Tensor) -> torch.Tensor:
    """Point second derivatives of f at x [B, n] -> [B, n, n, n] (for tests)."""
    from certify.spec.expr import TORCH

    env = {s: x[:, i] for i, s in enumerate(system.symbols)}
    vals = [evaluate(e, env, TORCH, x[:, 0]) for e in _derivatives(system)["hf"]]
    n = system.n
    return torch.stack(vals, -1).reshape(-1, n, n, n)


def pad_y(iv: Interval, p: int) -> Interval:
    """Derivatives in xhat [..., n] as derivatives in z = (xhat, y) [..., n + p] (exact zero
    columns for y: f and h do not depend on y)."""
    z = torch.zeros(*iv.lo.shape[:-1], p, dtype=iv.lo.dtype, device=iv.lo.device)
    return Interval(torch.cat([iv.lo, z], -1), torch.cat([iv.hi, z], -1))


def residual_jacobian(Hx: Interval) -> Interval:
    """dr/dz = (-dh/dxhat | I) [B, p, n + p] for r = y - h(xhat), from Hx = dh/dxhat
    [B, p, n] (negation and the identity are exact)."""
    B, p, _ = Hx.lo.shape
    eye = torch.eye(p, dtype=Hx.lo.dtype, device=Hx.lo.device).expand(B, p, p)
    return Interval(torch.cat([-Hx.hi, eye], -1), torch.cat([-Hx.lo, eye], -1))
