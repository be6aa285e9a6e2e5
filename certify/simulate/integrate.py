"""Batched fixed-step RK4 for plant + observer, float64: every run of a check in one batch.

    x'    = f(x)
    xhat' = f(xhat) + k(xhat, h(x) + v(t))

The noise v is held constant over each step (sample and hold), so every RK4 step integrates
a smooth right-hand side and keeps its fourth order. Three noise models:

- `bounded_noise`: piecewise constant over holds of a few steps, each value a random
  direction scaled to norm vbar (1 - 1e-14) (so ||v(t)||_2 <= vbar holds however the norm
  is computed; the largest admissible magnitude, which stresses a bound the most);
- worst-case-like noise chosen from the states as the run goes (`simulate_doubled`'s
  `feedback`, `certify.simulate.noise.SwitchingNoise`);
- `gaussian_noise`: white Gaussian samples of a given standard deviation, one per step (the
  source's protocol; it has no bound vbar).

Noise arrays have shape [steps, B, p]; states [B, n]; trajectories [steps + 1, B, n]. All
runs (every start under every noise kind, the source's protocol, and the runs again at 2 dt
for the integration error) advance together: one right-hand-side call per RK4 stage on the
whole batch. The batch is a few rows, so a step costs the number of library calls more than
arithmetic: the integrator runs on float64 NumPy arrays (f and h by `System.array_rows`, k
by `GainFunction`), whose calls are cheaper than torch's on a few rows. `Trajectories` hands
torch tensors on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from certify.model.network import GainNetwork
from certify.spec.system import System


def as_array(x: Any) -> np.ndarray:
    """A float64 NumPy copy of x (a torch tensor on any device, an array or nested lists)."""
    if isinstance(x, torch.Tensor):
        return x.detach().to(device="cpu", dtype=torch.float64).numpy().copy()
    return np.array(x, dtype=np.float64)


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
    # norm vbar (1 - 1e-14): the rounding of the scaling, or a norm computed by another
    # library, may exceed vbar (1 - 1e-14) by a few ulps, never vbar
    v = d * (float(vbar) * (1 - 1e-14))
    norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    v = torch.where(norm > vbar, v * (vbar / norm) * (1 - 1e-14), v)
    return v.repeat_interleave(k, dim=0)[:steps]


def gaussian_noise(steps: int, batch: int, p: int, std: float, *, seed: int = 0
                   ) -> torch.Tensor:
    """White Gaussian noise of standard deviation `std`, one sample per step -> [steps, B, p]."""
    gen = torch.Generator().manual_seed(int(seed))
    return std * torch.randn(steps, batch, p, generator=gen, dtype=torch.float64)


class Feedback(Protocol):
    """Noise chosen from the states (`simulate_doubled`'s `feedback`): for the runs `rows`
    of the batch, called at step index k (k = 0 first, a multiple of `hold`) with their
    plant and observer states [m, n] at t_k; returns their noise [H, m, p] for the next
    1 <= H <= `holds` holds of `hold` steps each, and is called again at k + H hold."""

    rows: list[int]
    hold: int

    def __call__(self, k: int, x: np.ndarray, xhat: np.ndarray, holds: int) -> np.ndarray: ...


class GainFunction:
    """k(xhat, y) for a batch of float64 NumPy rows (xhat [B, n], y [B, p] -> [B, n]): the
    plain network forward (no Jacobian), written out for the simulation, whose right-hand
    side calls it ~20 k times on a few rows each, where every library call counts.

    The composition of `certify.model.gain.gain_value` (the one every evaluation uses), step
    for step and with the same products, so the floats agree with its NumPy form exactly and
    with its torch form up to the libraries' rounding of products and the activation (last
    ulps; tested): N = W_L act(... act(W_0 [xhat, y] + b_0) ...) + b_L, then
    k = N (direct) or G (y - h(xhat)) with G = N as [n, p] (structural), plus K (y - h(xhat)).
    The weights are copied (transposed) once; the activation's `f_array` is its NumPy form.
    A network whose last layer is zero (a zero gain, training's warm start) has N = 0 at
    every finite input, and is not evaluated (k = K (y - h(xhat)), or 0).
    """

    def __init__(self, system: System, net: GainNetwork) -> None:
        spec = net.spec(torch.float64, detach=True)
        self.system = system
        self.n, self.p = spec.n, spec.p
        self.layers = [(np.ascontiguousarray(as_array(W).T), as_array(b)) for W, b in spec.layers]
        self.act = spec.activation.f_array
        self.structural = spec.structural
        self.needs_h = spec.needs_h
        self.K_T = np.ascontiguousarray(as_array(spec.K).T) if spec.has_K else None
        self._h = system.array_rows("fh") if spec.needs_h else None
        W_L, b_L = self.layers[-1]
        self.silent = not (W_L.any() or b_L.any())  # N = 0

    def __call__(self, xhat: np.ndarray, y: np.ndarray,
                 h_xhat: np.ndarray | None = None) -> np.ndarray:
        if not isinstance(xhat, np.ndarray) or not isinstance(y, np.ndarray):
            xhat, y = as_array(xhat), as_array(y)
        if self.silent and self.K_T is None:
            return np.zeros((xhat.shape[0], self.n))
        if self.needs_h and h_xhat is None:
            h_xhat = self._h(xhat)[:, self.n:]  # type: ignore[misc]
        if self.silent:
            return (y - h_xhat) @ self.K_T
        (W0, b0), rest = self.layers[0], self.layers[1:]
        a = np.concatenate([xhat, y], axis=1) @ W0 + b0
        for W, b in rest:
            a = self.act(a) @ W + b
        if not self.needs_h:
            return a
        r = y - h_xhat
        k = a
        if self.structural:  # G r, G = N as [B, n, p] (p = 1: N * r)
            k = a * r if self.p == 1 else (a.reshape(-1, self.n, self.p) @ r[:, :, None])[:, :, 0]
        if self.K_T is not None:
            k = k + r @ self.K_T
        return k


def rk4(rhs: Callable[[np.ndarray, int], np.ndarray], s0: np.ndarray, dt: float,
        steps: int) -> np.ndarray:
    """Classic RK4 on s' = rhs(s, k) (k: the step index, for inputs held over the step).

    s0 of any shape S -> states [steps + 1, *S] (float64 NumPy).
    """
    out = np.empty((steps + 1, *s0.shape), dtype=np.float64)
    out[0] = s0
    s = s0
    coef = rk4_coefficients(dt)
    for k in range(steps):
        s = rk4_step(rhs, s, k, dt, coef)
        out[k + 1] = s
    return out


Coefficients = tuple[Any, Any, Any]


def rk4_coefficients(dt: float | np.ndarray) -> Coefficients:
    """(dt/2, dt, dt/6), made once per integration; `dt` a float or a column [rows, 1]."""
    if np.ndim(dt) == 0:
        h = float(dt)
        return h / 2.0, h, h / 6.0
    col = np.asarray(dt, dtype=np.float64)
    return col / 2.0, col, col / 6.0


def rk4_step(rhs: Callable[[np.ndarray, int], np.ndarray], s: np.ndarray, k: int,
             dt: float | np.ndarray, coef: Coefficients | None = None) -> np.ndarray:
    """One RK4 step; `dt` a float or a column [rows, 1] (a step size per row of s);
    `coef`: `rk4_coefficients(dt)` when already made."""
    h2, h, h6 = rk4_coefficients(dt) if coef is None else coef
    k1 = rhs(s, k)
    k2 = rhs(s + h2 * k1, k)
    k3 = rhs(s + h2 * k2, k)
    k4 = rhs(s + h * k3, k)
    return s + h6 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def simulate_plant(system: System, x0: torch.Tensor | np.ndarray, *, dt: float, steps: int
                   ) -> torch.Tensor:
    """The plant alone, x' = f(x), from x0 [B, n] -> states [steps + 1, B, n] (RK4)."""
    f = system.array_rows("f")
    with np.errstate(all="ignore"):  # a run that blows up ends as inf/NaN, found later
        out = rk4(lambda s, k: f(s), as_array(x0), float(dt), int(steps))
    return torch.from_numpy(out)


def simulate(system: System, net: GainNetwork, x0: torch.Tensor, xhat0: torch.Tensor, *,
             dt: float, steps: int, noise: torch.Tensor | None = None) -> Trajectories:
    """Plant + observer from x0, xhat0 [B, n] over `steps` steps of `dt`, noise [steps, B, p].

    The plant and observer are integrated together (one RK4 on the stacked state [2B, n]);
    f and h are evaluated once per stage on the stacked batch [2B, n].
    """
    return simulate_doubled(system, net, x0, xhat0, dt=dt, steps=steps, noise=noise)[0]


def simulate_doubled(system: System, net: GainNetwork, x0: torch.Tensor, xhat0: torch.Tensor,
                     *, dt: float, steps: int, noise: torch.Tensor | None = None,
                     doubled: list[int] | None = None, doubled_steps: int = 0,
                     feedback: Feedback | None = None
                     ) -> tuple[Trajectories, Trajectories | None]:
    """`simulate`, and the runs `doubled` again at step 2 dt for `doubled_steps` steps.

    One batched integrator over every run: on every second step of dt the runs at 2 dt join
    the batch (a step size per row), so the second integration costs no extra right-hand-side
    calls. Their noise is the same signal sampled every second step (held over 2 dt when the
    hold is even, see `hold_steps`). Returns (the dt trajectories, the 2 dt ones or None).

    `feedback` (optional, e.g. `certify.simulate.noise.SwitchingNoise`): the noise of its
    `rows` is chosen from the states as the run goes (see `Feedback`; hold even): its H
    values [H, m, p] are held `hold` steps each from step k on (they replace what `noise`
    had there; the returned `v` is the signal used). A run at 2 dt replays the signal its
    dt run chose (the same piecewise-constant input), so step doubling still measures the
    integration error alone.
    """
    n, p = system.n, system.p
    x0 = as_array(x0)
    xhat0 = as_array(xhat0)
    if x0.ndim != 2 or x0.shape[1] != n or xhat0.shape != x0.shape:
        raise ValueError(f"x0 and xhat0 must have shape [B, {n}]; got {list(x0.shape)} and "
                         f"{list(xhat0.shape)}")
    B = x0.shape[0]
    noise = (np.zeros((steps, B, p)) if noise is None
             else as_array(noise))
    if noise.shape != (steps, B, p):
        raise ValueError(f"noise must have shape [{steps}, {B}, {p}]; got {list(noise.shape)}")
    rows = list(doubled or [])
    c_steps = min(int(doubled_steps), steps // 2) if rows else 0
    C = len(rows) if c_steps > 0 else 0
    gain = GainFunction(system, net)
    f_and_h = system.array_rows("fh")
    fb_rows = list(feedback.rows) if feedback is not None else []
    if feedback is not None and (feedback.hold < 2 or feedback.hold % 2):
        raise ValueError(f"feedback noise must be held an even number of steps >= 2; got "
                         f"{feedback.hold}")
    width = [B]  # rows of x (then of xhat) in the state now being stepped
    v_now = [noise[0] if steps > 0 else np.zeros((B, p))]  # the noise of the current step

    def rhs(s: np.ndarray, k: int) -> np.ndarray:
        # s [2W, n]: rows of x (first W), then rows of xhat; f and h in one call
        W = width[0]
        fh = f_and_h(s)  # [2W, n + p], a fresh array
        at_x, at_xhat = fh[:W], fh[W:]
        y = at_x[:, n:] + v_now[0]
        at_xhat[:, :n] += gain(s[W:], y, at_xhat[:, n:])  # f(xhat) + k, in place
        return fh[:, :n]

    dt = float(dt)
    fine = np.empty((steps + 1, 2 * B, n))
    fine[0] = np.concatenate([x0, xhat0])
    coarse = np.empty((c_steps + 1, 2 * C, n)) if C else None
    if coarse is not None:
        coarse[0] = np.concatenate([x0[rows], xhat0[rows]])
        col = np.concatenate([np.full((B, 1), dt), np.full((C, 1), 2 * dt)])
        col = np.concatenate([col, col])  # x rows, then xhat rows
        coef_joint = rk4_coefficients(col)
    coef = rk4_coefficients(dt)
    s_f = fine[0]
    next_fb = 0 if fb_rows else steps  # the step at which the feedback is asked again
    with np.errstate(all="ignore"):  # a run that blows up ends as inf/NaN, found later
        for k in range(steps):
            if k == next_fb:
                hold = feedback.hold  # type: ignore[union-attr]
                v = feedback(k, s_f[fb_rows], s_f[B:][fb_rows],  # type: ignore[misc]
                             -(-(steps - k) // hold))
                span = min(len(v) * hold, steps - k)
                noise[k: k + span, fb_rows] = np.repeat(v, hold, axis=0)[:span]
                next_fb = k + len(v) * hold
            j = k // 2
            v_now[0] = noise[k]
            if coarse is not None and k % 2 == 0 and j < c_steps:
                v_now[0] = np.concatenate([noise[k], noise[k, rows]])
                s_c = coarse[j]
                joint = np.concatenate([s_f[:B], s_c[:C], s_f[B:], s_c[C:]])
                width[0] = B + C
                out = rk4_step(rhs, joint, k, col, coef_joint)
                width[0] = B
                s_f = np.concatenate([out[:B], out[B + C: 2 * B + C]])
                coarse[j + 1] = np.concatenate([out[B: B + C], out[2 * B + C:]])
            else:
                s_f = rk4_step(rhs, s_f, k, dt, coef)
            fine[k + 1] = s_f
    t = torch.from_numpy(np.arange(steps + 1, dtype=np.float64) * dt)
    v_np = np.concatenate([noise, noise[-1:]]) if steps > 0 else np.zeros((1, B, p))
    result = Trajectories(t=t, x=torch.from_numpy(fine[:, :B]),
                          xhat=torch.from_numpy(fine[:, B:]), v=torch.from_numpy(v_np))
    if coarse is None:
        return result, None
    vc = noise[: 2 * c_steps: 2, rows]
    vc = np.concatenate([vc, vc[-1:]])
    tc = torch.from_numpy(np.arange(c_steps + 1, dtype=np.float64) * (2 * dt))
    return result, Trajectories(t=tc, x=torch.from_numpy(coarse[:, :C]),
                                xhat=torch.from_numpy(coarse[:, C:]), v=torch.from_numpy(vc))
