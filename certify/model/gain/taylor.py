"""`TaylorArithmetic`: `certify.model.gain.propagate` and `compose` over first-order Taylor models.

The values are `certify.enclose.taylor.TM` (c + g . (z - zc) + [-e, e] over the box with
radii r), and every primitive is one of that module's operations, so the rounding is theirs:
linear maps (`tm_linear`) act exactly on (c, g) with Higham's gamma_k bounds of their float
errors added to the remainder, products (`tm_mul`) and sums (`tm_sum`, `tm_add`) absorb
theirs with `tm_absorb`, the activation (`tm_activation`) adds its Lagrange remainders and
the float errors of its centre values. Negation is exact (c, g negated, e kept).

Layout: rows, as `RowArithmetic`: the value [B, h] and the first-derivative rows T [B, m, h]
(first order only: the Taylor models of the prover carry N and dN/dz). `network_taylor`
(`certify.enclose.taylor`) is `propagate` in this arithmetic; `jcl_taylor` composes its
output with the injection through `compose`.
"""

from __future__ import annotations

import math

import torch

from certify.arith.intervals import EPS, TINY, Interval, U, down, gamma, up
from certify.arith.taylor import (
    TM,
    as_radii,
    reach,
    tm_absorb,
    tm_add,
    tm_index,
    tm_linear,
    tm_mul,
    tm_rho,
    tm_sum,
)
from certify.model.activations import Activation
from certify.model.activations.tanh import d2tanh_enclosure
from certify.model.gain.propagate import NetOutput


def tm_tanh_and_dtanh(t: TM, r: torch.Tensor) -> tuple[TM, TM]:
    """TMs of tanh(q) and tanh'(q) for a TM q (second-order Lagrange remainders, with the
    range of tanh'' from its interval rule and |tanh'''| <= 2)."""
    rho = tm_rho(t, r)
    rng = Interval(down(t.c - rho), up(t.c + rho))
    M2 = d2tanh_enclosure(rng).mag()
    t0 = torch.tanh(t.c)
    s0 = 1.0 - t0 * t0
    s2 = -2.0 * t0 * s0
    gr = reach(t.g, as_radii(r, t.g.ndim))
    ga = t.g * s0.unsqueeze(-1)
    err_t0 = 4.0 * EPS * t0.abs() + 4 * TINY
    e_a = (torch.clamp(s0 + 16 * EPS, max=1.0) * t.e + 0.5 * M2 * rho * rho
           + 16 * EPS * gr + err_t0 + 4 * U * (t0.abs() + reach(ga, as_radii(r, ga.ndim))))
    A = TM(t0, ga, up(e_a * (1.0 + 8 * U) + 4 * TINY))
    gs = t.g * s2.unsqueeze(-1)
    e_s = ((s2.abs() + 64 * EPS) * t.e + 1.0 * rho * rho  # 0.5 * max|tanh'''| (<= 2)
           + 64 * EPS * gr + 32 * EPS + 4 * U * (s0.abs() + reach(gs, as_radii(r, gs.ndim))))
    S = TM(s0, gs, up(e_s * (1.0 + 8 * U) + 4 * TINY))
    return A, S


def tm_activation(act: Activation, t: TM, r: torch.Tensor) -> tuple[TM, TM]:
    """TMs of f(q) and f'(q) for a TM q and the activation `act` (tanh: `tm_tanh_and_dtanh`).

    f(q) = f(c) + f'(c) (q - c) + f''(xi) (q - c)^2 / 2 and, when f''' exists,
    f'(q) = f'(c) + f''(c) (q - c) + f'''(xi) (q - c)^2 / 2, |q - c| <= rho; else (ELU)
    f'(q) = f'(c) + f''(c) (q - c) + (mu - f''(c)) (q - c), mu in f''(range) (f' Lipschitz).
    The centre values are the midpoints of point enclosures; their radii (the float errors)
    go into the remainders, as does the error of the products g f'(c), g f''(c).
    """
    if act.name == "tanh":
        return tm_tanh_and_dtanh(t, r)
    rho = tm_rho(t, r)
    rng = Interval(down(t.c - rho), up(t.c + rho))
    d2r = act.enclose_d2(rng)
    M2 = d2r.mag()
    cI = Interval(t.c, t.c)
    t0, et0 = act.enclose_f(cI).midrad()
    s0, es0 = act.enclose_d1(cI).midrad()
    s2, es2 = act.enclose_d2(cI).midrad()
    gr = reach(t.g, as_radii(r, t.g.ndim))
    ga = t.g * s0.unsqueeze(-1)
    e_a = ((s0.abs() + es0) * t.e + es0 * gr + 0.5 * M2 * rho * rho + et0
           + 4 * U * (t0.abs() + reach(ga, as_radii(r, ga.ndim))))
    A = TM(t0, ga, up(e_a * (1.0 + 8 * U) + 4 * TINY))
    gs = t.g * s2.unsqueeze(-1)
    if math.isfinite(act.d3_bound):
        rem2 = 0.5 * act.d3_bound * rho * rho
    else:  # f'' bounded, not continuous: |mu - f''(c)| <= max(hi - s2, s2 - lo)
        rem2 = torch.maximum(up(d2r.hi - s2), up(s2 - d2r.lo)) * rho
    e_s = ((s2.abs() + es2) * t.e + es2 * gr + rem2 + es0
           + 4 * U * (s0.abs() + reach(gs, as_radii(r, gs.ndim))))
    S = TM(s0, gs, up(e_s * (1.0 + 8 * U) + 4 * TINY))
    return A, S


