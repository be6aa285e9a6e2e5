"""Worst-case-like measurement noise: chosen from the states, within ||v||_2 <= vbar.

The random noise of `certify.simulate.integrate.bounded_noise` points anywhere; a bound on
the error must also hold against noise that points where it hurts. Along a run, with
e = x - xhat and the residual k(x, h(x)) ~ 0, the error obeys to first order

    e' = A e - B v,   A = Jf(xhat) + dk/dxhat,   B = dk/dy   (at xhat, y = h(x)).

Two policies, both piecewise constant over holds of a few integration steps:

- "adjoint" (the default, `SwitchingNoise`): the linearisation frozen at the start of a
  window of length Tw (a few decay times of A), the noise over the window is the one that
  maximises c^T e(t0 + Tw) for that linear system: v(s) = -vbar B^T Phi^T c /
  ||B^T Phi^T c|| with Phi = e^(A (Tw - s)) (time-reversed impulse response; with one
  output, bang-bang +-vbar switching as the sign of c^T e^(A (Tw - s)) B changes), where the
  unit direction c is the one among +-e(t0)/||e(t0)|| and +-the coordinate axes whose
  predicted c^T e(t0 + Tw) is largest. Window after window the error is pushed to a peak of
  about vbar times the L1 norm of the noise-to-error impulse response: the largest peak any
  noise within vbar gives the frozen linear system.
- "greedy": the noise that increases V = e^T P e fastest right now,
  v = -vbar (dk/dy)^T P e / ||(dk/dy)^T P e||. With a large output injection this one
  chatters: it drives e onto the surface e^T P dk/dy = 0 (a sliding mode), where the error
  is small; it is kept as a comparison, not as the worst case.

Where a direction is undefined (e = 0, dk/dy = 0, a non-finite state or matrix) the
previous one is kept (a seeded random one at the start), so the signal is a function of the
states and the seed alone; where the adjoint policy finds no usable plan it keeps it for a
few holds before it tries again.

Contract: every value has ||v||_2 <= vbar exactly in float64 (the scaling's rounding is
clipped, and it is asserted). The feedback only chooses the signal; a run under it is
compared with the bound like any other.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from certify.model.gain import GainSpec, gain_at_points
from certify.model.network import GainNetwork
from certify.spec.system import System

__all__ = ["POLICIES", "SwitchingNoise", "clip_to_ball"]

POLICIES = ("adjoint", "greedy")
#: the adjoint window lasts this many decay times 1/min(-Re eig A) of the linearisation
WINDOW_DECAYS = 4.0
#: and at least this many holds
MIN_WINDOW_HOLDS = 8


#: rows at the full size vbar are scaled to vbar (1 - BALL_MARGIN): norms computed by
#: another library (another summation order) may differ by a few ulps, never by 1e-14
BALL_MARGIN = 1e-14


def clip_to_ball(v: np.ndarray, vbar: float) -> np.ndarray:
    """v [..., p] with every row of 2-norm > vbar (1 - BALL_MARGIN) scaled to that size, so
    that its norm stays <= vbar however it is computed; asserts the result is inside."""
    cap = vbar * (1.0 - BALL_MARGIN)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(norm > cap, v * (cap / norm), v)
    norm = np.linalg.norm(v, axis=-1)
    assert np.all(norm <= vbar), f"noise of norm {float(norm.max())!r} > vbar = {vbar!r}"
    return v


def _cpu_spec(net: GainNetwork) -> GainSpec:
    """The gain's description in float64 on the CPU (the simulation runs there)."""
    s = net.spec(torch.float64, detach=True)

    def cpu(t: torch.Tensor) -> torch.Tensor:
        return t.to("cpu")
    return GainSpec(s.n, s.p, tuple((cpu(W), cpu(b)) for W, b in s.layers), s.activation,
                    s.structure, cpu(s.K))


