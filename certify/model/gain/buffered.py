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


def tanh_and_d1_float32(x: torch.Tensor, f_out: torch.Tensor, d1_out: torch.Tensor) -> None:
    """tanh(x) into f_out and 1 - tanh(x)^2 into d1_out, float32, as 2 sigmoid(2 x) - 1.

    torch's float32 tanh kernel is several times slower than its sigmoid on the CPUs
    measured (docs/performance.md, `bench/train.py`); this form is within 2 ulp(1) of tanh
    in absolute terms (it gives up tanh's relative accuracy near 0, which a float32 training
    step does not use). For training only: the checkpoint is float64, the verifier evaluates
    tanh itself."""
    one = torch.ones((), dtype=x.dtype, device=x.device)
    torch.mul(x, 2.0, out=f_out)
    torch.sigmoid(f_out, out=f_out)
    f_out.mul_(2.0).sub_(1.0)
    torch.addcmul(one, f_out, f_out, value=-1.0, out=d1_out)


class ChunkBuffers:
    """Constants and work buffers for one chunk of C collocation points (m tangents)."""

    def __init__(self, Z: torch.Tensor, C: int, widths: list[int], m: int,
                 with_bc: bool) -> None:
        self.C = C
        self.m = m
        self.R = self.C * (2 if with_bc else 1)  # value rows: collocation (+ BC) points
        self.Z = Z
        rows, dt = self.R + m * self.C, Z.dtype
        dev = Z.device
        self.pre = [torch.empty(self.R, widths[1], dtype=dt, device=dev)]  # layer 0: value rows
        self.X: list[torch.Tensor] = [Z]
        self.S: list[torch.Tensor] = [torch.empty(0, device=dev)]
        self.G = [torch.empty(self.R, widths[1], dtype=dt, device=dev)]
        self.GX: list[torch.Tensor] = [torch.empty(0, device=dev)]
        for i in range(1, len(widths) - 1):
            self.X.append(torch.empty(rows, widths[i], dtype=dt, device=dev))
            self.S.append(torch.empty(self.R, widths[i], dtype=dt, device=dev))
            self.pre.append(torch.empty(rows, widths[i + 1], dtype=dt, device=dev))
            self.G.append(torch.empty(rows, widths[i + 1], dtype=dt, device=dev))
            self.GX.append(torch.empty(rows, widths[i], dtype=dt, device=dev))
        self.gs = [torch.empty(self.C, w, dtype=dt, device=dev) for w in widths]
        self.tmp = torch.empty(self.C, widths[1], dtype=dt, device=dev)  # reverse: layer 1
        self.w0_tangent = torch.empty(m, widths[1], dtype=dt, device=dev)
        self.ones = torch.ones(self.R, dtype=dt, device=dev)
        self.grads = [torch.empty(b, a, dtype=dt, device=dev) if k == 0
                      else torch.empty(b, dtype=dt, device=dev)
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
        if act.name == "tanh" and pre.dtype == torch.float32:
            tanh_and_d1_float32(pre, a, s)
        else:
            act.f_and_d1_into(pre, a, s)
        return a, s, None

    def scale(self, s: torch.Tensor, T: torch.Tensor, layer: int) -> torch.Tensor:
        ch = self.ch
        A = ch.X[layer][ch.R:].view(ch.m, ch.C, -1)
        if T.shape[1] == 1:  # the first layer's tangent, one row per column: no broadcast
            for j in range(ch.m):  # over C (a slow path of torch.mul), a row each
                torch.mul(s[:ch.C], T[j, 0], out=A[j])
        else:
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
        R, C, m = ch.R, ch.C, ch.m
        L = len(Ws) - 1
        G = ch.G[L]
        G[:R].copy_(g_val)
        G[R:].copy_(g_tan.reshape(m * C, -1))
        for i in range(L, 0, -1):
            X, S, G = ch.X[i], ch.S[i], ch.G[i]
            torch.mm(G.T, X, out=grads[2 * i])
            torch.mv(G[:R].T, ch.ones, out=grads[2 * i + 1])
            GX = ch.GX[i]
            torch.mm(G, Ws[i], out=GX)
            gt, gA = GX[:R], GX[R:].view(m, C, -1)
            gs = ch.gs[i]
            if i == 1:
                w0t = Ws[0][:, :m].T
                torch.mul(gA[0], w0t[0], out=gs)
                for j in range(1, m):
                    gs.addcmul_(gA[j], w0t[j])
                for j in range(m):  # sum over the points of gA_j * s, into a buffer
                    torch.mul(gA[j], S[:C], out=ch.tmp)
                    torch.sum(ch.tmp, 0, out=ch.w0_tangent[j])
            else:
                U = ch.pre[i - 1][R:].view(m, C, -1)
                torch.mul(gA[0], U[0], out=gs)
                for j in range(1, m):
                    gs.addcmul_(gA[j], U[j])
                torch.mul(gA, S[:C].unsqueeze(0), out=ch.G[i - 1][R:].view(m, C, -1))
            # through a = f(pre), s = f'(pre): d/dpre = gt f' + gs f'' (tangent rows only)
            act.chain_pre(gt, gs, ch.pre[i - 1][:R], X[:R], S, ch.G[i - 1][:R])
        G0 = ch.G[0]
        torch.mm(G0.T, ch.Z, out=grads[0])
        grads[0][:, :m].add_(ch.w0_tangent.T)
        torch.mv(G0.T, ch.ones, out=grads[1])
