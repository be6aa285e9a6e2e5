"""Where the simulation check starts its runs: where the bound's conditions can hold a while.

A run is compared with the proved bound only while its validity conditions hold (METHOD
§3.7 (a)-(d)); a run that leaves X within a few milliseconds compares nothing. The
checkable form of "xhat stays in X" says where to start: if the plant state x(s) stays in a
set K and the P-ellipsoid {z : ||P^(1/2)(z - x)|| <= max(W(0), c/(2 lam))} lies inside X
for every x in K, the observer state stays in X too. So:

1. candidate plant states are drawn uniformly in X (with h(x0) in Y), and the plant alone,
   x' = f(x), is integrated over the horizon (one batched RK4 on a coarse grid): its window
   is how long x stays in X and h(x) in Y (Y shrunk by vbar when L is a local bound, so that
   y = h(x) + v stays in Y too), and its room is the smallest P-ellipsoid radius that fits
   in X around x(s) over that window;
2. candidates are drawn again around the best ones, closer each round (`REFINE_ROUNDS`:
   the plant may stay long only near a small set, e.g. close to an unstable equilibrium);
   the best are kept: the longest windows, then the most room, spread apart; or, when runs
   must stay valid a given time (`need_time`, five time constants of the bound), those
   whose window reaches it, then the most room over it, only kept distinct;
3. each initial error e(0) = x(0) - xhat(0) has W(0) = ||P^(1/2) e(0)|| = half the room, in a
   seeded random direction: small enough that xhat(0) is in X, and, when the bound's radius
   c/(2 lam) also fits in the room, the checkable form holds over the whole window.

The screening only chooses where to start; every run is then integrated at the check's own
step and its exits found exactly as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.errors import SpecError
from certify.simulate.integrate import simulate_plant
from certify.spec.system import System

#: steps of the plant-only screening integration (over the whole horizon)
SCREEN_STEPS = 400
#: candidate plant states drawn per run kept
CANDIDATES_PER_RUN = 64
#: W(0) as a fraction of the room around the start
ERROR_FRACTION = 0.5
#: rounds of sampling again around the best candidates (the plant may stay long only near
#: a small set, e.g. close to an unstable equilibrium), each with this many points per
#: start kept, spread by REFINE_SPREAD of the box's width times REFINE_SHRINK per round
REFINE_ROUNDS = 3
REFINE_PER_START = 16
REFINE_SPREAD = 0.05
REFINE_SHRINK = 0.2
#: the starts kept are this far apart (a fraction of the box's width in each coordinate);
#: when runs must stay valid a given time, the few places where the plant stays that long
#: may be small, so the starts are only kept distinct (SPREAD_NEEDED)
SPREAD = 0.05
SPREAD_NEEDED = 0.002


@dataclass
class InitialConditions:
    """Labels, initial states x0 and xhat0 [R, n], and how each start was chosen."""

    labels: list[str]
    x0: torch.Tensor
    xhat0: torch.Tensor
    notes: list[str] = field(default_factory=list)


def source_initial_condition(system: System) -> tuple[list[float], list[float]] | None:
    """The source's x0 and xhat0 from the spec's [simulation] table (None if absent)."""
    sim = system.simulation or {}
    if "x0" not in sim:
        return None
    try:
        x0 = [float(v) for v in sim["x0"]]
        xhat0 = [float(v) for v in sim.get("xhat0", [0.0] * system.n)]
    except (TypeError, ValueError):
        raise SpecError(f"system {system.name}: [simulation] x0/xhat0 must be lists of "
                        "numbers") from None
    if len(x0) != system.n or len(xhat0) != system.n:
        raise SpecError(f"system {system.name}: [simulation] x0 and xhat0 need {system.n} "
                        "entries each")
    if not all(math.isfinite(v) for v in x0 + xhat0):
        raise SpecError(f"system {system.name}: [simulation] x0/xhat0 must be finite")
    return x0, xhat0


def ellipsoid_room(X: np.ndarray, P: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Largest r with {z : ||P^(1/2)(z - x)|| <= r} inside the box X, for x [..., n] -> [...].

    The ellipsoid's half-width along coordinate i is r sqrt((P^-1)_ii); negative outside X.
    """
    half = np.sqrt(np.diag(np.linalg.inv(P)))
    gap = np.minimum(x - X[:, 0], X[:, 1] - x)
    return np.min(gap / half, axis=-1)


