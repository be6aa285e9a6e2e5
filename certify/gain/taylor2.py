"""`Taylor2Arithmetic`: `certify.gain.propagate` over second-order Taylor models.

The values are `certify.bounds.taylor2.TM2` (c + g . dz + dz^T H dz / 2 + [-e, e] over the
box zc +- r), every primitive one of that module's operations, so the rounding is theirs.
Layout: rows, as `certify.gain.taylor.TaylorArithmetic`: the value [B, h] and the
first-derivative rows T [B, m, h]; only N and dN/dz are propagated (the prover's
contraction matrix needs dN/dxhat), and only for tanh networks.
"""

from __future__ import annotations

import torch

from certify.activations import Activation
from certify.bounds.taylor2 import TM2, tm2_linear, tm2_mul, tm2_tanh_and_dtanh
from certify.gain.propagate import NetOutput


class Taylor2Arithmetic:
    """Second-order Taylor models of N and dN/dz over the boxes zc +- r ([B, d] each)."""

    def __init__(self, zc: torch.Tensor, r: torch.Tensor) -> None:
        self.zc = zc
        self.r = r

    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[TM2, TM2 | None]:
        """pre = W z + b (z = zc + I dz exactly), T = W[:, :m] as constant models."""
        zc, r = self.zc, self.r
        B, d = zc.shape
        eye = torch.eye(d, dtype=zc.dtype).expand(B, d, d)
        zero = torch.zeros(B, d, d, d, dtype=zc.dtype)
        pre = tm2_linear(TM2(zc, eye, zero, torch.zeros_like(zc)), W.T, b, r)  # [B, h]
        if not m:
            return pre, None
        h = W.shape[0]
        T = TM2(W[:, :m].T.expand(B, m, h), torch.zeros(B, m, h, d, dtype=zc.dtype),
                torch.zeros(B, m, h, d, d, dtype=zc.dtype), torch.zeros(B, m, h, dtype=zc.dtype))
        return pre, T

    def activate(self, act: Activation, pre: TM2, layer: int, order: int
                 ) -> tuple[TM2, TM2, None]:
        if order >= 2 or act.name != "tanh":
            raise ValueError("Taylor2Arithmetic: first derivatives of tanh networks only")
        a, s = tm2_tanh_and_dtanh(pre, self.r)
        return a, s, None

    def scale(self, s: TM2, T: TM2, layer: int) -> TM2:
        s1 = TM2(s.c.unsqueeze(1), s.g.unsqueeze(1), s.H.unsqueeze(1), s.e.unsqueeze(1))
        return tm2_mul(s1, T, self.r)

    def affine(self, a: TM2, T: TM2 | None, S: None, W: torch.Tensor, b: torch.Tensor,
               layer: int) -> tuple[TM2, TM2 | None, None]:
        r = self.r
        return (tm2_linear(a, W.T, b, r),
                None if T is None else tm2_linear(T, W.T, None, r), None)

    def output(self, pre: TM2, T: TM2 | None, S: None) -> NetOutput:
        jac = None if T is None else TM2(T.c.transpose(1, 2), T.g.transpose(1, 2),
                                         T.H.transpose(1, 2), T.e.transpose(1, 2))
        return NetOutput(pre, jac)