def _unit(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of g [m, p] normalised, and which rows had a usable (finite, nonzero) norm."""
    norm = np.linalg.norm(g, axis=-1, keepdims=True)
    good = np.isfinite(norm[..., 0]) & (norm[..., 0] > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(good[..., None], g / np.where(good[..., None], norm, 1.0), 0.0), good


def _transition_transposed(A: np.ndarray, times: np.ndarray) -> np.ndarray:
    """e^(A^T s) for each s in times [J] -> [J, n, n]: by the eigendecomposition of A^T
    when it is well conditioned, else by repeated products of expm over the (equal) spacing
    of `times` (descending by a constant step, as the plans use them)."""
    from scipy.linalg import expm

    w, V = np.linalg.eig(A.T)
    if np.linalg.cond(V) < 1e8:
        phis = np.einsum("ik,jk,kl->jil", V, np.exp(np.outer(times, w)), np.linalg.inv(V))
        return np.ascontiguousarray(phis.real)
    J, n = len(times), A.shape[0]
    phis = np.empty((J, n, n))
    cur = expm(A.T * times[-1])
    step = expm(A.T * (times[-2] - times[-1])) if J > 1 else cur
    for j in range(J - 1, -1, -1):
        phis[j] = cur
        cur = step @ cur
    return phis


class SwitchingNoise:
    """The worst-case-like noise of the module docstring for the runs `rows` of a batch.

    The integrator (`certify.simulate.integrate.simulate_doubled`) calls the object at step
    index k (a multiple of hold; hold even, >= 2) with those rows' plant and observer
    states [m, n] at t_k = k dt, and gets v [H, m, p] for the next H holds of `hold` steps
    each (as far as every row's plan reaches; the greedy policy: one hold); it calls again
    at step k + H hold.
    Deterministic: the same states and seed give the same values. `switches` counts, per
    row, the holds at which the direction changed.
    """

    def __init__(self, system: System, net: GainNetwork, P: np.ndarray, vbar: float,
                 rows: list[int], *, dt: float, hold: int = 2, seed: int = 0,
                 policy: str = "adjoint", max_window: float | None = None) -> None:
        if hold < 2 or hold % 2:
            raise ValueError(f"hold must be an even number of steps >= 2; got {hold}")
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}; got {policy!r}")
        self.system = system
        self.spec = _cpu_spec(net)
        self.P = np.asarray(P, dtype=np.float64)
        self.vbar = float(vbar)
        self.rows = list(rows)
        self.hold = int(hold)
        self.dt = float(dt)
        self.policy = policy
        self.max_window = max_window
        m, p = len(self.rows), system.p
        u = np.random.default_rng(int(seed)).standard_normal((m, p))
        self._last = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        self.switches = np.zeros(m, dtype=np.int64)
        # the adjoint plans: per row, the step its window began and its directions per hold
        self._plan_start = np.full(m, -1, dtype=np.int64)
        self._plans = np.zeros((m, 0, p))  # [m, longest plan, p]; zero rows: keep the last
        self._plan_len = np.zeros(m, dtype=np.int64)

    # ----- the linearisation ---------------------------------------------------------------
    def linearisation(self, x: np.ndarray, xhat: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A [m, n, n], B [m, n, p], e [m, n]) at plant states x and observer states xhat."""
        n = self.system.n
        xt, xht = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(
            np.ascontiguousarray(xhat))
        with torch.no_grad():
            y = self.system.h(xt)
            g = gain_at_points(self.spec, self.system, xht, y, with_dy=True, with_k=False)
            A = (self.system.jac_f(xht) + g.dk_dx).numpy()
        B = g.dk_dy.numpy().reshape(x.shape[0], n, self.system.p)
        return A, B, x - xhat

    # ----- the two policies ----------------------------------------------------------------
    def greedy(self, x: np.ndarray, xhat: np.ndarray) -> np.ndarray:
        """-(dk/dy)^T P e normalised [m, p] (the previous direction where undefined)."""
        u = self._last.copy()
        ok = np.isfinite(x).all(1) & np.isfinite(xhat).all(1)
        if ok.any():
            _, B, e = self.linearisation(x[ok], xhat[ok])
            g, good = _unit(-np.einsum("mip,mi->mp", B, e @ self.P.T))
            idx = np.flatnonzero(ok)[good]
            u[idx] = g[good]
        return u

    def plan(self, A: np.ndarray, B: np.ndarray, e: np.ndarray) -> np.ndarray | None:
        """The adjoint plan for one run: directions [J, p] for the J holds of its window
        (zero rows: no direction helps there, e.g. dk/dy = 0, where the noise does not
        reach the error to first order; None when the linearisation is not usable:
        non-finite, or not decaying)."""
        if not (np.isfinite(A).all() and np.isfinite(B).all() and np.isfinite(e).all()):
            return None
        decay = -float(np.max(np.linalg.eigvals(A).real))
        h = self.hold * self.dt
        if not decay > 0:
            return None
        window = WINDOW_DECAYS / decay
        if self.max_window is not None:
            window = min(window, self.max_window)
        J = max(MIN_WINDOW_HOLDS, int(math.ceil(window / h)))
        if J > 100_000:
            return None
        if not B.any():  # the noise does not reach the error over this window: keep the last
            return np.zeros((J, B.shape[1]))
        # Phi^T at the hold midpoints' times-to-go (J - j - 1/2) h, j = 0 .. J-1
        phis = _transition_transposed(A, (np.arange(J)[::-1] + 0.5) * h)  # [J, n, n]
        free = _transition_transposed(A, np.array([J * h]))[0].T @ e  # e^(A T) e
        n = A.shape[0]
        cands = list(np.eye(n))
        ne = float(np.linalg.norm(e))
        if ne > 0:
            cands.append(e / ne)
        C = np.array(cands + [-c for c in cands])  # [m_c, n]
        g = np.einsum("ip,jik,ck->cjp", B, phis, C)  # B^T Phi_j^T c  [m_c, J, p]
        score = C @ free + self.vbar * h * np.linalg.norm(g, axis=2).sum(axis=1)
        if not np.isfinite(score).any():
            return None
        u, good = _unit(-g[int(np.nanargmax(score))])
        return u if good.any() else None

    def adjoint(self, k: int, x: np.ndarray, xhat: np.ndarray, holds: int
                ) -> np.ndarray:
        """The directions [m, H, p] of each row's plan for the next H <= `holds` holds: as
        many as every row's current plan still covers. A row whose plan is over (or that
        has none) first gets a new one from its current states. Where no plan is usable
        (`plan` returns None) the previous direction is kept for `MIN_WINDOW_HOLDS` holds
        before the next try, so a row without one costs a plan every few holds, not every
        hold. A zero row of a plan keeps the previous direction."""
        m = len(self.rows)
        idx = (k - self._plan_start) // self.hold  # the hold of each row's plan
        due = (self._plan_start < 0) | (idx >= self._plan_len)
        ok = np.isfinite(x).all(1) & np.isfinite(xhat).all(1)
        todo = np.flatnonzero(due & ok)
        if todo.size:
            A, B, e = self.linearisation(x[todo], xhat[todo])
            for i, r in enumerate(todo):
                pl = self.plan(A[i], B[i], e[i])
                self._store(int(r), np.zeros((MIN_WINDOW_HOLDS, self.system.p))
                            if pl is None else pl)
                self._plan_start[r] = k
            idx = (k - self._plan_start) // self.hold
        live = (idx >= 0) & (idx < self._plan_len)  # not live: non-finite states, kept
        if not live.any():
            return np.repeat(self._last[:, None], holds, axis=1)
        H = max(1, min(holds, int((self._plan_len - idx)[live].min())))
        width = self._plans.shape[1]
        seq = self._plans[np.arange(m)[:, None],
                          np.clip(idx[:, None] + np.arange(H), 0, width - 1)]  # [m, H, p]
        usable = live[:, None] & seq.any(axis=2)  # [m, H]
        # each hold takes the latest usable direction at or before it, else the last one
        at = np.maximum.accumulate(np.where(usable, np.arange(H), -1), axis=1)
        picked = np.take_along_axis(seq, np.maximum(at, 0)[..., None], axis=1)
        return np.where((at >= 0)[..., None], picked, self._last[:, None])

    def _store(self, r: int, plan: np.ndarray) -> None:
        """Row r's plan [J, p] into the padded array of plans (grown when J is longer)."""
        J = len(plan)
        if J > self._plans.shape[1]:
            grown = np.zeros((self._plans.shape[0], J, self._plans.shape[2]))
            grown[:, : self._plans.shape[1]] = self._plans
            self._plans = grown
        self._plans[r, :J] = plan
        self._plans[r, J:] = 0.0
        self._plan_len[r] = J

    def __call__(self, k: int, x: np.ndarray, xhat: np.ndarray, holds: int = 1
                 ) -> np.ndarray:
        """The noise [H, m, p] of the rows for the next H holds from step k (1 <= H <=
        `holds`; the greedy policy: H = 1), from their plant and observer states [m, n]."""
        x = np.asarray(x, dtype=np.float64)
        xhat = np.asarray(xhat, dtype=np.float64)
        if self.policy == "adjoint":
            u = self.adjoint(k, x, xhat, max(int(holds), 1))
        else:
            u = self.greedy(x, xhat)[:, None]
        steps = np.concatenate([self._last[:, None], u], axis=1)
        self.switches += (steps[:, 1:] != steps[:, :-1]).any(axis=2).sum(axis=1)
        self._last = u[:, -1]
        return clip_to_ball(self.vbar * u.transpose(1, 0, 2), self.vbar)
