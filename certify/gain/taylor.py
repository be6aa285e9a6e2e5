"""`TaylorArithmetic`: `certify.gain.propagate` and `compose` over first-order Taylor models.

The values are `certify.bounds.taylor.TM` (c + g . (z - zc) + [-e, e] over the box with
radii r), and every primitive is one of that module's operations, so the rounding is theirs:
linear maps (`tm_linear`) act exactly on (c, g) with Higham's gamma_k bounds of their float
errors added to the remainder, products (`tm_mul`) and sums (`tm_sum`, `tm_add`) absorb
theirs with `tm_absorb`, the activation (`tm_activation`) adds its Lagrange remainders and
the float errors of its centre values. Negation is exact (c, g negated, e kept).

Layout: rows, as `RowArithmetic`: the value [B, h] and the first-derivative rows T [B, m, h]
(first order only: the Taylor models of the prover carry N and dN/dz). `network_taylor`
(`certify.bounds.taylor`) is `propagate` in this arithmetic; `jcl_taylor` composes its
output with the injection through `compose`.
"""

from __future__ import annotations

import torch

from certify.activations import Activation
from certify.bounds.taylor import (
    TM,
    tm_absorb,
    tm_activation,
    tm_add,
    tm_index,
    tm_linear,
    tm_mul,
    tm_sum,
)
from certify.gain.propagate import NetOutput
from certify.intervals import gamma, up


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
