"""`ChunkArithmetic`: the point arithmetic over a training chunk's preallocated buffers.

Training evaluates N and its first m input derivatives at C collocation points (plus, for the
direct structure, the value at C boundary points (x, h(x))) thousands of times. Per layer one
buffer X [R + m C, width] holds the activations of the R value rows followed by the m tangent
blocks of the first C rows, so `affine` is a single `torch.mm(..., out=)` for value and
tangents; `activate` writes f and f' in place. The buffers stay filled after `propagate`
for the hand-written reverse pass, `ChunkArithmetic.reverse` (the adjoint of that forward
pass, kept beside it because it reads exactly the buffers the forward writes; training's
`training.objective.Objective` calls both).

`compose` runs on the chunk layout too (the training loss heads): the tangents dN/dz of all
points are [m, N, out], derivative first. `cols` hands `compose` a standard-layout view
[N, ..., k] of the columns it asks for (no copy), and `contract` turns that view back into
the derivative-first one before its einsum, so the heads' arithmetic is the one they always
did, operation for operation (tests/training/test_training_heads.py freezes the old heads).
"""

from __future__ import annotations

import torch

from certify.model.activations import Activation
from certify.model.gain.arithmetic import PointCompose
from certify.model.gain.propagate import NetOutput
from certify.model.gain.spec import GainSpec


def tanh_and_d1_float32(x: torch.Tensor, f_out: torch.Tensor, d1_out: torch.Tensor,
                        one: torch.Tensor) -> None:
    """tanh(x) into f_out and 1 - tanh(x)^2 into d1_out, float32, as 2 sigmoid(2 x) - 1.

    torch's float32 tanh kernel is several times slower than its sigmoid on the CPUs
    measured (docs/performance.md, `bench/train.py`); this form is within 2 ulp(1) of tanh
    in absolute terms (it gives up tanh's relative accuracy near 0, which a float32 training
    step does not use). For training only: the checkpoint is float64, the verifier evaluates
    tanh itself. `one` is a 0-dim tensor holding 1 (of x's dtype)."""
    torch.mul(x, 2.0, out=f_out)
    torch.sigmoid(f_out, out=f_out)
    f_out.mul_(2.0).sub_(1.0)
    torch.addcmul(one, f_out, f_out, value=-1.0, out=d1_out)


