"""The one propagation of the gain: MLP value and input derivatives, then the injection.

`propagate` runs the chain rule layer by layer, in forward mode, against an `Arithmetic`
(`certify.gain.arithmetic`), which decides the number kind (float32/float64 point, later
interval / Taylor / relaxation) and the memory layout. For every hidden layer:

    (a, s, s2) = f, f', f'' of the pre-activation           arith.activate
    T <- s * T                    (first derivatives)       arith.scale
    S <- s2 * (T_j T_m) + s * S   (second, order 2 only)    arith.second   (uses the old T)
    pre, T, S <- W a + b, W T, W S  (one product)           arith.affine

starting from pre = W_0 z + b_0, T = W_0[:, :m] (arith.input_layer), and an optional
`pre_hook(layer, pre, T)` that may tighten each pre-activation (the interval arithmetic's
mean-value intersection). `compose` then builds k, dk/dxhat, dk/dy from N, dN/dz and
r = y - h(xhat), dh/dxhat, for the direct or structural injection plus K r, with the
arithmetic's contraction primitives.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from certify.gain.spec import GainSpec

PreHook = Callable[[int, Any, Any], Any]


@dataclass
class NetOutput:
    """N [B, out], dN/dz[:, :, :m] [B, out, m] (None if m = 0), d2N [B, out, J, m] (order 2),
    in the arithmetic's value type."""

    value: Any
    jac: Any
    hess: Any = None


def propagate(spec: GainSpec, arith: Any, z: Any, m: int, order: int = 1,
              second_cols: int | None = None, pre_hook: PreHook | None = None) -> NetOutput:
    """N(z) with its derivatives in the first m inputs (order 2: d2/dz_j dz_k, j < second_cols).

    `z` is whatever the arithmetic takes as input ([B, d] points for the point arithmetics).
    """
    act = spec.activation
    (W0, b0), rest = spec.layers[0], spec.layers[1:]
    pre, T = arith.input_layer(z, W0, b0, m)
    J = m if second_cols is None else int(second_cols)
    S = arith.zero_second(pre, J, m) if order >= 2 else None
    for i, (W, b) in enumerate(rest, start=1):
        if pre_hook is not None:
            pre = pre_hook(i - 1, pre, T)
        a, s, s2 = arith.activate(act, pre, i, order)
        if S is not None:
            S = arith.second(s2, T, s, S, J, i)
        if T is not None:
            T = arith.scale(s, T, i)
        pre, T, S = arith.affine(a, T, S, W, b, i)
    return arith.output(pre, T, S)


@dataclass
class GainValues:
    """k [B, n], dk/dxhat [B, n, n] and (when asked for) dk/dy [B, n, p], arithmetic values."""

    k: Any
    dk_dx: Any
    dk_dy: Any | None


def columns_needed(spec: GainSpec, with_dy: bool) -> int:
    """Input derivatives `compose` needs: xhat only, or xhat and y (dk/dy, structural)."""
    return spec.n + spec.p if (with_dy or spec.structural) else spec.n


def compose(spec: GainSpec, arith: Any, net: NetOutput, r: Any, Hx: Any,
            with_dy: bool = True, with_k: bool = True) -> GainValues:
    """k and its Jacobians from N, dN/dz (columns per `columns_needed`; None for k alone)
    and, where `spec.needs_h`, r = y - h(xhat) [B, p] and Hx = dh/dxhat [B, p, n] (else
    None; r may be None when `with_k` is False and the structure is direct)."""
    n, p = spec.n, spec.p
    out, J = net.value, net.jac
    k = dk_dx = dk_dy = None
    if not spec.structural:
        k = out if with_k else None
        if J is not None:
            dk_dx = arith.cols(J, 0, n)
            dk_dy = arith.cols(J, n, n + p) if with_dy else None
    else:
        G = arith.reshape_out(out, n, p)  # [B, n, p]
        k = arith.matvec(G, r) if with_k else None
        if J is not None:
            dG = arith.reshape_jac(J, n, p)  # [B, n, p, n + p]
            dk_dx = arith.sub(arith.contract(arith.cols(dG, 0, n), r), arith.matmul(G, Hx))
            if with_dy:
                dk_dy = arith.add(arith.contract(arith.cols(dG, n, n + p), r), G)
    if spec.has_K:
        K = spec.K
        if with_k:
            k = arith.add(k, arith.const_matvec(K, r))
        if dk_dx is not None:
            dk_dx = arith.sub(dk_dx, arith.const_matmul(K, Hx))
        if dk_dy is not None:
            dk_dy = arith.add_const(dk_dy, K)
    return GainValues(k=k, dk_dx=dk_dx, dk_dy=dk_dy)
