"""Batched fixed-step RK4 for plant + observer, float64, vectorised over initial conditions.

    x'    = f(x)
    xhat' = f(xhat) + k(xhat, h(x) + v(t))

The noise v is held constant over each step (sample and hold), so every RK4 step integrates
a smooth right-hand side and keeps its fourth order. Two noise models:

- `bounded_noise`: piecewise constant over holds of a few steps, each value a random
  direction scaled to norm exactly `vbar` (so ||v(t)||_2 <= vbar holds exactly; the largest
  admissible magnitude, which stresses a bound the most);
- `gaussian_noise`: white Gaussian samples of a given standard deviation, one per step (the
  source's protocol; it has no bound vbar).

Noise tensors have shape [steps, B, p]; states [B, n]; trajectories [steps + 1, B, n].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from certify.gain import GainSpec, RowArithmetic, gain_value
from certify.network import GainNetwork
from certify.system import System


@dataclass
class Trajectories:
    """Time grid t [T], plant x [T, B, n], observer xhat [T, B, n], noise held per step
    v [T, B, p] (v[k] acts on [t_k, t_k+1]; the last row repeats the previous one)."""

    t: torch.Tensor
    x: torch.Tensor
    xhat: torch.Tensor
    v: torch.Tensor


def hold_steps(dt: float, hold: float) -> int:
    """Steps per noise hold: round(hold / dt), at least 2 and even (so a run at 2 dt sees the
    same signal; used to estimate the integration error)."""
    k = max(2, int(round(hold / dt)))
    return k + (k % 2)


def bounded_noise(steps: int, batch: int, p: int, vbar: float, dt: float, *,
                  hold: float = 0.05, seed: int = 0) -> torch.Tensor:
    """Piecewise-constant noise with ||v||_2 = vbar exactly on each hold -> [steps, B, p]."""
    gen = torch.Generator().manual_seed(int(seed))
    k = hold_steps(dt, hold)
    m = -(-steps // k)
    d = torch.randn(m, batch, p, generator=gen, dtype=torch.float64)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-300)
    v = d * float(vbar)
    # the rounding of the scaling may exceed vbar by an ulp: clip to the exact bound
    norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    v = torch.where(norm > vbar, v * (vbar / norm) * (1 - 1e-15), v)
    return v.repeat_interleave(k, dim=0)[:steps]


def gaussian_noise(steps: int, batch: int, p: int, std: float, *, seed: int = 0
                   ) -> torch.Tensor:
    """White Gaussian noise of standard deviation `std`, one sample per step -> [steps, B, p]."""
    gen = torch.Generator().manual_seed(int(seed))
    return std * torch.randn(steps, batch, p, generator=gen, dtype=torch.float64)


class _ValueRows(RowArithmetic):
    """`RowArithmetic` for k alone (no tangents), with fewer operations per call: the
    activation's derivative is not computed (nothing uses it), the weights' transposes are
    made once, and G r for p = 1 is one product (the floats of einsum's batched product:
    one multiplication per entry). The simulation calls it ~20 k times on a few rows, where
    the cost is the number of torch operations, not their size."""

    def __init__(self, spec: GainSpec) -> None:
        self._transposed = {id(W): W.T for W, _ in spec.layers}
        self._transposed[id(spec.K)] = spec.K.T

    def _T(self, W: torch.Tensor) -> torch.Tensor:
        WT = self._transposed.get(id(W))
        return W.T if WT is None else WT

    def input_layer(self, z: torch.Tensor, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        if m:
            return super().input_layer(z, W, b, m)
        return z @ self._T(W) + b, None

    def activate(self, act: Any, pre: torch.Tensor, layer: int, order: int
                 ) -> tuple[torch.Tensor, None, None]:
        return act.f(pre), None, None

    def affine(self, a: torch.Tensor, T: torch.Tensor | None, S: torch.Tensor | None,
               W: torch.Tensor, b: torch.Tensor, layer: int
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        if T is None and S is None:
            return torch.addmm(b, a, self._T(W)), None, None
        return super().affine(a, T, S, W, b, layer)

    def reshape_out(self, out: torch.Tensor, n: int, p: int) -> torch.Tensor:
        return out if p == 1 else out.reshape(out.shape[0], n, p)  # p = 1: G as [B, n]

    def matvec(self, A: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        if A.ndim == 2:  # p = 1: G r = G[:, :, 0] * r
            return A * v
        return torch.bmm(A, v.unsqueeze(-1)).squeeze(-1)

    def const_matvec(self, K: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return v @ self._T(K)


class GainFunction:
    """k(xhat, y) for a batch, by the plain network forward (no Jacobian), float64
    (`certify.gain.gain_value`: the same composition as every other evaluation)."""

    def __init__(self, system: System, net: GainNetwork) -> None:
        self.system = system
        self.spec = net.spec(torch.float64, detach=True)
        self.arith = _ValueRows(self.spec)

    def __call__(self, xhat: torch.Tensor, y: torch.Tensor,
                 h_xhat: torch.Tensor | None = None) -> torch.Tensor:
        return gain_value(self.spec, self.system, xhat, y, h_xhat, arith=self.arith)


def rk4(rhs: Callable[[torch.Tensor, int], torch.Tensor], s0: torch.Tensor, dt: float,
        steps: int) -> torch.Tensor:
    """Classic RK4 on s' = rhs(s, k) (k: the step index, for inputs held over the step).

    s0 of any shape S -> states [steps + 1, *S].
    """
    out = torch.empty((steps + 1, *s0.shape), dtype=s0.dtype)
    out[0] = s0
    s = s0
    coef = rk4_coefficients(dt)
    for k in range(steps):
        s = rk4_step(rhs, s, k, dt, coef)
        out[k + 1] = s
    return out


Coefficients = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def rk4_coefficients(dt: float | torch.Tensor) -> Coefficients:
    """(dt/2, dt, dt/6, 2) as float64 tensors, made once per integration: a tensor operand
    costs less per operation than a Python float, and gives the same floats."""
    dt_t = torch.as_tensor(dt, dtype=torch.float64)
    return dt_t / 2.0, dt_t, dt_t / 6.0, torch.tensor(2.0, dtype=torch.float64)


def rk4_step(rhs: Callable[[torch.Tensor, int], torch.Tensor], s: torch.Tensor, k: int,
             dt: float | torch.Tensor, coef: Coefficients | None = None) -> torch.Tensor:
    """One RK4 step; `dt` a float or a column [rows, 1] (a step size per row of s);
    `coef`: `rk4_coefficients(dt)` when already made."""
    h2, h, h6, two = rk4_coefficients(dt) if coef is None else coef
    k1 = rhs(s, k)
    k2 = rhs(s + h2 * k1, k)
    k3 = rhs(s + h2 * k2, k)
    k4 = rhs(s + h * k3, k)
    return s + h6 * (k1 + two * k2 + two * k3 + k4)


def simulate_plant(system: System, x0: torch.Tensor, *, dt: float, steps: int) -> torch.Tensor:
    """The plant alone, x' = f(x), from x0 [B, n] -> states [steps + 1, B, n] (RK4)."""
    with torch.no_grad():
        return rk4(lambda s, k: system.f(s), torch.as_tensor(x0, dtype=torch.float64),
                   float(dt), int(steps))


