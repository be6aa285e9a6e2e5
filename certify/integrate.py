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

import torch

from certify.gain import gain_value
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


class GainFunction:
    """k(xhat, y) for a batch, by the plain network forward (no Jacobian), float64
    (`certify.gain.gain_value`: the same composition as every other evaluation)."""

    def __init__(self, system: System, net: GainNetwork) -> None:
        self.system = system
        self.spec = net.spec(torch.float64, detach=True)

    def __call__(self, xhat: torch.Tensor, y: torch.Tensor,
                 h_xhat: torch.Tensor | None = None) -> torch.Tensor:
        return gain_value(self.spec, self.system, xhat, y, h_xhat)


def rk4(rhs: Callable[[torch.Tensor, int], torch.Tensor], s0: torch.Tensor, dt: float,
        steps: int) -> torch.Tensor:
    """Classic RK4 on s' = rhs(s, k) (k: the step index, for inputs held over the step).

    s0 of any shape S -> states [steps + 1, *S].
    """
    out = torch.empty((steps + 1, *s0.shape), dtype=s0.dtype)
    out[0] = s0
    s = s0
    h2, h6 = dt / 2.0, dt / 6.0
    for k in range(steps):
        k1 = rhs(s, k)
        k2 = rhs(s + h2 * k1, k)
        k3 = rhs(s + h2 * k2, k)
        k4 = rhs(s + dt * k3, k)
        s = s + h6 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out[k + 1] = s
    return out


def simulate(system: System, net: GainNetwork, x0: torch.Tensor, xhat0: torch.Tensor, *,
             dt: float, steps: int, noise: torch.Tensor | None = None) -> Trajectories:
    """Plant + observer from x0, xhat0 [B, n] over `steps` steps of `dt`, noise [steps, B, p].

    The plant and observer are integrated together (one RK4 on the stacked state [2B, n]);
    f and h are evaluated once per stage on the stacked batch [2B, n].
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
    gain = GainFunction(system, net)

    def rhs(s: torch.Tensor, k: int) -> torch.Tensor:
        # s [2B, n]: rows of x (first B), then rows of xhat
        fz = system.f(s)
        hz = system.h(s)
        y = hz[:B] + noise[k]
        kk = gain(s[B:], y, hz[B:])
        return torch.cat([fz[:B], fz[B:] + kk], dim=0)

    with torch.no_grad():
        s0 = torch.cat([x0, xhat0], dim=0)
        traj = rk4(rhs, s0, float(dt), int(steps))  # [steps + 1, 2B, n]
    t = torch.arange(steps + 1, dtype=torch.float64) * float(dt)
    v = torch.cat([noise, noise[-1:]], dim=0) if steps > 0 else noise.new_zeros(1, B, p)
    return Trajectories(t=t, x=traj[:, :B], xhat=traj[:, B:], v=v)
