"""The training objective: the loss over collocation points and its weight gradient.

The objective (METHOD.md section 2) needs, at every collocation point, the network's value and
its Jacobian in xhat, and the gradient of the loss with respect to the weights. A plain
autograd implementation (double backward) costs about 45 ms per evaluation here; this module
instead evaluates the MLP trunk by hand:

- forward mode for the n Jacobian columns by the one propagation of the gain
  (`certify.gain.propagate` with `certify.gain.buffered.ChunkArithmetic`): value and tangent
  rows stacked in one buffer so each layer is one matrix product (no Python loop over points);
- a hand-written reverse pass through that forward-mode computation; the activation's own
  reverse rule (`Activation.chain_pre`) brings in f'' (for tanh, f'' = -2 f f': one fused
  multiply-add);
- preallocated buffers, float32 (the checkpoint and the verifier stay float64);
- autograd only for the small loss head on [B, n, n] matrices, so any n, p, either structure,
  the linear injection K and every loss kind share one code path.

Everything that does not depend on the weights (Jf at the points, the constant part of D,
h and dh/dx for the structural gain) is computed once, in float64, before training.
`tests/test_training.py` checks the hand-written gradient against autograd through
`GainNetwork.forward_with_jacobian` and `certify.kernels.gain_terms`. The training run that
optimises it (Adam, then L-BFGS) is `training.train`; the CEGIS loop extends it
(`training.cegis_objective`).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import torch

from certify.gain import propagate
from certify.gain.buffered import ChunkArithmetic, ChunkBuffers
from certify.kernels import sym
from certify.network import GainNetwork
from certify.system import System
from training import losses
from training.curvature import CurvaturePenalty

# points per chunk of the objective. Chunks are the unit of parallel work (one worker thread
# each); the constant is fixed so that the weights do not depend on the number of workers.
CHUNK_POINTS = 2048
# worker threads for the chunks (each runs single-threaded torch ops: no OpenMP barriers, so
# a busy second core costs nothing, while a free one nearly halves the time)
WORKERS = 2


@dataclass
class LossValues:
    """The loss terms at one evaluation (python floats); `curv` is the Jacobian-variation
    penalty C of `training.curvature` (0 when the term is off), before its weight."""

    total: float
    mpdi: float
    bc: float
    curv: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return {"total": self.total, "mpdi": self.mpdi, "bc": self.bc, "curv": self.curv}


class Objective:
    """The training loss of `net` over fixed collocation points, with its weight gradient.

    `evaluate(grad=True)` writes d(loss)/d(weights) into each parameter's `.grad` and returns
    the loss terms. The network's parameters are read at every call (optimisers update them
    in place).
    """

    def __init__(self, system: System, net: GainNetwork, xhat: torch.Tensor, y: torch.Tensor,
                 *, lam: float, P: torch.Tensor, weights: losses.LossWeights,
                 loss: str = "minors", margin: float = 0.0,
                 chunk_points: int = CHUNK_POINTS, workers: int = WORKERS,
                 curvature: CurvaturePenalty | None = None) -> None:
        if len(net.layers) < 2:
            raise ValueError("training needs a network with at least one hidden layer")
        dt = net.layers[0].weight.dtype
        n, p = system.n, system.p
        self.net, self.n, self.p, self.m = net, n, p, n
        self.N = xhat.shape[0]
        self.weights, self.loss, self.margin = weights, loss, float(margin)
        self.structural = net.structure == "structural"
        self.spec = net.spec()  # references the parameters: optimisers update them in place
        self.params: list[torch.Tensor] = []
        for layer in net.layers:
            self.params += [layer.weight, layer.bias]
        widths = [n + p, *[layer.weight.shape[0] for layer in net.layers]]
        x64, y64 = xhat.to(torch.float64), y.to(torch.float64)
        P64 = torch.as_tensor(P, dtype=torch.float64)
        K = net.K.to(torch.float64)
        Jbase = system.jac_f(x64)
        need_h = self.structural or bool(torch.any(K != 0))
        hx = system.h(x64) if (need_h or not self.structural) else None
        Hx = system.jac_h(x64) if need_h else None
        if Hx is not None and bool(torch.any(K != 0)):
            Jbase = Jbase - K @ Hx  # the K (y - h(xhat)) term's xhat-derivative
        D0 = sym(P64 @ Jbase) + 2.0 * float(lam) * P64  # the weight-free part of D
        self.P = P64.to(dt)
        self.P_is_identity = bool(torch.equal(P64, torch.eye(n, dtype=torch.float64)))
        self.D0 = D0.to(dt).contiguous()
        self.r = (y64 - hx).to(dt) if self.structural else None
        self.Hx = Hx.to(dt) if (self.structural and Hx is not None) else None
        self.chunks: list[ChunkBuffers] = []
        for lo in range(0, self.N, max(1, int(chunk_points))):
            hi = min(self.N, lo + int(chunk_points))
            z = torch.cat([x64[lo:hi], y64[lo:hi]], dim=1)
            if not self.structural:  # BC rows: k(x, h(x)); zero by construction if structural
                z = torch.cat([z, torch.cat([x64[lo:hi], hx[lo:hi]], dim=1)], dim=0)
            self.chunks.append(ChunkBuffers(z.to(dt).contiguous(), hi - lo, widths, self.m,
                                      not self.structural))
        self.curvature = curvature if (curvature is not None
                                       and curvature.settings.weight > 0) else None
        self.evaluations = 0
        self.workers = max(1, min(int(workers), len(self.chunks)))
        self._pool: ThreadPoolExecutor | None = None

    def _map(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        """fn over items, on `workers` threads (torch releases the GIL inside its ops)."""
        if self.workers == 1 or len(items) == 1:
            return [fn(item) for item in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.workers,
                                            thread_name_prefix="certify-train",
                                            initializer=torch.set_num_threads, initargs=(1,))
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        """Stop the worker threads (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # ----- trunk: forward mode with stacked value/tangent rows ---------------------------
    @torch.no_grad()
    def _forward(self, ch: ChunkBuffers) -> tuple[torch.Tensor, torch.Tensor]:
        """N and its first m input derivatives at the chunk's points, by the one propagation
        (`certify.gain.propagate`) over the chunk's buffers: value rows [R, out] and
        tangents [m, C, out]."""
        out = propagate(self.spec, ChunkArithmetic(ch), ch.Z, self.m)
        return out.value, out.jac

    @torch.no_grad()
    def _backward(self, ch: ChunkBuffers, g_val: torch.Tensor, g_tan: torch.Tensor) -> None:
        """Reverse pass through `_forward`: this chunk's weight gradient into `ch.grads`."""
        Ws = self.params[0::2]
        act = self.spec.activation
        grads = ch.grads
        R, C, m = ch.R, ch.C, self.m
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
                w0_tangent_grad = (gA * S[:C].unsqueeze(0)).sum(1).T
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
        grads[0][:, :m].add_(w0_tangent_grad)
        torch.mv(G0.T, ch.ones, out=grads[1])

    # ----- loss head: D from the trunk's outputs, the loss, and its gradient ----------
    def _head(self, val: torch.Tensor, tan: torch.Tensor, k_bc: torch.Tensor | None,
              grad: bool) -> tuple[float, float, list[torch.Tensor] | None]:
        """MPDI and BC sums over all points; with `grad`, d(total)/d(val, tan, k_bc).

        val [N, out] and tan [m, N, out] are the trunk's value and xhat-tangents at the
        collocation points, k_bc [N, n] its value at (x, h(x)) (None if structural). D is
        linear in (val, tan), so only d(loss)/dD needs differentiating (closed form for the
        minor loss with n <= 2, autograd otherwise); the rest is mapped back by hand.
        """
        n, p, N = self.n, self.p, self.N
        if self.structural:
            G = val.view(N, n, p)
            dG = tan.view(self.m, N, n, p)  # [j, b, i, q] = dG_iq/dxhat_j
            M = torch.einsum("jbiq,bq->bij", dG, self.r)
            if self.Hx is not None:
                M = M - G @ self.Hx
        else:
            M = tan.permute(1, 2, 0)  # [b, i, j] = dk_i/dxhat_j
        D = self.D0 + sym(M if self.P_is_identity else self.P @ M)
        bc = 0.0 if k_bc is None else float((k_bc * k_bc).sum())
        if self.loss == "minors":
            if grad:
                mpdi_t, gD = losses.minor_loss_sum_and_grad(D, self.weights.rho)
            else:
                mpdi_t, gD = losses.minor_loss(D, self.weights.rho, reduce="sum"), None
        else:
            squared = self.loss == "eigen_squared"
            if grad:
                Dl = D.detach().requires_grad_(True)
                with torch.enable_grad():
                    mpdi_t = losses.eigen_loss(Dl, self.margin, squared, reduce="sum")
                    (gD,) = torch.autograd.grad(mpdi_t, [Dl])
            else:
                mpdi_t, gD = losses.eigen_loss(D, self.margin, squared, reduce="sum"), None
        mpdi = float(mpdi_t)
        if not grad:
            return mpdi, bc, None
        scale = self.weights.mu1 / N
        gM = sym(gD) * scale
        if not self.P_is_identity:
            gM = self.P.T @ gM
        if self.structural:
            g_tan = torch.einsum("bij,bq->jbiq", gM, self.r).reshape(self.m, N, n * p)
            g_val = torch.zeros_like(val) if self.Hx is None else \
                (-(gM @ self.Hx.transpose(1, 2))).reshape(N, n * p)
            return mpdi, bc, [g_val, g_tan]
        g_tan = gM.permute(2, 0, 1)
        g_bc = k_bc * (2.0 * self.weights.mu2 / N)
        return mpdi, bc, [torch.zeros_like(val), g_tan, g_bc]

    def evaluate(self, grad: bool = True) -> LossValues:
        """Loss terms at the current weights; with `grad`, d(total)/d(weights) into `.grad`.

        All chunks go forward, then one loss head over all points, then all chunks go
        backward; chunks run on `workers` threads, and their gradients are summed in a
        fixed order (the result does not depend on the number of workers).
        """
        mu1, mu2 = self.weights.mu1, self.weights.mu2
        outs = self._map(self._forward, self.chunks)
        with torch.no_grad():
            val = torch.cat([v[:ch.C] for (v, _), ch in zip(outs, self.chunks)])
            tan = torch.cat([t for _, t in outs], dim=1)
            k_bc = None if self.structural else torch.cat(
                [v[ch.C:] for (v, _), ch in zip(outs, self.chunks)])
            mpdi, bc, g = self._head(val, tan, k_bc, grad)
        if g is not None:
            jobs, lo = [], 0
            for ch in self.chunks:
                hi = lo + ch.C
                g_val = g[0][lo:hi] if self.structural else torch.cat([g[0][lo:hi],
                                                                      g[2][lo:hi]])
                jobs.append((ch, g_val, g[1][:, lo:hi]))
                lo = hi
            self._map(lambda job: self._backward(*job), jobs)
            with torch.no_grad():
                for k, prm in enumerate(self.params):  # fixed order: deterministic sums
                    if prm.grad is None:
                        prm.grad = torch.empty_like(prm)
                    prm.grad.copy_(self.chunks[0].grads[k])
                    for ch in self.chunks[1:]:
                        prm.grad.add_(ch.grads[k])
        curv = self._curvature(grad)
        self.evaluations += 1
        mpdi_mean, bc_mean = mpdi / self.N, bc / self.N
        w_curv = 0.0 if self.curvature is None else self.curvature.settings.weight
        return LossValues(total=mu1 * mpdi_mean + mu2 * bc_mean + w_curv * curv,
                          mpdi=mpdi_mean, bc=bc_mean, curv=curv)

    def _curvature(self, grad: bool) -> float:
        """The Jacobian-variation penalty C (0 when off); with `grad`, adds weight * dC/dW
        to each parameter's `.grad` (autograd through the point propagation: small)."""
        if self.curvature is None:
            return 0.0
        with torch.enable_grad():
            c = self.curvature.value(self.spec)
            if grad:
                gs = torch.autograd.grad(c * self.curvature.settings.weight, self.params,
                                         allow_unused=True)
        if grad:
            with torch.no_grad():
                for prm, g in zip(self.params, gs):
                    if g is not None:
                        prm.grad.add_(g)
        return float(c.detach())