class ChunkBuffers:
    """Constants, work buffers and their views for one chunk of C collocation points (m
    tangents). The views (value rows, tangent blocks, transposes) are made once here: a pass
    of training then runs the products and elementwise kernels only, not hundreds of view
    operations."""

    def __init__(self, Z: torch.Tensor, C: int, widths: list[int], m: int,
                 with_bc: bool) -> None:
        self.C = C
        self.m = m
        self.R = R = self.C * (2 if with_bc else 1)  # value rows: collocation (+ BC) points
        self.Z = Z
        self.ZT = Z.T
        rows, dt = R + m * self.C, Z.dtype
        dev = Z.device

        def new(*shape: int) -> torch.Tensor:
            return torch.empty(*shape, dtype=dt, device=dev)

        def tangents(buf: torch.Tensor) -> list[torch.Tensor]:
            return list(buf[R:].view(m, C, -1))

        self.one = torch.ones((), dtype=dt, device=dev)
        last = len(widths) - 2  # the output layer's index
        self.pre = [new(R, widths[1])]  # layer 0: value rows only
        self.X: list[torch.Tensor] = [Z]
        self.S: list[torch.Tensor] = [new(0)]
        self.G = [new(R, widths[1])]
        self.GX: list[torch.Tensor] = [new(0)]
        for i in range(1, len(widths) - 1):
            self.X.append(new(rows, widths[i]))
            self.S.append(new(R, widths[i]))
            # the output layer's rows go to `out_t` instead
            self.pre.append(new(rows, widths[i + 1] if i < last else 0))
            self.G.append(new(rows, widths[i + 1]))
            self.GX.append(new(rows, widths[i]))
        # views, per layer: value rows [R, w], tangent blocks [m, C, w] and each block [C, w]
        self.pre_val = [b[:R] for b in self.pre]
        self.pre_tan = [b[R:].view(m, C, -1) for b in self.pre]
        self.pre_tan_j = [tangents(b) for b in self.pre]
        self.X_val = [b[:R] for b in self.X]
        self.X_tan = [b[R:].view(m, C, -1) for b in self.X]
        self.X_tan_j = [tangents(b) for b in self.X]
        self.S_C = [b[:C] for b in self.S]
        self.S_C1 = [b[:C].unsqueeze(0) for b in self.S]
        self.G_val = [b[:R] for b in self.G]
        self.G_tan = [b[R:].view(m, C, -1) for b in self.G]
        self.GT = [b.T for b in self.G]
        self.GX_val = [b[:R] for b in self.GX]
        self.GX_tan = [b[R:].view(m, C, -1) for b in self.GX]
        self.GX_tan_j = [tangents(b) for b in self.GX]
        self.gs = [new(self.C, w) for w in widths]
        self.tmp = new(self.C, widths[1])  # reverse: layer 1
        self.w0_tangent = new(m, widths[1])
        self.w0_tangent_j = list(self.w0_tangent)
        # the output layer's rows, transposed [out, rows]: a product with few output columns
        # is several times faster as W X^T than as X W^T
        self.out_t = new(widths[-1], rows)
        self.out_t_val = self.out_t[:, :R]
        self.out_val = self.out_t_val.T
        self.out_tan = self.out_t[:, R:].T.view(m, C, -1)
        self.X_last_T = self.X[last].T
        self.grads = [new(b, a) if k == 0 else new(b)
                      for a, b in zip(widths[:-1], widths[1:]) for k in (0, 1)]
        # the first weight's gradient is formed transposed (Z^T G [d, h]: few rows, fast)
        self.g0_t = new(widths[0], widths[1])
        self.grads[0] = self.g0_t.T
        self.g0_tangent = self.grads[0][:, :m]
        self.w0_tangent_t = self.w0_tangent.T


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
        # the first layer's tangent is the same at every point: its m rows of W0^T, one per
        # column (`scale` multiplies each into its block)
        return ch.pre[0], (W[:, :m].T if m else None)

    def activate(self, act: Activation, pre: torch.Tensor, layer: int, order: int
                 ) -> tuple[torch.Tensor, torch.Tensor, None]:
        if order >= 2:
            raise ValueError("ChunkArithmetic propagates first derivatives only")
        ch = self.ch
        a, s = ch.X_val[layer], ch.S[layer]
        if act.name == "tanh" and pre.dtype == torch.float32:
            tanh_and_d1_float32(pre, a, s, ch.one)
        else:
            act.f_and_d1_into(pre, a, s)
        return a, s, None

    def scale(self, s: torch.Tensor, T: torch.Tensor, layer: int) -> torch.Tensor:
        ch = self.ch
        if layer == 1:  # W0's rows [m, h]: each over the C rows (no broadcast of a block)
            sC = ch.S_C[1]
            for j, A in enumerate(ch.X_tan_j[1]):
                torch.mul(sC, T[j], out=A)
        else:
            torch.mul(ch.S_C1[layer], T, out=ch.X_tan[layer])
        return ch.X_tan[layer]

    def affine(self, a: torch.Tensor, T: torch.Tensor | None, S: None, W: torch.Tensor,
               b: torch.Tensor, layer: int) -> tuple[torch.Tensor, torch.Tensor, None]:
        ch = self.ch
        if layer == len(ch.pre) - 1:  # the output layer: W X^T into [out, rows]
            torch.mm(W, ch.X_last_T, out=ch.out_t)
            ch.out_t_val.add_(b[:, None])
            return ch.out_val, ch.out_tan, None
        torch.mm(ch.X[layer], W.T, out=ch.pre[layer])  # value and tangent rows at once
        ch.pre_val[layer].add_(b)  # the bias enters the value rows only
        return ch.pre_val[layer], ch.pre_tan[layer], None

    def output(self, pre: torch.Tensor, T: torch.Tensor | None, S: None) -> NetOutput:
        return NetOutput(pre, T)

    @torch.no_grad()
    def reverse(self, spec: GainSpec, g_val: torch.Tensor, g_tan: torch.Tensor) -> None:
        """The adjoint of `propagate` over these buffers (first order): given d(loss)/dN at
        the value rows g_val [R, out] and at the tangents g_tan [m, C, out], write
        d(loss)/d(W_i, b_i) into `ch.grads` (W0, b0, W1, b1, ...). Reads the activations,
        derivatives and tangents the forward pass left in the buffers; the activation's own
        rule `chain_pre` brings in f''. `spec` must be the one the forward pass ran."""
        ch = self.ch
        Ws = [W for W, _ in spec.layers]
        act = spec.activation
        grads = ch.grads
        L = len(Ws) - 1
        ch.G_val[L].copy_(g_val)
        ch.G_tan[L].copy_(g_tan)
        for i in range(L, 0, -1):
            torch.mm(ch.GT[i], ch.X[i], out=grads[2 * i])
            torch.sum(ch.G_val[i], 0, out=grads[2 * i + 1])
            torch.mm(ch.G[i], Ws[i], out=ch.GX[i])
            gA, gs = ch.GX_tan_j[i], ch.gs[i]
            if i == 1:
                w0t = Ws[0][:, :ch.m].T
                torch.mul(gA[0], w0t[0], out=gs)
                for j in range(1, ch.m):
                    gs.addcmul_(gA[j], w0t[j])
                for j in range(ch.m):  # sum over the points of gA_j * s, into a buffer
                    torch.mul(gA[j], ch.S_C[1], out=ch.tmp)
                    torch.sum(ch.tmp, 0, out=ch.w0_tangent_j[j])
            else:
                U = ch.pre_tan_j[i - 1]
                torch.mul(gA[0], U[0], out=gs)
                for j in range(1, ch.m):
                    gs.addcmul_(gA[j], U[j])
                torch.mul(ch.GX_tan[i], ch.S_C1[i], out=ch.G_tan[i - 1])
            # through a = f(pre), s = f'(pre): d/dpre = gt f' + gs f'' (tangent rows only)
            act.chain_pre(ch.GX_val[i], gs, ch.pre_val[i - 1], ch.X_val[i], ch.S[i],
                          ch.G_val[i - 1])
        torch.mm(ch.ZT, ch.G[0], out=ch.g0_t)
        ch.g0_tangent.add_(ch.w0_tangent_t)
        torch.sum(ch.G[0], 0, out=grads[1])
