"""The one propagation of the gain: MLP value and input derivatives, then the injection.

`propagate` runs the chain rule layer by layer, in forward mode, against an `Arithmetic`
(`certify.model.gain.arithmetic`), which decides the number kind (float32/float64 point, later
interval / Taylor / relaxation) and the memory layout. For every hidden layer:

    (a, s, s2) = f, f', f'' of the pre-activation           arith.activate
    T <- s * T                    (first derivatives)       arith.scale
    S <- s2 * (T_j T_m) + s * S   (second, order 2 only)    arith.second   (uses the old T)
    pre, T, S <- W a + b, W T, W S  (one product)           arith.affine

starting from pre = W_0 z + b_0, T = W_0[:, :m] (arith.input_layer), and an optional
`pre_hook(layer, pre, T)` that may tighten each pre-activation (the interval arithmetic's
mean-value intersection) or `layer_hook(layer, pre, T)` that may replace both (the CROWN
prover's ranges, over `PairedArithmetic`). `compose` then builds k, dk/dxhat, dk/dy from N,
dN/dz and r = y - h(xhat), dh/dxhat, for the direct or structural injection plus K r, with the
arithmetic's contraction primitives; `compose_second` the second derivatives
d2k_i / dxhat_j dz_m from d2N and dr/dz, d2r/dxhat dz (the prover's curvature term).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from certify.model.gain.spec import GainSpec

PreHook = Callable[[int, Any, Any], Any]
LayerHook = Callable[[int, Any, Any], tuple[Any, Any]]


@dataclass
class NetOutput:
    """N [B, out], dN/dz[:, :, :m] [B, out, m] (None if m = 0), d2N [B, out, J, m] (order 2),
    in the arithmetic's value type."""

    value: Any
    jac: Any
    hess: Any = None


def propagate(spec: GainSpec, arith: Any, z: Any, m: int, order: int = 1,
              second_cols: int | None = None, pre_hook: PreHook | None = None,
              layer_hook: LayerHook | None = None) -> NetOutput:
    """N(z) with its derivatives in the first m inputs (order 2: d2/dz_j dz_k, j < second_cols).

    `z` is whatever the arithmetic takes as input ([B, d] points for the point arithmetics).
    `layer_hook(layer, pre, T) -> (pre, T)`, called after `pre_hook`, may replace both the
    pre-activation and the first-derivative rows of each hidden layer (the CROWN prover's
    forward ranges: intersections and backward queries, `certify.enclose.crown`).
    """
    act = spec.activation
    (W0, b0), rest = spec.layers[0], spec.layers[1:]
    pre, T = arith.input_layer(z, W0, b0, m)
    J = m if second_cols is None else int(second_cols)
    S = arith.zero_second(pre, J, m) if order >= 2 else None
    for i, (W, b) in enumerate(rest, start=1):
        if pre_hook is not None:
            pre = pre_hook(i - 1, pre, T)
        if layer_hook is not None:
            pre, T = layer_hook(i - 1, pre, T)
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
            with_dy: bool = True, with_k: bool = True, with_K_dx: bool = True) -> GainValues:
    """k and its Jacobians from N, dN/dz (columns per `columns_needed`; None for k alone)
    and, where `spec.needs_h`, r = y - h(xhat) [B, p] and Hx = dh/dxhat [B, p, n] (else
    None; r may be None when `with_k` is False and the structure is direct).

    `with_K_dx=False` leaves the weight-free term -K Hx out of dk/dxhat, for a caller that
    folds it into a constant of its own (training adds it to the float64 part of D once); Hx
    may then be None for the direct structure."""
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
        if dk_dx is not None and with_K_dx:
            dk_dx = arith.sub(dk_dx, arith.const_matmul(K, Hx))
        if dk_dy is not None:
            dk_dy = arith.add_const(dk_dy, K)
    return GainValues(k=k, dk_dx=dk_dx, dk_dy=dk_dy)


def compose_second(spec: GainSpec, arith: Any, net: NetOutput, r: Any, dr: Any, d2r: Any
                   ) -> Any:
    """d2k_i / dxhat_j dz_m [B, n, n, d] from N, dN/dz, d2N (`propagate` with order 2, all
    d columns, second_cols = n) and, where `spec.needs_h`, r = y - h(xhat) [B, p],
    dr/dz = (-dh/dxhat | I) [B, p, d], d2r / dxhat_j dz_m = (-d2h/dxhat_j dxhat_m | 0)
    [B, p, n, d] (else None). Structural, with G = N as [n, p]:

        d2k_i/dx_j dz_m = sum_l d2G_iljm r_l + dG_ilj dr_lm + dG_ilm dr_lj + G_il d2r_ljm,

    the four products summed per l before the sum over l; K adds sum_l K_il d2r_ljm."""
    n, p, d = spec.n, spec.p, spec.n + spec.p
    if not spec.structural:
        d2k = net.hess
    else:
        G = arith.reshape_out(net.value, n, p)  # [B, n, p]
        dG = arith.reshape_jac(net.jac, n, p)  # [B, n, p, d]
        d2G = arith.reshape(net.hess, (n, p, n, d))
        a1 = arith.mul(d2G, arith.index(r, (slice(None), None, slice(None), None, None)))
        a2 = arith.mul(arith.index(dG, (Ellipsis, slice(0, n), None)),
                       arith.index(dr, (slice(None), None, slice(None), None, slice(None))))
        a3 = arith.mul(arith.index(dG, (slice(None),) * 3 + (None, slice(None))),
                       arith.index(dr, (slice(None), None, slice(None), slice(0, n), None)))
        a4 = arith.mul(arith.index(G, (Ellipsis, None, None)),
                       arith.index(d2r, (slice(None), None)))
        d2k = arith.sum(arith.add(arith.add(a1, a2), arith.add(a3, a4)), 2)
    if spec.has_K:
        Kd2 = arith.const_matmul(spec.K, arith.reshape(d2r, (p, n * d)))  # [B, n, n d]
        d2k = arith.add(d2k, arith.reshape(Kd2, (n, n, d)))
    return d2k
