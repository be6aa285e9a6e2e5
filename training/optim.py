"""The two optimisation phases of the source method: full-batch Adam, then L-BFGS.

Both reproduce `torch.optim.Adam` and `torch.optim.LBFGS` (defaults; L-BFGS with
`line_search_fn="strong_wolfe"` and torch's own strong Wolfe line search) operation for
operation: `tests/training/test_training.py` checks that the iterates agree with torch's. They are
re-stated here rather than called because constructing any `torch.optim` optimizer imports
`torch._dynamo`, which costs 2-3 s on this machine, a fifth of the paper preset's budget.

Both drive an objective with `evaluate(grad=True) -> values` that writes the weight gradient
into `.grad`; each evaluation is handed to `record(values, iteration)` and shown through the
injected `Progress` (task names "adam" and "lbfgs").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

try:  # torch's line search (a plain function; importing it does not import dynamo)
    from torch.optim.lbfgs import _strong_wolfe
except ImportError:  # pragma: no cover - very old or very new torch
    _strong_wolfe = None

from certify.progress import Progress


class _Objective(Protocol):
    def evaluate(self, grad: bool = True) -> Any: ...


@dataclass
class PhaseStats:
    """What one phase did: iterations taken and objective evaluations spent."""

    iterations: int
    evaluations: int


def _fields(values: Any) -> dict[str, float]:
    return {"loss": values.total, "mpdi": values.mpdi, "bc": values.bc}


# ----- Adam ------------------------------------------------------------------------------


class Adam:
    """torch.optim.Adam (single-tensor path, no weight decay, no amsgrad), restated."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float = 1e-3,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.params = list(params)
        self.lr, self.beta1, self.beta2, self.eps = float(lr), betas[0], betas[1], float(eps)
        self.exp_avg = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
        self.step_count = 0

    @torch.no_grad()
    def step(self) -> None:
        self.step_count += 1
        step = float(self.step_count)
        bias_correction1 = 1 - self.beta1 ** step
        bias_correction2 = 1 - self.beta2 ** step
        step_size = self.lr / bias_correction1
        bias_correction2_sqrt = bias_correction2 ** 0.5
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq):
            g = p.grad
            m.lerp_(g, 1 - self.beta1)
            v.mul_(self.beta2).addcmul_(g, g, value=1 - self.beta2)
            denom = (v.sqrt() / bias_correction2_sqrt).add_(self.eps)
            p.addcdiv_(m, denom, value=-step_size)


def run_adam(objective: _Objective, params: Sequence[torch.Tensor], *, iters: int, lr: float,
             record: Callable[[Any, int], None], progress: Progress) -> PhaseStats:
    """`iters` full-batch Adam steps (one evaluation each, recorded before its step)."""
    opt = Adam(params, lr=lr)
    progress.start("adam", total=iters)
    last = None
    for it in range(iters):
        last = objective.evaluate(grad=True)
        record(last, it)
        opt.step()
        progress.update("adam", advance=1, **_fields(last))
    progress.finish("adam", f"loss {last.total:.4g}" if last is not None else "")
    return PhaseStats(iterations=iters, evaluations=iters)


# ----- L-BFGS ----------------------------------------------------------------------------


def _scalar(value: Any, like: torch.Tensor | None = None) -> np.generic:
    """A 0-dim tensor (or a number, in the dtype of `like`) as a numpy scalar of its dtype:
    arithmetic on it rounds as on the tensor (IEEE, correctly rounded, same precision)."""
    if isinstance(value, torch.Tensor):
        return value.numpy()[()]
    return np.dtype(str(like.dtype).removeprefix("torch.")).type(value)


