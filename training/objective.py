"""The training objective: the loss over collocation points and its weight gradient.

The objective (METHOD.md section 2) needs, at every collocation point, the network's value and
its Jacobian in xhat, and the gradient of the loss with respect to the weights. A plain
autograd implementation (double backward) is slow (`bench/train.py`); this module instead
evaluates the MLP trunk by hand:

- forward mode for the n Jacobian columns by the one propagation of the gain
  (`certify.model.gain.propagate` with `certify.model.gain.buffered.ChunkArithmetic`): value and
  tangent
  rows stacked in one buffer so each layer is one matrix product (no Python loop over points);
- the loss head forms dk/dxhat (CEGIS: and dk/dy) from the trunk's outputs by the one
  composition `certify.model.gain.compose`, over the chunk layout [m, N, out]
  (`certify.model.gain.buffered.ChunkCompose`), leaving out the weight-free -K dh/dxhat
  (`with_K_dx=False`): that term is folded, in float64, into the constant part D0 of D;
- the head's gradient: d(loss)/dD in closed form (minors, n <= 2) or by autograd on the
  small [N, n, n] matrices, then autograd back through `compose` to d(loss)/d(N, dN/dz);
  no hand-written adjoint of the head, so the head's chain rule is written once;
- the trunk's reverse pass, `ChunkArithmetic.reverse`, is hand-written: the adjoint of the
  forward-mode propagation over the chunk buffers (the activation's own reverse rule
  `Activation.chain_pre` brings in f''; for tanh f'' = -2 f f', one fused multiply-add). It
  cannot be derived from `propagate`'s structure: `propagate` runs forward mode against an
  arithmetic and records nothing, and its reverse is the adjoint of each step in the
  opposite order (the tangent recurrence T <- f'(pre) T included). Autograd would derive
  it, at the cost above; a generic `reverse` in the arithmetic protocol would be needed by
  this one arithmetic only. So the adjoint is written once, beside the forward whose
  buffers it reads (`certify.model.gain.buffered`), and checked against autograd here;
- preallocated buffers, float32 (the checkpoint and the verifier stay float64), hidden
  widths padded with inert units to a multiple of `WIDTH_MULTIPLE` (the trunk runs a padded
  copy of the weights, `_load_trunk`; the real blocks of the gradient are read back), and
  tanh as 2 sigmoid(2x) - 1 in float32 (`certify.model.gain.buffered.tanh_and_d1_float32`).

Everything that does not depend on the weights (Jf at the points, the constant part of D,
h and dh/dx for the structural gain) is computed once, in float64, before training.
`tests/training/test_training.py` checks the gradient against autograd through
`GainNetwork.forward_with_jacobian` and `certify.model.kernels.gain_terms`, and
`tests/training/test_training_heads.py` the heads against frozen copies of the hand-composed ones
they replaced (the same bits). `check_finite` stops a training loop whose loss, weights or
gradient went non-finite. The training run that optimises it (Adam, then L-BFGS) is
`training.train`; the CEGIS loop extends it (`training.cegis_objective`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import torch

from certify.errors import SettingsError
from certify.model.gain import GainValues, NetOutput, compose, propagate
from certify.model.gain.buffered import CHUNK_COMPOSE, ChunkArithmetic, ChunkBuffers
from certify.model.gain.spec import GainSpec
from certify.model.kernels import sym
from certify.model.network import GainNetwork
from certify.spec.system import System
from training import losses
from training.curvature import CurvaturePenalty
from training.verifier import VerifierPenalty

# points per chunk of the objective. Chunks are the unit of parallel work (one worker thread
# each); the constant is fixed so that the weights do not depend on the number of workers.
CHUNK_POINTS = 2048
# worker threads for the chunks (each runs single-threaded torch ops: no OpenMP barriers, so
# a busy second core costs nothing, while a free one nearly halves the time)
WORKERS = 2
# the trunk's hidden widths are padded to a multiple of this with inert units (zero weights
# in and out, zero bias: every value, derivative and real gradient is unchanged): a float32
# matrix product of width 32 runs faster than one of width 30 (AVX2 holds 8 float32)
WIDTH_MULTIPLE = 8


def padded_widths(widths: list[int], multiple: int = WIDTH_MULTIPLE) -> list[int]:
    """[input, hidden..., output] with each hidden width rounded up to `multiple`."""
    return [widths[0], *[-(-w // multiple) * multiple for w in widths[1:-1]], widths[-1]]


@dataclass
class LossValues:
    """The loss terms at one evaluation (python floats); `curv` is the Jacobian-variation
    penalty C of `training.curvature` (0 when the term is off), before its weight."""

    total: float
    mpdi: float
    bc: float
    curv: float = 0.0
    verifier: float = 0.0  # the box-bound term of `training.verifier`, before its weight

    def as_dict(self) -> dict[str, float]:
        return {"total": self.total, "mpdi": self.mpdi, "bc": self.bc, "curv": self.curv,
                "verifier": self.verifier}


class TrainingDiverged(SettingsError):
    """A loss term or a weight became non-finite (or the gradient overflowed) in training.

    The objective is finite and differentiable for finite weights, so this is float32
    overflow of the problem as set up (lam, the metric's scale, the system's scales, the
    learning rate): the user's settings, exit 2 with one line, no checkpoint."""