def simulate(system: System, net: GainNetwork, x0: torch.Tensor, xhat0: torch.Tensor, *,
             dt: float, steps: int, noise: torch.Tensor | None = None) -> Trajectories:
    """Plant + observer from x0, xhat0 [B, n] over `steps` steps of `dt`, noise [steps, B, p].

    The plant and observer are integrated together (one RK4 on the stacked state [2B, n]);
    f and h are evaluated once per stage on the stacked batch [2B, n].
    """
    return simulate_doubled(system, net, x0, xhat0, dt=dt, steps=steps, noise=noise)[0]


def simulate_doubled(system: System, net: GainNetwork, x0: torch.Tensor, xhat0: torch.Tensor,
                     *, dt: float, steps: int, noise: torch.Tensor | None = None,
                     doubled: list[int] | None = None, doubled_steps: int = 0
                     ) -> tuple[Trajectories, Trajectories | None]:
    """`simulate`, and the runs `doubled` again at step 2 dt for `doubled_steps` steps.

    One batched integrator over every run: on every second step of dt the runs at 2 dt join
    the batch (a step size per row), so the second integration costs no extra right-hand-side
    calls. Their noise is the same signal sampled every second step (held over 2 dt when the
    hold is even, see `hold_steps`). Returns (the dt trajectories, the 2 dt ones or None).
    """
    n, p = system.n, system.p
    x0 = torch.as_tensor(x0, dtype=torch.float64)
    xhat0 = torch.as_tensor(xhat0, dtype=torch.float64)
    if x0.ndim != 2 or x0.shape[1] != n or xhat0.shape != x0.shape:
        raise ValueError(f"x0 and xhat0 must have shape [B, {n}]; got {list(x0.shape)} and "
                         f"{list(xhat0.shape)}")
    B = x0.shape[0]
    if noise is None:
        noise = torch.zeros(steps, B, p, dtype=torch.float64)
    noise = torch.as_tensor(noise, dtype=torch.float64)
    if noise.shape != (steps, B, p):
        raise ValueError(f"noise must have shape [{steps}, {B}, {p}]; got {list(noise.shape)}")
    rows = list(doubled or [])
    c_steps = min(int(doubled_steps), steps // 2) if rows else 0
    C = len(rows) if c_steps > 0 else 0
    gain = GainFunction(system, net)
    both = noise if C == 0 else torch.cat([noise, noise[:, rows]], dim=1)  # [steps, B + C, p]
    width = [B]  # rows of x (then of xhat) in the state now being stepped

    # per step, as Python lists: indexing them is no torch operation
    noise_fine, noise_both = noise.unbind(0), both.unbind(0)

    def rhs(s: torch.Tensor, k: int) -> torch.Tensor:
        # s [2W, n]: rows of x (first W), then rows of xhat; f and h in one call
        W = width[0]
        fh = system.f_and_h(s)  # [2W, n + p], a fresh tensor
        at_x, at_xhat = fh.split(W)
        y = at_x[:, n:] + (noise_fine[k] if W == B else noise_both[k])
        at_xhat[:, :n] += gain(s[W:], y, at_xhat[:, n:])  # f(xhat) + k, in place
        return fh[:, :n]

    dt = float(dt)
    with torch.no_grad():
        fine = torch.empty((steps + 1, 2 * B, n), dtype=torch.float64)
        fine[0] = torch.cat([x0, xhat0], dim=0)
        coarse = torch.empty((c_steps + 1, 2 * C, n), dtype=torch.float64) if C else None
        if coarse is not None:
            coarse[0] = torch.cat([x0[rows], xhat0[rows]], dim=0)
            col = torch.cat([torch.full((B, 1), dt, dtype=torch.float64),
                             torch.full((C, 1), 2 * dt, dtype=torch.float64)])
            col = torch.cat([col, col], dim=0)  # x rows, then xhat rows
            coef_joint = rk4_coefficients(col)
        coef = rk4_coefficients(dt)
        s_f = fine[0]
        for k in range(steps):
            j = k // 2
            if coarse is not None and k % 2 == 0 and j < c_steps:
                s_c = coarse[j]
                joint = torch.cat([s_f[:B], s_c[:C], s_f[B:], s_c[C:]], dim=0)
                width[0] = B + C
                out = rk4_step(rhs, joint, k, col, coef_joint)
                width[0] = B
                s_f = torch.cat([out[:B], out[B + C: 2 * B + C]], dim=0)
                coarse[j + 1] = torch.cat([out[B: B + C], out[2 * B + C:]], dim=0)
            else:
                s_f = rk4_step(rhs, s_f, k, dt, coef)
            fine[k + 1] = s_f
    t = torch.arange(steps + 1, dtype=torch.float64) * dt
    v = torch.cat([noise, noise[-1:]], dim=0) if steps > 0 else noise.new_zeros(1, B, p)
    result = Trajectories(t=t, x=fine[:, :B], xhat=fine[:, B:], v=v)
    if coarse is None:
        return result, None
    vc = noise[: 2 * c_steps: 2, rows]
    vc = torch.cat([vc, vc[-1:]], dim=0)
    tc = torch.arange(c_steps + 1, dtype=torch.float64) * (2 * dt)
    return result, Trajectories(t=tc, x=coarse[:, :C], xhat=coarse[:, C:], v=vc)