class LBFGS:
    """torch.optim.LBFGS with the strong Wolfe line search, restated (one `run` = one torch
    `step`: up to `max_iter` iterations and `max_eval` evaluations)."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float = 1.0, max_iter: int = 20,
                 max_eval: int | None = None, tolerance_grad: float = 1e-7,
                 tolerance_change: float = 1e-9, history_size: int = 100) -> None:
        if _strong_wolfe is None:  # pragma: no cover
            raise RuntimeError("this torch has no torch.optim.lbfgs._strong_wolfe")
        self.params = list(params)
        self.lr, self.max_iter = float(lr), int(max_iter)
        self.max_eval = max_iter * 5 // 4 if max_eval is None else int(max_eval)
        self.tolerance_grad, self.tolerance_change = tolerance_grad, tolerance_change
        self.history_size = history_size
        self.n_iter = 0
        self.func_evals = 0

    def _flat_grad(self) -> torch.Tensor:
        return torch.cat([p.grad.reshape(-1) for p in self.params], 0)

    def _add_grad(self, step_size: float, update: torch.Tensor) -> None:
        offset = 0
        for p in self.params:
            numel = p.numel()
            p.add_(update[offset:offset + numel].view_as(p), alpha=step_size)
            offset += numel

    def _directional_evaluate(self, closure: Callable[[], float], x: list[torch.Tensor],
                              t: float, d: torch.Tensor) -> tuple[float, torch.Tensor]:
        self._add_grad(t, d)
        loss = float(closure())
        flat_grad = self._flat_grad()
        for p, pdata in zip(self.params, x):
            p.copy_(pdata)
        return loss, flat_grad

    @torch.no_grad()
    def run(self, closure: Callable[[], float]) -> float:
        """Minimise from the current parameters; returns the first loss (as torch does)."""
        orig_loss = closure()
        loss = float(orig_loss)
        current_evals = 1
        self.func_evals += 1
        flat_grad = self._flat_grad()
        if flat_grad.abs().max() <= self.tolerance_grad:
            return orig_loss
        d: Any = None
        t: Any = None
        old_dirs: list[torch.Tensor] = []
        old_stps: list[torch.Tensor] = []
        ro: list[Any] = []
        H_diag: Any = 1
        al: list[Any] = [None] * self.history_size
        prev_flat_grad = None
        n_iter = 0
        while n_iter < self.max_iter:
            n_iter += 1
            self.n_iter += 1
            if self.n_iter == 1:
                d = flat_grad.neg()
                old_dirs, old_stps, ro, H_diag = [], [], [], 1
            else:
                y = flat_grad.sub(prev_flat_grad)
                s = d.mul(t)
                ys = y.dot(s)
                if ys > 1e-10:
                    if len(old_dirs) == self.history_size:
                        old_dirs.pop(0)
                        old_stps.pop(0)
                        ro.pop(0)
                    old_dirs.append(y)
                    old_stps.append(s)
                    ro.append(_scalar(1.0, ys) / _scalar(ys))
                    H_diag = _scalar(ys) / _scalar(y.dot(y))
                num_old = len(old_dirs)
                q = flat_grad.neg()
                # the two-loop recursion: the scalars in the vectors' precision on the host
                # (numpy), the same roundings as torch's 0-dim tensors at a third of the calls
                for i in range(num_old - 1, -1, -1):
                    al[i] = _scalar(old_stps[i].dot(q)) * ro[i]
                    q.add_(old_dirs[i], alpha=float(-al[i]))
                d = r = torch.mul(q, float(H_diag))
                for i in range(num_old):
                    be_i = _scalar(old_dirs[i].dot(r)) * ro[i]
                    r.add_(old_stps[i], alpha=float(al[i] - be_i))
            if prev_flat_grad is None:
                prev_flat_grad = flat_grad.clone(memory_format=torch.contiguous_format)
            else:
                prev_flat_grad.copy_(flat_grad)
            prev_loss = loss
            if self.n_iter == 1:
                t = min(1.0, 1.0 / flat_grad.abs().sum()) * self.lr
            else:
                t = self.lr
            gtd = flat_grad.dot(d)
            if gtd > -self.tolerance_change:
                break
            x_init = [p.clone(memory_format=torch.contiguous_format) for p in self.params]

            def obj_func(x: list[torch.Tensor], t: float, d: torch.Tensor
                         ) -> tuple[float, torch.Tensor]:
                return self._directional_evaluate(closure, x, t, d)

            loss, flat_grad, t, ls_func_evals = _strong_wolfe(
                obj_func, x_init, t, d, loss, flat_grad, gtd,
                max_ls=self.max_eval - current_evals)
            self._add_grad(t, d)
            opt_cond = flat_grad.abs().max() <= self.tolerance_grad
            current_evals += ls_func_evals
            self.func_evals += ls_func_evals
            if n_iter == self.max_iter or current_evals >= self.max_eval or opt_cond:
                break
            if d.mul(t).abs().max() <= self.tolerance_change:
                break
            if abs(loss - prev_loss) < self.tolerance_change:
                break
        return orig_loss


def run_lbfgs(objective: _Objective, params: Sequence[torch.Tensor], *, iters: int,
              lr: float, record: Callable[[Any, int], None],
              progress: Progress) -> PhaseStats:
    """One L-BFGS run with `max_iter = iters` and the strong Wolfe line search (other
    settings at torch's defaults, as the source method uses them)."""
    params = list(params)
    opt = LBFGS(params, lr=lr, max_iter=iters)
    progress.start("lbfgs", total=iters)
    count = {"evaluations": 0, "shown": 0}
    last: list[Any] = [None]

    def closure() -> float:
        with torch.enable_grad():
            values = objective.evaluate(grad=True)
        count["evaluations"] += 1
        it = opt.n_iter
        record(values, it)
        last[0] = values
        if it > count["shown"]:
            progress.update("lbfgs", advance=it - count["shown"], **_fields(values))
            count["shown"] = it
        return values.total

    opt.run(closure)
    if opt.n_iter > count["shown"] and last[0] is not None:
        progress.update("lbfgs", advance=opt.n_iter - count["shown"], **_fields(last[0]))
    progress.finish("lbfgs", f"{opt.n_iter} iterations, {count['evaluations']} evaluations")
    return PhaseStats(iterations=opt.n_iter, evaluations=count["evaluations"])
