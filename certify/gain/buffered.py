"""`ChunkArithmetic`: the point arithmetic over a training chunk's preallocated buffers.

Training evaluates N and its first m input derivatives at C collocation points (plus, for the
direct structure, the value at C boundary points (x, h(x))) thousands of times. Per layer one
buffer X [R + m C, width] holds the activations of the R value rows followed by the m tangent
blocks of the first C rows, so `affine` is a single `torch.mm(..., out=)` for value and
tangents; `activate` writes f and f' in place. The buffers stay filled after `propagate`
for the hand-written reverse pass in `training.objective` (`Objective._backward`).

`compose` runs on the chunk layout too (the training loss heads): the tangents dN/dz of all
points are [m, N, out], derivative first. `cols` hands `compose` a standard-layout view
[N, ..., k] of the columns it asks for (no copy), and `contract` turns that view back into
the derivative-first one before its einsum, so the heads' arithmetic is the one they always
did, operation for operation (tests/test_training_heads.py freezes the old heads).
"""

from __future__ import annotations

import torch

from certify.activations import Activation
from certify.gain.arithmetic import PointCompose
from certify.gain.propagate import NetOutput


class ChunkBuffers:
    """Constants and work buffers for one chunk of C collocation points (m tangents)."""

    def __init__(self, Z: torch.Tensor, C: int, widths: list[int], m: int,
                 with_bc: bool) -> None:
        self.C = C
        self.m = m
        self.R = self.C * (2 if with_bc else 1)  # value rows: collocation (+ BC) points
        self.Z = Z
        rows, dt = self.R + m * self.C, Z.dtype
        self.pre = [torch.empty(self.R, widths[1], dtype=dt)]  # layer 0: value rows only
        self.X: list[torch.Tensor] = [Z]
        self.S: list[torch.Tensor] = [torch.empty(0)]
        self.G = [torch.empty(self.R, widths[1], dtype=dt)]
        self.GX: list[torch.Tensor] = [torch.empty(0)]
        for i in range(1, len(widths) - 1):
            self.X.append(torch.empty(rows, widths[i], dtype=dt))
            self.S.append(torch.empty(self.R, widths[i], dtype=dt))
            self.pre.append(torch.empty(rows, widths[i + 1], dtype=dt))
            self.G.append(torch.empty(rows, widths[i + 1], dtype=dt))
            self.GX.append(torch.empty(rows, widths[i], dtype=dt))
        self.gs = [torch.empty(self.C, w, dtype=dt) for w in widths]
        self.ones = torch.ones(self.R, dtype=dt)
        self.grads = [torch.empty(b, a, dtype=dt) if k == 0 else torch.empty(b, dtype=dt)
                      for a, b in zip(widths[:-1], widths[1:]) for k in (0, 1)]


class ChunkCompose(PointCompose):
    """`compose` primitives for N [B, out] and dN/dz in the chunk layout [m, B, out]."""

    def cols(self, x: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """Derivative columns start:stop of x [m, B, ...] as a view [B, ..., stop - start]."""
        return x[start:stop].movedim(0, -1)

    def reshape_jac(self, jac: torch.Tensor, n: int, p: int) -> torch.Tensor:
        return jac.view(jac.shape[0], jac.shape[1], n, p)  # [m, B, n, p], chunk layout

    def contract(self, dA: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """sum_q dA[b, i, q, j] v[b, q], on the derivative-first view `cols` came from."""
        return torch.einsum("jbiq,bq->bij", dA.movedim(-1, 0), v)


CHUNK_COMPOSE = ChunkCompose()


class ChunkArithmetic(ChunkCompose):
    """First-order point arithmetic writing into `ChunkBuffers` (layout: value rows [R, w],
    tangents [m, C, w]); `output` returns that layout, not the standard one, and the
    `compose` primitives (`ChunkCompose`) read it."""

    def __init__(self, chunk: ChunkBuffers) -> None:
        self.ch = chunk

    def input_layer(self, z: torch.Tensor, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        ch = self.ch
        torch.mm(z, W.T, out=ch.pre[0]).add_(b)
        # the first layer's tangent is the same at every point: [m, 1, h], broadcast later
        return ch.pre[0], (W[:, :m].T.unsqueeze(1) if m else None)

    def activate(self, act: Activation, pre: torch.Tensor, layer: int, order: int
                 ) -> tuple[torch.Tensor, torch.Tensor, None]:
        if order >= 2:
            raise ValueError("ChunkArithmetic propagates first derivatives only")
        ch = self.ch
        a, s = ch.X[layer][:ch.R], ch.S[layer]
        act.f_and_d1_into(pre, a, s)
        return a, s, None

    def scale(self, s: torch.Tensor, T: torch.Tensor, layer: int) -> torch.Tensor:
        ch = self.ch
        A = ch.X[layer][ch.R:].view(ch.m, ch.C, -1)
        torch.mul(s[:ch.C].unsqueeze(0), T, out=A)
        return A

    def affine(self, a: torch.Tensor, T: torch.Tensor | None, S: None, W: torch.Tensor,
               b: torch.Tensor, layer: int) -> tuple[torch.Tensor, torch.Tensor, None]:
        ch = self.ch
        out = ch.pre[layer]
        torch.mm(ch.X[layer], W.T, out=out)  # value and tangent rows at once
        out[:ch.R].add_(b)  # the bias enters the value rows only
        return out[:ch.R], out[ch.R:].view(ch.m, ch.C, -1), None

    def output(self, pre: torch.Tensor, T: torch.Tensor | None, S: None) -> NetOutput:
        return NetOutput(pre, T)