class NonFiniteGradient(RuntimeError):
    """The weight gradient is NaN at finite loss terms and finite weights: the objective's
    derivative is undefined where it must not be, a defect of this code, not of the
    settings (the command line's internal error, exit 4)."""


def _param_name(k: int) -> str:
    return f"layer {k // 2} {'weight' if k % 2 == 0 else 'bias'}"


def check_finite(terms: dict[str, float], params: list[torch.Tensor], where: str,
                 grad: bool = True) -> None:
    """Stop training when something went non-finite at `where` (e.g. "adam iteration 12").

    Checks the loss terms (the parts before `total`), then the weights, then (with `grad`)
    their gradients; raises `TrainingDiverged` naming the first bad one, or
    `NonFiniteGradient` for a NaN gradient when everything else is finite."""
    for name in sorted(terms, key=lambda t: t == "total"):
        v = terms[name]
        if not math.isfinite(v):
            raise TrainingDiverged(
                f"training diverged at {where}: the loss term {name} is {v} (overflow:"
                f" lower lam, the metric's scale or the learning rate); nothing was written")
    with torch.no_grad():
        tensors = [t for prm in params
                   for t in ((prm, prm.grad) if grad and prm.grad is not None else (prm,))]
        # the largest |entry| of each (NaN if any is NaN): one call over everything; the
        # culprit is named only when one is not finite
        if not tensors or bool(torch.stack(torch._foreach_norm(tensors, math.inf)).isfinite()
                               .all()):
            return
        for k, prm in enumerate(params):
            if not bool(torch.isfinite(prm).all()):
                raise TrainingDiverged(
                    f"training diverged at {where}: the {_param_name(k)} has a non-finite "
                    f"entry (lower lam, the metric's scale or the learning rate); nothing "
                    f"was written")
        if not grad:
            return
        for k, prm in enumerate(params):
            g = prm.grad
            if g is None or bool(torch.isfinite(g).all()):
                continue
            if bool(torch.isnan(g).any()):
                raise NonFiniteGradient(
                    f"training stopped at {where}: the gradient of the {_param_name(k)} is NaN "
                    f"at finite loss terms and weights; nothing was written")
            raise TrainingDiverged(
                f"training diverged at {where}: the gradient of the {_param_name(k)} "
                f"overflowed (lower lam, the metric's scale or the learning rate); nothing "
                f"was written")


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
                 curvature: CurvaturePenalty | None = None,
                 verifier: VerifierPenalty | None = None) -> None:
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
        self.widths = padded_widths([n + p, *[layer.weight.shape[0] for layer in net.layers]])
        self.trunk = self._trunk_spec()
        self.trunk_params = [t for layer in self.trunk.layers for t in layer]
        self._view_cache: dict[int, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
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
            self.chunks.append(ChunkBuffers(z.to(dt).contiguous(), hi - lo, self.widths,
                                            self.m, not self.structural))
        self.curvature = curvature if (curvature is not None
                                       and curvature.settings.weight > 0) else None
        self.verifier = verifier if (verifier is not None
                                     and verifier.settings.weight > 0) else None
        self.evaluations = 0
        self.workers = max(1, min(int(workers), len(self.chunks)))
        self._pool: ThreadPoolExecutor | None = None

    def _map(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        """fn over items, on `workers` threads (torch releases the GIL inside its ops): the
        calling thread takes the first item, a pool of workers - 1 threads the others."""
        if self.workers == 1 or len(items) == 1:
            return [fn(item) for item in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.workers - 1,
                                            thread_name_prefix="certify-train",
                                            initializer=torch.set_num_threads, initargs=(1,))
        rest = [self._pool.submit(fn, item) for item in items[1:]]
        first = fn(items[0])
        return [first, *(f.result() for f in rest)]

    def close(self) -> None:
        """Stop the worker threads (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # ----- trunk: forward mode with stacked value/tangent rows ---------------------------
    def _trunk_spec(self) -> GainSpec:
        """The gain the chunks propagate: `self.spec` itself when no width is padded, else a
        copy over zero-padded weight buffers that `_load_trunk` fills before each pass."""
        if self.widths[1:] == [layer.weight.shape[0] for layer in self.net.layers]:
            return self.spec
        layers = tuple((torch.zeros(o, i, dtype=W.dtype), torch.zeros(o, dtype=b.dtype))
                       for (W, b), i, o in zip(self.spec.layers, self.widths, self.widths[1:]))
        s = self.spec
        return GainSpec(s.n, s.p, layers, s.activation, s.structure, s.K)

    @torch.no_grad()
    def _load_trunk(self) -> None:
        """Copy the network's current weights into the padded trunk (a no-op without one)."""
        if self.trunk is not self.spec:
            torch._foreach_copy_(self._views(self.trunk_params), self.params)

    def _views(self, padded: list[torch.Tensor]) -> list[torch.Tensor]:
        """`_real(padded)`, made once per list of buffers (a chunk's gradients, the trunk);
        the cache holds the list it was made for, so its id is not reused."""
        cached = self._view_cache.get(id(padded))
        if cached is None or cached[0] is not padded:
            cached = self._view_cache[id(padded)] = (padded, self._real(padded))
        return cached[1]

    def _real(self, padded: list[torch.Tensor]) -> list[torch.Tensor]:
        """The blocks of padded tensors (W0, b0, W1, ...) that are the parameters' (views)."""
        return [t[:p.shape[0], :p.shape[1]] if p.dim() == 2 else t[:p.shape[0]]
                for t, p in zip(padded, self.params)]

    @torch.no_grad()
    def _forward(self, ch: ChunkBuffers) -> tuple[torch.Tensor, torch.Tensor]:
        """N and its first m input derivatives at the chunk's points, by the one propagation
        (`certify.model.gain.propagate`) over the chunk's buffers: value rows [R, out] and
        tangents [m, C, out]."""
        out = propagate(self.trunk, ChunkArithmetic(ch), ch.Z, self.m)
        return out.value, out.jac

    @torch.no_grad()
    def _backward(self, ch: ChunkBuffers, g_val: torch.Tensor, g_tan: torch.Tensor) -> None:
        """Reverse pass through `_forward`: this chunk's weight gradient into `ch.grads`
        (`ChunkArithmetic.reverse`, beside the forward whose buffers it reads)."""
        ChunkArithmetic(ch).reverse(self.trunk, g_val, g_tan)

    # ----- loss head: D from the trunk's outputs, the loss, and its gradient ----------
    def _compose(self, val: torch.Tensor, tan: torch.Tensor, with_dy: bool) -> GainValues:
        """dk/dxhat (and, `with_dy`, dk/dy) at the collocation points from the trunk's value
        val [N, out] and tangents tan [m, N, out] (chunk layout), by `certify.model.gain.compose`.
        dk/dxhat leaves out -K dh/dxhat: that term is weight-free and sits in the float64
        constant D0 (`with_K_dx=False`)."""
        return compose(self.spec, CHUNK_COMPOSE, NetOutput(val, tan), self.r, self.Hx,
                       with_dy=with_dy, with_k=False, with_K_dx=False)

    def _head(self, val: torch.Tensor, tan: torch.Tensor, k_bc: torch.Tensor | None,
              grad: bool) -> tuple[float, float, list[torch.Tensor] | None]:
        """MPDI and BC sums over all points; with `grad`, d(total)/d(val, tan, k_bc).

        val [N, out] and tan [m, N, out] are the trunk's value and xhat-tangents at the
        collocation points, k_bc [N, n] its value at (x, h(x)) (None if structural). D is
        linear in dk/dxhat, so only d(loss)/dD needs differentiating (closed form for the
        minor loss with n <= 2, autograd otherwise); autograd through `compose` maps it back
        to (val, tan).
        """
        N = self.N
        val_l = val.detach().requires_grad_(grad)
        tan_l = tan.detach().requires_grad_(grad)
        with torch.set_grad_enabled(grad):
            M = self._compose(val_l, tan_l, with_dy=False).dk_dx  # [b, i, j] = dk_i/dxhat_j
        D = self.D0 + sym(M.detach() if self.P_is_identity else self.P @ M.detach())
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
        gM = sym(gD) * (self.weights.mu1 / N)
        if not self.P_is_identity:
            gM = self.P.T @ gM
        g_val, g_tan = torch.autograd.grad(M, [val_l, tan_l], grad_outputs=gM,
                                           allow_unused=True)
        g_val = torch.zeros_like(val) if g_val is None else g_val
        if self.structural:
            return mpdi, bc, [g_val, g_tan]
        g_bc = k_bc * (2.0 * self.weights.mu2 / N)
        return mpdi, bc, [g_val, g_tan, g_bc]

    def evaluate(self, grad: bool = True) -> LossValues:
        """Loss terms at the current weights; with `grad`, d(total)/d(weights) into `.grad`.

        All chunks go forward, then one loss head over all points, then all chunks go
        backward; chunks run on `workers` threads, and their gradients are summed in a
        fixed order (the result does not depend on the number of workers).
        """
        mu1, mu2 = self.weights.mu1, self.weights.mu2
        self._load_trunk()
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
            with torch.no_grad():  # the chunks' sums in a fixed order: deterministic
                for prm in self.params:
                    if prm.grad is None:
                        prm.grad = torch.empty_like(prm)
                grads = [prm.grad for prm in self.params]
                torch._foreach_copy_(grads, self._views(self.chunks[0].grads))
                for ch in self.chunks[1:]:
                    torch._foreach_add_(grads, self._views(ch.grads))
        curv = self._extra(self.curvature, grad)
        ver = self._extra(self.verifier, grad)
        self.evaluations += 1
        mpdi_mean, bc_mean = mpdi / self.N, bc / self.N
        return LossValues(total=mu1 * mpdi_mean + mu2 * bc_mean + self.extra_total(curv, ver),
                          mpdi=mpdi_mean, bc=bc_mean, curv=curv, verifier=ver)

    def extra_total(self, curv: float, ver: float) -> float:
        """The weighted sum of the curvature and verifier terms (each 0 when off)."""
        return sum(t.settings.weight * v for t, v in ((self.curvature, curv),
                                                       (self.verifier, ver)) if t is not None)

    def _extra(self, term: CurvaturePenalty | VerifierPenalty | None, grad: bool) -> float:
        """A term evaluated on the network's spec (the Jacobian-variation penalty C of
        `training.curvature`, the box-bound term of `training.verifier`; 0 when off); with
        `grad`, adds weight * d(term)/dW to each parameter's `.grad` (autograd through its
        own small propagation)."""
        if term is None:
            return 0.0
        with torch.enable_grad():
            c = term.value(self.spec)
            if grad:
                gs = torch.autograd.grad(c * term.settings.weight, self.params,
                                         allow_unused=True)
        if grad:
            with torch.no_grad():
                for prm, g in zip(self.params, gs):
                    if g is not None:
                        prm.grad.add_(g)
        return float(c.detach())