def _neg(t: TM) -> TM:
    return TM(-t.c, -t.g, t.e)


def _index(t: TM, idx: tuple) -> TM:
    """Index the value dims with slices, integers and new axes (the coefficient dim stays
    last: behind an ellipsis, g's index gets one more full slice at the end)."""
    if Ellipsis in idx:
        return TM(t.c[idx], t.g[idx + (slice(None),)], t.e[idx])
    return tm_index(t, idx)


class TaylorArithmetic:
    """First-order Taylor models of N and dN/dz over the boxes zc +- r ([B, d] each)."""

    def __init__(self, zc: torch.Tensor, r: torch.Tensor) -> None:
        self.zc = zc
        self.r = r

    # --- propagate ---
    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[TM, TM | None]:
        """pre = W z + b (z = zc + I (z - zc), exact), T = W[:, :m] as constant models."""
        zc, r = self.zc, self.r
        B, d = zc.shape
        eye = torch.eye(d, dtype=zc.dtype, device=zc.device).expand(B, d, d)
        pre = tm_linear(TM(zc, eye, torch.zeros_like(zc)), W.T, b, r)  # [B, h]
        if not m:
            return pre, None
        h = W.shape[0]
        like = dict(dtype=zc.dtype, device=zc.device)
        T = TM(W[:, :m].T.expand(B, m, h), torch.zeros(B, m, h, d, **like),
               torch.zeros(B, m, h, **like))
        return pre, T

    def activate(self, act: Activation, pre: TM, layer: int, order: int
                 ) -> tuple[TM, TM, None]:
        if order >= 2:
            raise ValueError("TaylorArithmetic propagates first derivatives only")
        a, s = tm_activation(act, pre, self.r)
        return a, s, None

    def scale(self, s: TM, T: TM, layer: int) -> TM:
        return tm_mul(TM(s.c.unsqueeze(1), s.g.unsqueeze(1), s.e.unsqueeze(1)), T, self.r)

    def affine(self, a: TM, T: TM | None, S: None, W: torch.Tensor, b: torch.Tensor,
               layer: int) -> tuple[TM, TM | None, None]:
        r = self.r
        return tm_linear(a, W.T, b, r), (None if T is None else tm_linear(T, W.T, None, r)), None

    def output(self, pre: TM, T: TM | None, S: None) -> NetOutput:
        jac = None if T is None else TM(T.c.transpose(1, 2), T.g.transpose(1, 2),
                                        T.e.transpose(1, 2))
        return NetOutput(pre, jac)

    # --- compose ---
    def cols(self, x: TM, start: int, stop: int) -> TM:
        return _index(x, (Ellipsis, slice(start, stop)))

    def reshape_out(self, out: TM, n: int, p: int) -> TM:
        B, d = out.c.shape[0], out.g.shape[-1]
        return TM(out.c.reshape(B, n, p), out.g.reshape(B, n, p, d), out.e.reshape(B, n, p))

    def reshape_jac(self, jac: TM, n: int, p: int) -> TM:
        B, m, d = jac.c.shape[0], jac.c.shape[-1], jac.g.shape[-1]
        return TM(jac.c.reshape(B, n, p, m), jac.g.reshape(B, n, p, m, d),
                  jac.e.reshape(B, n, p, m))

    def matvec(self, A: TM, v: TM) -> TM:
        """sum_l A_il v_l: A [B, n, p], v [B, p]."""
        return tm_sum(tm_mul(A, _index(v, (slice(None), None, slice(None))), self.r), 2, self.r)

    def contract(self, dA: TM, v: TM) -> TM:
        """sum_l dA_ilm v_l: dA [B, n, p, m], v [B, p]."""
        vb = _index(v, (slice(None), None, slice(None), None))
        return tm_sum(tm_mul(dA, vb, self.r), 2, self.r)

    def matmul(self, A: TM, B: TM) -> TM:
        """sum_l A_il B_lm: A [B, n, p], B [B, p, m]."""
        return tm_sum(tm_mul(_index(A, (Ellipsis, None)), _index(B, (slice(None), None)),
                             self.r), 2, self.r)

    def add(self, a: TM, b: TM) -> TM:
        return tm_add(a, b, self.r)

    def sub(self, a: TM, b: TM) -> TM:
        return tm_add(a, _neg(b), self.r)

    def const_matvec(self, K: torch.Tensor, v: TM) -> TM:
        """K v for a point matrix K [n, p] and v [B, p] (`const_matmul` on one column)."""
        return _index(self.const_matmul(K, _index(v, (Ellipsis, None))), (Ellipsis, 0))

    def const_matmul(self, K: torch.Tensor, A: TM) -> TM:
        """K A for a point matrix K [n, p] and A [B, p, m]: the float errors of the products
        (gamma_{p+1} |K| |A|) enter the remainder."""
        p = K.shape[1]
        KA = TM(K @ A.c, torch.einsum("ip,bpjd->bijd", K, A.g), K.abs() @ A.e)
        return tm_absorb(KA.c, KA.g, up(KA.e * (1 + 2 * gamma(p + 1))), self.r, p + 2)

    def add_const(self, a: TM, K: torch.Tensor) -> TM:
        return tm_absorb(a.c + K, a.g, a.e, self.r, 2)