def plant_windows(system: System, P: np.ndarray, x0: torch.Tensor, *, horizon: float,
                  y_margin: float, need: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(window [M], room [M]) of the plant alone from x0 [M, n] over `horizon` (coarse RK4).

    window: time until x leaves X or h(x) leaves Y shrunk by `y_margin` (the horizon if never);
    room: the smallest `ellipsoid_room` of x(s) over that window, or over its first `need`
    seconds when given (0 if it starts outside).
    """
    steps = SCREEN_STEPS
    traj = simulate_plant(system, x0, dt=horizon / steps, steps=steps)  # [T, M, n]
    T, M, n = traj.shape
    X = np.asarray(system.X, dtype=np.float64)
    Y = np.asarray(system.Y, dtype=np.float64)
    if np.all(Y[:, 1] - Y[:, 0] > 2 * y_margin):
        Y = Y + np.array([y_margin, -y_margin])
    x = traj.numpy()
    hx = system.h(traj.reshape(T * M, n)).reshape(T, M, -1).numpy()
    with np.errstate(invalid="ignore"):
        inside = (((x >= X[:, 0]) & (x <= X[:, 1])).all(-1)
                  & ((hx >= Y[:, 0]) & (hx <= Y[:, 1])).all(-1))  # NaN -> outside
    first = np.where(inside.all(0), T, np.argmin(inside, axis=0))
    window = np.minimum(first, T - 1) * (horizon / steps)
    window[first >= T] = horizon
    room = np.where(np.isfinite(x).all(-1), ellipsoid_room(X, P, np.nan_to_num(x)), -np.inf)
    last = first if need is None else np.minimum(first, math.ceil(need / horizon * steps) + 1)
    mask = np.arange(T)[:, None] < np.maximum(last, 1)[None, :]
    room = np.where(mask, room, np.inf).min(axis=0)
    return window, np.maximum(room, 0.0)


def choose_starts(system: System, P: np.ndarray, count: int, seed: int, *, horizon: float,
                  vbar: float, L_is_local: bool, radius: float | None,
                  need_time: float | None = None) -> InitialConditions:
    """The source's (x0, xhat0) when the spec has one, then `count` - 1 chosen starts.

    `radius`: the bound's ultimate radius c/(2 lam) in the P-norm (None: no bound).
    `need_time`: how long (s) a run should stay valid (None: as long as possible); the
    starts whose plant stays `need_time` seconds are preferred, then the most room over
    those seconds. See the module docstring for the rule; the notes say, per run, its plant
    window and room and whether the checkable form of "xhat stays in X" holds.
    """
    labels: list[str] = []
    x0s: list[torch.Tensor] = []
    xh0s: list[torch.Tensor] = []
    notes: list[str] = []
    src = source_initial_condition(system)
    if src is not None:
        labels.append("source x0")
        x0s.append(torch.tensor([src[0]], dtype=torch.float64))
        xh0s.append(torch.tensor([src[1]], dtype=torch.float64))
        notes.append("the spec's [simulation] x0 and xhat0")
    need = count - len(labels)
    if need > 0:
        P = np.asarray(P, dtype=np.float64)
        gen = torch.Generator().manual_seed(int(seed) + 1)
        X = torch.as_tensor(system.X, dtype=torch.float64)
        Y = torch.as_tensor(system.Y, dtype=torch.float64)
        lo, width = X[:, 0], X[:, 1] - X[:, 0]
        cand = lo + width * torch.rand(CANDIDATES_PER_RUN * need, system.n, generator=gen,
                                       dtype=torch.float64)
        hy = system.h(cand)
        ok = ((hy >= Y[:, 0]) & (hy <= Y[:, 1])).all(dim=1)
        if int(ok.sum()) >= need:  # h(X) barely meets Y: keep unfiltered points
            cand = cand[ok]
        y_margin = vbar if L_is_local else 0.0
        need_s = None if need_time is None else min(float(need_time), horizon)
        window, room = plant_windows(system, P, cand, horizon=horizon, y_margin=y_margin,
                                     need=need_s)
        for r in range(REFINE_ROUNDS):  # sample again around the best, closer each round
            order = _rank(window, room, need_s)
            top = cand[torch.as_tensor(order[:need].copy())]
            scale = width * REFINE_SPREAD * REFINE_SHRINK ** r
            more = top.repeat_interleave(REFINE_PER_START, dim=0)
            more = more + scale * torch.randn(more.shape, generator=gen, dtype=torch.float64)
            more = torch.minimum(torch.maximum(more, X[:, 0]), X[:, 1])
            hy = system.h(more)
            more = more[((hy >= Y[:, 0]) & (hy <= Y[:, 1])).all(dim=1)]
            if len(more) == 0:
                break
            w2, r2 = plant_windows(system, P, more, horizon=horizon, y_margin=y_margin,
                                   need=need_s)
            cand = torch.cat([cand, more])
            window, room = np.concatenate([window, w2]), np.concatenate([room, r2])
        order = _rank(window, room, need_s)
        picked = _spread(cand.numpy()[order], (width.numpy()), need,
                         apart=SPREAD if need_s is None else SPREAD_NEEDED)
        idx = order[picked]
        W0 = ERROR_FRACTION * room[idx]
        u = torch.randn(len(idx), system.n, generator=gen, dtype=torch.float64).numpy()
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        # e0 = P^(-1/2) u W0, so that ||P^(1/2) e0|| = W0
        evals, evecs = np.linalg.eigh((P + P.T) / 2)
        P_inv_half = evecs @ np.diag(1.0 / np.sqrt(evals)) @ evecs.T
        e0 = (u @ P_inv_half.T) * W0[:, None]
        x0 = cand.numpy()[idx]
        xhat0 = np.clip(x0 - e0, system.X[:, 0], system.X[:, 1])
        x0s.append(torch.as_tensor(x0))
        xh0s.append(torch.as_tensor(xhat0))
        for i, j in enumerate(idx):
            labels.append(f"start {i + 1}")
            held = ("for the whole horizon" if window[j] >= horizon
                    else f"for {window[j]:.3g} s")
            form = ("" if radius is None else
                    "; the checkable form of 'xhat stays in X' holds while x does"
                    if radius <= room[j] else
                    f"; the checkable form cannot hold (c/(2 lam) = {radius:.3g} > room)")
            notes.append(f"the plant alone stays in the conditions {held}; room "
                         f"{room[j]:.3g} (P-norm); W(0) = {W0[i]:.3g}{form}")
    return InitialConditions(labels=labels, x0=torch.cat(x0s), xhat0=torch.cat(xh0s),
                             notes=notes)


def initial_conditions(system: System, count: int, seed: int, *, P: np.ndarray | None = None,
                       horizon: float = 10.0, vbar: float = 0.0, L_is_local: bool = False,
                       radius: float | None = None, need_time: float | None = None
                       ) -> InitialConditions:
    """`choose_starts` with the identity metric when P is not given."""
    P = np.eye(system.n) if P is None else np.asarray(P, dtype=np.float64)
    return choose_starts(system, P, count, seed, horizon=horizon, vbar=vbar,
                         L_is_local=L_is_local, radius=radius, need_time=need_time)


def _rank(window: np.ndarray, room: np.ndarray, need: float | None) -> np.ndarray:
    """Candidate indices, best first: without `need`, the longest window first, then the
    most room; with it, those whose window reaches `need` first, then the most room (over
    the first `need` seconds), then the longest window."""
    if need is None:
        return np.lexsort((-room, -window))
    long = window >= need * (1 - 1e-9)
    return np.lexsort((-window, -room, ~long))


def _spread(ranked: np.ndarray, width: np.ndarray, k: int, apart: float = 0.05
            ) -> np.ndarray:
    """Indices of `k` ranked points [M, n], best first: each pick removes the points within
    `apart` of the box of it (filled up from the rest, in rank order, when too few are
    apart)."""
    scaled = ranked / np.where(width > 0, width, 1.0)
    free = np.ones(len(ranked), dtype=bool)
    kept: list[int] = []
    for _ in range(min(k, len(ranked))):  # k picks, each vectorised over the candidates
        if not free.any():
            break
        i = int(np.argmax(free))  # the best remaining (ranked order)
        kept.append(i)
        free &= np.max(np.abs(scaled - scaled[i]), axis=1) > apart
    rest = np.ones(len(ranked), dtype=bool)
    rest[kept] = False  # the others, in rank order (np.setdiff1d would import numpy.ma)
    return np.concatenate([np.array(kept, dtype=np.int64), np.flatnonzero(rest)])[:k]
