"""Dissipation certificates: V' <= -alpha V + mu ||v||^2 (+ mu_r ||P^(1/2) r||^2), V = e^T P e.

Notation: x' = f(x), y = h(x), measured output y + v, observer xhat' = f(xhat) + k(xhat, y + v),
e = x - xhat, F(z, w) = f(z) + k(z, w), J_F = Jf + dk/dxhat, B = dk/dy, r = k(x, h(x)) the
boundary-condition residual (0 for a structural gain; ||P^(1/2) r|| <= eps_bar_P otherwise).

**The path certificate (one proof).** Join x to xhat by the segment z(s) = x - s e and the
output y to y + v by w(s) = y + s v, s in [0, 1]. Since x' = F(x, y) - r,

    e' = F(x, y) - F(xhat, y + v) - r = int_0^1 [J_F(z(s), w(s)) e - B(z(s), w(s)) v] ds - r,

with J_F and B at the *same* point (z(s), w(s)) of X x Y while x, xhat in X (a convex box) and
y, y + v in Y. Hence with s_r = P^(1/2) r,

    V' + alpha V - mu |v|^2 - mu_r |s_r|^2 = int_0^1 [e; -v; -s_r]^T N(z(s), w(s)) [...] ds,
    N = [[2 He{P J_F} + alpha P, P B, P^(1/2)], [B^T P, -mu I, 0], [P^(1/2), 0, -mu_r I]],

so N <= 0 at every point of X x Y gives the inequality. After the Schur complement of the
residual block (mu_r > 0), N <= 0 is twice the matrix D~ of a problem with a noise input
(`certify.model.problem.NoiseInput`, at lam = alpha/4, with the constant term
Q = P / (2 mu_r) rounded up in the PSD order by `upper_shift`): one MPDI-form proof of an
(n + p)-square matrix over X x Y by the same prover (`prove_mpdi`), no cover of dk/dy.

**The cover certificate (the fallback).** The older argument averages J_F and B at different
points (e' = A e - B v - r with A, B integrals along different segments), so the inequality
must hold for A and B independently: by the Schur complement M <= 0 iff
D(alpha/4) + P B B^T P / (2 mu) + P / (2 mu_r) <= 0, affine in A (every point of X x Y) and,
before the Schur step, affine in B (the vertices b of a polytope containing dk/dy(X x Y), or a
ball ||B - b_c|| <= delta handled by Young's inequality: the constant term delta^2 P^2 /
(2 eta) and eta added to mu). One MPDI proof per vertex with a constant shift. It implies the
path certificate for the same (alpha, mu) (B(z, w) lies in the hull), so it can only prove a
smaller bound where the path proof fails within its budget; it runs only then.

**Choosing alpha and mu.** At sampled points (xhat, y) the smallest mu for a rate alpha is
max lam_max(b^T P (-D_eff)^-1 P b) / 2 with D_eff = D(alpha/4) (+ residual and ball terms),
b = B at the same point (path) or each vertex at every point (cover); alpha is scanned
(geometric grid, then golden-section steps) to minimise the bound
sqrt((mu vbar^2 + mu_r eps_bar_P^2) / alpha), and the prover decides a slightly larger mu.
A path attempt that the prover refutes (a point where N is not negative semidefinite) adds
that point to the samples and plans again; one that spends its share of the box budget
gives the next attempt more room (a slower rate whose sampled bound is within a few percent,
a larger mu). The budget counts boxes (`max_boxes`, all attempts and pieces together), so the
outcome does not depend on the machine's speed; an optional `deadline` (a
`time.perf_counter()` value) caps the wall clock. A candidate that does not prove is never
reported. Consequence, while the conditions hold (x, xhat in X, y and y + v in Y):
V(t) <= e^(-alpha t) V(0) + (1 - e^(-alpha t)) (mu vbar^2 + mu_r eps_bar_P^2) / alpha.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.arith.golden import golden_section
from certify.arith.intervals import gamma
from certify.arith.text import lower_text, upper_text
from certify.enclose.network_interval import gain_enclosure
from certify.model.kernels import contraction_matrix, gain_terms
from certify.model.problem import NoiseInput, Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.settings import DEFAULTS

__all__ = ["Cover", "DissipationOutcome", "dk_dy_cover", "prove_dissipation", "upper_shift",
           "DEFAULT_BOXES"]

_F64 = torch.float64
#: the box budget of all attempts together when the caller gives none (`dissipation_boxes`)
DEFAULT_BOXES = DEFAULTS.dissipation_boxes
#: at most this many vertices of the polytope covering dk/dy (one MPDI proof each); above,
#: a centre and a ball
MAX_VERTICES = 16
#: directions of the outer polygon when dk/dy has two entries
POLYGON_SIDES = 8
#: a one-proof cover (ellipsoid, ball) is used when its sampled bound is within this factor
#: of the polytope's (one proof per vertex)
BALL_ALLOWANCE = 1.03
#: the attempts, in turn: (room, growth, share): the slowest sampled rate whose bound is
#: within `room` of the best one, with its sampled mu times `growth` (the bound grows like
#: sqrt(mu)), given `share` of the box budget left. The first aims at the sampled optimum on
#: a small share (most proofs close there at once); if it does not prove, the others go from
#: loose (cheap to prove, a bound for sure) to tight, each only while it aims below the best
#: proved so far, and a failed one ends the search (a tighter one would fail too)
SCHEDULE = ((1.0, 1.02, 1 / 8), (1.1, 1.5, 1 / 4), (1.05, 1.1, 1 / 3), (1.02, 1.05, 1 / 2),
            (1.0, 1.02, 1.0))
#: a refuted attempt (a point where the inequality fails) plans again with that point, at most
#: this many times per attempt
REPLANS = 3
#: before each plan, projected ascent from this many of the worst samples, this many steps
#: (on the noise gain each point needs, and on the largest eigenvalue of D(alpha/4))
SHARPEN_STARTS = 8
SHARPEN_STEPS = 30
#: rates alpha sampled (geometric, up to 4x the fastest sampled rate), then golden-section
#: steps around the best
ALPHA_GRID = 24
ALPHA_REFINE = 14
#: an enclosure narrower than this relative to its centre is a point up to rounding: one
#: centre and a ball (one proof) rather than a polytope
NARROW = 1e-6
TINY_SCALE = 1e-9
#: the share of the residual block in the margin of -D (direct gains)
RESIDUAL_SHARE = 0.02


@dataclass(frozen=True)
class Cover:
    """A set containing dk/dy(X x Y): conv(vertices) + {||Delta||_2 <= delta}.

    vertices [V, n, p] float64; delta >= 0 (0 for a polytope)."""

    vertices: np.ndarray
    delta: float


@dataclass
class DissipationOutcome:
    """The result of `prove_dissipation` (`status` PROVED when a candidate is proved).

    `route`: "path" (one proof, dk/dy at the same point) or "cover" (one proof per piece of
    a cover of dk/dy); `vertices` the pieces proved (1 for the path)."""

    status: Status
    message: str
    alpha: float | None = None
    mu: float | None = None  # the total noise gain: mu_b + eta
    mu_residual: float | None = None
    vertices: int = 0
    delta: float = 0.0
    candidates: list[dict] = field(default_factory=list)
    boxes: int = 0
    route: str = ""
    stopped_by_cap: bool = False  # a proof was stopped by the run's wall-clock cap


def _sub_boxes(lo: np.ndarray, hi: np.ndarray, total: int) -> tuple[torch.Tensor, torch.Tensor]:
    d = lo.shape[0]
    k = max(1, int(total ** (1.0 / d)))
    edges = [np.linspace(lo[i], hi[i], k + 1) for i in range(d)]
    edges = [np.concatenate([[lo[i]], e[1:-1], [hi[i]]]) for i, e in enumerate(edges)]
    idx = np.stack(np.meshgrid(*[np.arange(k)] * d, indexing="ij"), -1).reshape(-1, d)
    blo = np.stack([edges[i][idx[:, i]] for i in range(d)], 1)
    bhi = np.stack([edges[i][idx[:, i] + 1] for i in range(d)], 1)
    return torch.as_tensor(blo, dtype=_F64), torch.as_tensor(bhi, dtype=_F64)


def dk_dy_cover(problem: Problem, boxes: int = 4096, ball: bool = False) -> Cover | None:
    """A `Cover` of dk/dy over X x Y from interval enclosures on `boxes` sub-boxes (their
    union contains the image; the cover contains the union): a point when every enclosure
    is one point (a linear gain), an interval (n p = 1), an outer polygon of `POLYGON_SIDES`
    support lines (n p = 2), a box in the principal axes (n p <= 4); else a centre and a
    ball (also when `ball` is true). Support values and coordinates are widened by a
    relative 1e-9 (far above the float errors of the projections). None when an enclosure
    is not finite."""
    s = problem.system
    box = np.concatenate([s.X, s.Y], 0).astype(np.float64)
    lo, hi = _sub_boxes(box[:, 0], box[:, 1], boxes)
    g, _ = gain_enclosure(s, problem.on("cpu").network, lo, hi)
    blo, bhi = g.dk_dy.lo.numpy(), g.dk_dy.hi.numpy()  # [B, n, p]
    if not (np.all(np.isfinite(blo)) and np.all(np.isfinite(bhi))):
        return None
    n, p = blo.shape[1], blo.shape[2]
    d = n * p
    lo2, hi2 = blo.reshape(-1, d), bhi.reshape(-1, d)
    if np.array_equal(lo2.min(0), hi2.max(0)):  # one point
        return Cover(lo2[:1].reshape(1, n, p).copy(), 0.0)
    centred = _ball(lo2, hi2)
    if ball:
        return Cover(centred.vertices.reshape(1, n, p), centred.delta)
    if centred.delta <= NARROW * max(float(np.linalg.norm(centred.vertices)), TINY_SCALE):
        return Cover(centred.vertices.reshape(1, n, p), centred.delta)  # a point, rounded
    # every corner of every enclosure box
    signs = np.array(np.meshgrid(*[[0, 1]] * d, indexing="ij")).reshape(d, -1).T  # [2^d, d]
    if d <= 4:
        pts = np.where(signs[None, :, :] == 0, lo2[:, None, :], hi2[:, None, :]).reshape(-1, d)
    else:
        pts = np.concatenate([lo2, hi2], 0)
    scale = float(np.abs(pts).max()) or 1.0
    widen = 1e-9 * scale
    if d == 1:
        verts = np.array([[pts.min() - widen], [pts.max() + widen]])
        return Cover(verts.reshape(-1, n, p), 0.0)
    c = 0.5 * (pts.min(0) + pts.max(0))
    if d == 2:
        _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
        base = math.atan2(vt[0, 1], vt[0, 0])
        ang = base + 2 * math.pi * np.arange(POLYGON_SIDES) / POLYGON_SIDES
        U = np.stack([np.cos(ang), np.sin(ang)], 1)  # [m, 2]
        h = ((pts - c) @ U.T).max(0) + widen  # support values around c
        verts = []
        for i in range(POLYGON_SIDES):
            j = (i + 1) % POLYGON_SIDES
            verts.append(c + np.linalg.solve(U[[i, j]], h[[i, j]]))
        return Cover(np.array(verts).reshape(-1, n, p), 0.0)
    if 2 ** d <= MAX_VERTICES:
        _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
        t = (pts - c) @ vt.T
        tlo, thi = t.min(0) - widen, t.max(0) + widen
        corners = np.where(signs == 0, tlo, thi)  # [2^d, d]
        # vt is orthonormal up to rounding: x - c = vt^T t exactly in reals would need
        # vt^-1; the widening covers the difference (|vt^T vt - I| ~ 1e-16)
        verts = c + corners @ vt
        return Cover(verts.reshape(-1, n, p), 0.0)
    return Cover(centred.vertices.reshape(1, n, p), centred.delta)


def ellipsoid_cover(cover: Cover) -> Cover | None:
    """One "vertex" L [n, n] with L L^T >= b b^T for every vertex b [n, 1] of `cover` (so for
    every point of its hull: {b : ||L^-1 b|| <= 1} is convex), from the origin-centred
    minimum-volume ellipsoid through the vertices (Khachiyan's iteration), scaled so that
    max ||L^-1 b|| <= 1 / (1 + 1e-8) (the solve errs by ~1e-15 relative): one proof with the
    constant term P L L^T P / (2 mu) instead of one per vertex. None for p > 1, a ball cover,
    or vertices that do not span R^n."""
    V = cover.vertices
    if cover.delta > 0 or V.shape[2] != 1 or len(V) < 2:
        return None
    pts = V[:, :, 0]
    m, n = pts.shape
    if np.linalg.matrix_rank(pts) < n:
        return None
    try:
        return _mvee(pts)
    except np.linalg.LinAlgError:  # numerically degenerate vertices: no ellipsoid
        return None


def _mvee(pts: np.ndarray) -> Cover:
    m, n = pts.shape
    u = np.full(m, 1.0 / m)
    for _ in range(500):
        M = (pts.T * u) @ pts
        g = np.einsum("ij,jk,ik->i", pts, np.linalg.inv(M), pts)
        j = int(np.argmax(g))
        if g[j] <= n * (1 + 1e-4):
            break
        step = (g[j] / n - 1.0) / (g[j] - 1.0)
        u *= 1.0 - step
        u[j] += step
    L = np.linalg.cholesky(n * (pts.T * u) @ pts)
    reach = float(np.linalg.norm(np.linalg.solve(L, pts.T), axis=0).max())
    return Cover((L * (reach * (1 + 1e-8)))[None], 0.0)


def _ball(lo: np.ndarray, hi: np.ndarray) -> Cover:
    """The centre c of the boxes' bounding box [lo, hi] ([B, d] each) and delta >= every
    ||B - c||_F over the boxes (>= the spectral norm of B - c as a matrix)."""
    c = 0.5 * (lo.min(0) + hi.max(0))
    corner = np.maximum(np.abs(lo - c), np.abs(hi - c))
    delta = float(np.sqrt((corner ** 2).sum(1)).max()) * (1 + 1e-9)
    return Cover(c[None], delta + 1e-300)


def upper_shift(Q: np.ndarray, magnitude: np.ndarray, n_ops: int) -> np.ndarray:
    """fl(Q) + t I, an upper bound of Q in the PSD order: Q was computed in float64 by at
    most `n_ops` roundings per entry from terms whose magnitudes sum to `magnitude`
    (elementwise), so |fl(Q) - Q| <= gamma_{n_ops} magnitude and its spectral norm is at most
    t = gamma_{n_ops} ||magnitude||_F (doubled for the symmetrisation)."""
    t = 2.0 * gamma(n_ops) * float(np.sqrt((magnitude ** 2).sum()))
    return 0.5 * (Q + Q.T) + (t + 1e-300) * np.eye(Q.shape[0])


def _samples(problem: Problem, count: int, seed: int) -> torch.Tensor:
    """`count` uniform points of X x Y and its corners, [S, n + p] float64."""
    s = problem.system
    box = np.concatenate([s.X, s.Y], 0).astype(np.float64)
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(count, box.shape[0], generator=gen, dtype=_F64)
    z = torch.as_tensor(box[:, 0]) + u * torch.as_tensor(box[:, 1] - box[:, 0])
    corners = torch.as_tensor(np.array(np.meshgrid(*box, indexing="ij")).reshape(
        box.shape[0], -1).T, dtype=_F64)
    return torch.cat([z, corners], 0)


@dataclass
class _Samples:
    """Points z [S, n + p] with He{P J_F} [S, n, n] and P dk/dy [S, n, p] there (numpy)."""

    z: torch.Tensor
    D0: np.ndarray
    PB: np.ndarray

    @classmethod
    def at(cls, problem: Problem, z: torch.Tensor) -> _Samples:
        n = problem.n
        xhat, y = z[:, :n], z[:, n:]
        terms = gain_terms(problem.system, problem.network, xhat, y, with_dy=True)
        P = torch.as_tensor(problem.P, dtype=_F64)
        D0 = contraction_matrix(problem.system.jac_f(xhat), terms.dk_dx, P, 0.0).numpy()
        return cls(z, D0, (P @ terms.dk_dy).numpy())

    def add(self, problem: Problem, z: torch.Tensor) -> _Samples:
        more = _Samples.at(problem, z)
        return _Samples(torch.cat([self.z, more.z]), np.concatenate([self.D0, more.D0]),
                        np.concatenate([self.PB, more.PB]))


def _mu_needed(D: np.ndarray, PB: np.ndarray) -> np.ndarray:
    """max over points of lam_max(b^T P (-D)^-1 P b) / 2 per vertex: D [S, n, n], PB
    [V, S or 1, n, p] (P b at each point, or one b for every point) -> [V] (inf where some
    -D is not positive definite)."""
    try:
        L = np.linalg.cholesky(-D)  # [S, n, n]
    except np.linalg.LinAlgError:
        return np.full(PB.shape[0], np.inf)
    out = []
    for V in PB:
        Z = np.linalg.solve(L, np.broadcast_to(V, (L.shape[0],) + V.shape[1:]))  # L^-1 P b
        G = np.einsum("sij,sik->sjk", Z, Z)
        out.append(float(np.linalg.eigvalsh(G)[:, -1].max()) / 2.0)
    return np.array(out)


def _bound(mu: float, mu_r: float, alpha: float, vbar: float, eps_P: float) -> float:
    """sqrt((mu vbar^2 + mu_r eps_P^2) / alpha) without overflowing the squares (inf only
    where the bound itself exceeds the float range)."""
    return math.hypot(math.sqrt(mu / alpha) * vbar, math.sqrt(mu_r / alpha) * eps_P)


def _rank(mu: float, mu_r: float, alpha: float, vbar: float, eps_P: float) -> float:
    """The bound divided by the larger of vbar and eps_P (1 where both are 0): the same order
    as `_bound`, finite whenever mu, mu_r and alpha are, however large the noise."""
    s = max(vbar, eps_P) or 1.0
    return math.hypot(math.sqrt(mu / alpha) * (vbar / s), math.sqrt(mu_r / alpha) * (eps_P / s))


def _plan(problem: Problem, samples: _Samples, PB: np.ndarray, delta: float, eps_P: float,
          vbar: float) -> list[dict]:
    """Candidate (alpha, mu_b, eta, mu_r) ranked by their sampled bound (smallest first):
    PB [V, S or 1, n, p] (`_mu_needed`), delta the ball radius of a cover (0: none)."""
    P = np.asarray(problem.P, dtype=np.float64)
    D0 = samples.D0
    if not (np.all(np.isfinite(D0)) and np.all(np.isfinite(PB))):
        return []
    P2 = P @ P
    # D(lam) = D0 + 2 lam P; the fastest sampled rate: lam_max of the pencil (D0, -P) < 0
    Linv = np.linalg.inv(np.linalg.cholesky(P))
    pencil = np.linalg.eigvalsh(Linv @ D0 @ Linv.T)[:, -1].max()
    lam_s = -pencil / 2.0
    if not lam_s > 0:
        return []
    nP2 = float(np.linalg.norm(P2, 2))
    nP = float(np.linalg.norm(P, 2))
    # a ball of rounding size around a point: its share of the margin can be the smallest
    tiny_ball = NARROW * max(float(np.abs(PB).max()) / max(nP, TINY_SCALE), TINY_SCALE)

    def at(alpha: float) -> dict | None:
        """The best (mu_b, eta, mu_r) at this alpha and its sampled bound (None: none)."""
        D = D0 + 0.5 * alpha * P  # 2 (alpha / 4) P
        margin = float(np.linalg.eigvalsh(D)[:, -1].max())  # < 0 where alpha is feasible
        if not margin < 0:
            return None
        fracs_r = (RESIDUAL_SHARE,) if not problem.structural else (0.0,)
        fracs_b = ((0.0,) if delta == 0 else (1e-6,) if delta <= tiny_ball
                   else (1e-6, 1e-3, 0.05, 0.2, 0.5))
        best = None
        for frac_r in fracs_r:
            for frac_b in fracs_b:
                # each extra term takes a fraction of the margin: its P^2 term <= frac |margin|
                eta = delta ** 2 * nP2 / (2 * frac_b * -margin) if frac_b else 0.0
                mu_r = nP / (2 * frac_r * -margin) if frac_r else 0.0
                Deff = D.copy()
                if eta:
                    Deff = Deff + delta ** 2 * P2 / (2 * eta)
                if mu_r:
                    Deff = Deff + P / (2 * mu_r)
                mu_b = float(_mu_needed(Deff, PB).max())
                if not math.isfinite(mu_b):
                    continue
                rank = _rank(mu_b + eta, mu_r, alpha, vbar, eps_P)
                if not math.isfinite(rank):
                    continue
                if best is None or rank < best["rank"]:
                    best = dict(alpha=float(alpha), mu_b=mu_b, eta=eta, mu_r=mu_r, rank=rank,
                                bound=_bound(mu_b + eta, mu_r, alpha, vbar, eps_P))
        return best

    grid = 4.0 * lam_s * np.geomspace(0.02, 0.98, ALPHA_GRID)
    out = [c for c in (at(float(a)) for a in grid) if c is not None]
    if out:  # golden-section refinement in log alpha between the best point's neighbours
        k = int(np.argmin([c["rank"] for c in out]))
        i = int(np.searchsorted(grid, out[k]["alpha"]))
        lo, hi = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, len(grid) - 1)])

        def value(u: float) -> float:
            c = at(math.exp(u))
            if c is not None:
                out.append(c)
            return c["rank"] if c is not None else math.inf
        golden_section(value, lo, hi, ALPHA_REFINE)
    return sorted(out, key=lambda c: (c["rank"], c["alpha"]))


def _residual_shift(P: np.ndarray, mu_r: float) -> np.ndarray | None:
    """P / (2 mu_r) rounded upward in the PSD order (None without a residual block)."""
    if not mu_r:
        return None
    return upper_shift(P / (2.0 * mu_r), np.abs(P) / (2.0 * mu_r), 4)


def _shifts(P: np.ndarray, cover: Cover, mu_b: float, eta: float, mu_r: float
            ) -> list[np.ndarray]:
    """The constant terms P b b^T P / (2 mu_b) + delta^2 P^2 / (2 eta) + P / (2 mu_r), one
    per vertex b of the cover, each rounded upward (`upper_shift`)."""
    n = P.shape[0]
    A = np.abs(P)
    P2, A2 = P @ P, A @ A
    out = []
    for b in cover.vertices:
        Pb, Ab = P @ b, A @ np.abs(b)
        if mu_b > 0:
            Q = Pb @ Pb.T / (2.0 * mu_b)
            mag = Ab @ Ab.T / (2.0 * mu_b)
        elif not np.any(b):  # dk/dy = 0: the noise does not enter, mu = 0 is exact
            Q, mag = np.zeros_like(P), np.zeros_like(P)
        else:
            raise ValueError("mu = 0 with a nonzero dk/dy")
        if eta:
            Q = Q + cover.delta ** 2 * P2 / (2.0 * eta)
            mag = mag + cover.delta ** 2 * A2 / (2.0 * eta)
        if mu_r:  # the residual enters as s = P^(1/2) r, ||s|| <= eps_bar_P
            Q = Q + P / (2.0 * mu_r)
            mag = mag + A / (2.0 * mu_r)
        out.append(upper_shift(Q, mag, 2 * n + b.shape[1] + 8))
    return out


def _needed_mu(host: Problem, alpha: float, mu_r: float, fn: str):
    """At points z [N, n + p] (torch, differentiable): the noise gain the path inequality
    needs there at rate alpha, lam_max(B^T P (-D)^-1 P B) / 2 (NaN where -D is not positive
    definite), or (fn "margin") lam_max(D), D = D(alpha/4) (+ P / (2 mu_r))."""
    P = torch.as_tensor(host.P, dtype=_F64)
    n = host.n

    def value(z: torch.Tensor) -> torch.Tensor:
        xhat, y = z[:, :n], z[:, n:]
        terms = gain_terms(host.system, host.network, xhat, y, with_dy=True)
        D = contraction_matrix(host.system.jac_f(xhat), terms.dk_dx, P, alpha / 4.0)
        if mu_r:
            D = D + P / (2.0 * mu_r)
        if fn == "margin":
            return torch.linalg.eigvalsh(D)[:, -1]
        L, info = torch.linalg.cholesky_ex(-D)
        ok = info == 0
        L = torch.where(ok[:, None, None], L, torch.eye(n, dtype=_F64).expand_as(L))
        Z = torch.linalg.solve_triangular(L, P @ terms.dk_dy, upper=False)
        mu = torch.linalg.eigvalsh(Z.transpose(1, 2) @ Z)[:, -1] / 2.0
        return torch.where(ok, mu, torch.full_like(mu, float("nan")))

    return value


def _sharpen(host: Problem, samples: _Samples, cand: dict) -> _Samples:
    """`samples` with the points projected ascent reaches from the worst ones for `cand`'s
    rate: where the noise gain needed is largest, and where D(alpha/4) is least negative (a
    sampled plan that misses them is refuted by the prover, at the price of a proof)."""
    from certify.search.falsify import projected_ascent

    s = host.system
    box = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=_F64)
    lo, hi = box[:, 0], box[:, 1]
    found = []
    for fn in ("mu", "margin"):
        f = _needed_mu(host, cand["alpha"], cand["mu_r"], fn)
        with torch.no_grad():
            v = torch.nan_to_num(f(samples.z), nan=math.inf)
        starts = samples.z[torch.argsort(v, descending=True)[:SHARPEN_STARTS]]
        best, _ = projected_ascent(f, starts, lo, hi, SHARPEN_STEPS)
        found.append(best)
    return samples.add(host, torch.cat(found))


def _proved(route: str, cand: dict, mu: float, pieces: int, delta: float
            ) -> DissipationOutcome:
    how = ("by the path certificate (one proof, dk/dy at the same point as the contraction)"
           if route == "path" else f"by a cover of dk/dy ({pieces} piece(s), one proof each)")
    return DissipationOutcome(
        Status.PROVED, f"V' <= -{lower_text(cand['alpha'], 4)} V + {upper_text(mu, 4)} "
        "||v||^2" + (f" + {upper_text(cand['mu_r'], 4)} ||P^(1/2) r||^2" if cand["mu_r"] else "")
        + f" proved over X x Y {how}",
        alpha=cand["alpha"], mu=mu, mu_residual=cand["mu_r"] or None, vertices=pieces,
        delta=delta, route=route)


def _pick(plan: list[dict], room: float) -> dict:
    """The slowest candidate whose sampled bound is within `room` of the best."""
    return min((c for c in plan if c["rank"] <= room * plan[0]["rank"]),
               key=lambda c: c["alpha"])


class _Budget:
    """The box budget of all attempts and the optional wall-clock deadline (whether a proof
    was stopped by it: `capped`)."""

    def __init__(self, boxes: int, deadline: float | None) -> None:
        self.start = self.left = int(boxes)
        self.deadline = deadline
        self.capped = False

    def seconds(self) -> float:
        """Wall-clock seconds left (inf without a deadline)."""
        if self.deadline is None:
            return math.inf
        return max(0.0, self.deadline - time.perf_counter())

    def expired(self) -> bool:
        return self.left <= 0 or self.seconds() <= 0

    def share(self, fraction: float) -> int:
        return max(1, int(self.left * fraction))

    def spend(self, boxes: int) -> None:
        self.left -= int(boxes)

    @property
    def spent(self) -> int:
        return self.start - self.left


@dataclass
class _Route:
    """One certificate: how it plans (`plan(samples)`: candidates, best first) and proves a
    candidate at a noise gain within a box budget (`prove(cand, mu_b, boxes)` -> status,
    boxes used, a refuting point or None), its name and pieces."""

    name: str
    plan: Callable[[_Samples], list[dict]]
    prove: Callable[[dict, float, int], tuple[Status, int, torch.Tensor | None]]
    pieces: int = 1
    delta: float = 0.0


def _attempts(route: _Route, host: Problem, samples: _Samples, eps_P: float, vbar: float,
              budget: _Budget, tried: list[dict], below: float = math.inf
              ) -> tuple[DissipationOutcome | None, bool]:
    """Run `SCHEDULE` on `route` (module docstring), only with candidates whose sampled bound
    ranks below `below` (`_rank`). Returns the best proved outcome (None: none) and whether
    it was proved by the first attempt, as planned."""
    best: DissipationOutcome | None = None
    first = True
    for step, (room, grow, share) in enumerate(SCHEDULE):
        if budget.expired() or (step == 0) != first:
            break
        boxes = budget.share(share)
        for _ in range(REPLANS + 1):
            plan = route.plan(samples)
            if plan:
                samples = _sharpen(host, samples, plan[0])
                plan = route.plan(samples)
            plan = [c for c in plan if c["rank"] < below]
            if not plan:
                return best, False
            cand = _pick(plan, room)
            mu_b = cand["mu_b"] * grow
            mu = mu_b + cand["eta"]
            aim = _bound(mu, cand["mu_r"], cand["alpha"], vbar, eps_P)
            rank = _rank(mu, cand["mu_r"], cand["alpha"], vbar, eps_P)
            if best is not None and rank >= best.candidates[-1]["rank"]:
                break
            status, used, refuted = route.prove(cand, mu_b, min(boxes, budget.left))
            budget.spend(used)
            boxes -= used
            tried.append(dict(route=route.name, alpha=cand["alpha"], mu=mu, bound=aim,
                              rank=rank, status=status.value))
            if status == Status.PROVED:
                best = _proved(route.name, cand, mu, route.pieces, route.delta)
                best.candidates = [tried[-1]]
                if step == 0:
                    return best, True
                break
            if status != Status.VIOLATED or refuted is None or boxes <= 0:
                if step > 0:  # a looser attempt failed: a tighter one would fail too
                    return best, False
                break
            samples = samples.add(host, refuted)  # plan again with the refuting point
        first = False
    return best, False


def _path_route(problem: Problem, host: Problem, eps_P: float, vbar: float,
                budget: _Budget) -> _Route:
    """The path certificate: one proof of the noise-input problem per candidate."""
    P = np.asarray(problem.P, dtype=np.float64)

    def prove(cand: dict, mu: float, boxes: int):
        if not mu > 0:  # dk/dy = 0 at every sample: only the cover can tell it is 0
            return Status.UNKNOWN, 0, None
        sub = Problem(system=problem.system, network=problem.network,
                      lam=cand["alpha"] / 4.0, P=problem.P, device=problem.device,
                      shift=_residual_shift(P, cand["mu_r"]),
                      noise=NoiseInput(alpha=cand["alpha"], mu=mu, scale=0.5 * mu))
        out = prove_mpdi(sub, max_boxes=boxes, deadline=budget.deadline, estimate_points=0,
                         task="dissipation proof")
        budget.capped = budget.capped or out.stats.stopped_by_cap
        cex = out.counterexample
        point = None if cex is None else torch.as_tensor([cex.xhat + cex.y], dtype=_F64)
        return out.status, out.stats.boxes_processed, point

    return _Route("path", lambda smp: _plan(host, smp, smp.PB[None], 0.0, eps_P, vbar), prove)


def _cover_route(problem: Problem, host: Problem, samples: _Samples, eps_P: float,
                 vbar: float, budget: _Budget, constant: bool) -> _Route | None:
    """The cover certificate: one proof per piece of a cover of dk/dy (None: no finite
    enclosure). Where one proof (an ellipsoid, a ball) plans nearly as well as the
    polytope's vertices, that one. `constant`: dk/dy is constant by construction (one
    enclosure over the whole box is a point up to rounding)."""
    cover = dk_dy_cover(host, boxes=1 if constant else 4096)
    if cover is None:
        return None
    P = np.asarray(problem.P, dtype=np.float64)

    def plan_of(c: Cover, smp: _Samples) -> list[dict]:
        try:
            PB = np.einsum("ij,vjk->vik", P, c.vertices)[:, None]
            return _plan(host, smp, PB, c.delta, eps_P, vbar)
        except np.linalg.LinAlgError:
            return []

    if len(cover.vertices) > 1:
        plan = plan_of(cover, samples)
        for one in (ellipsoid_cover(cover), dk_dy_cover(host, ball=True)):
            if one is None:
                continue
            plan_1 = plan_of(one, samples)
            if plan_1 and (not plan or plan_1[0]["rank"] <= BALL_ALLOWANCE * plan[0]["rank"]):
                cover = one
                break

    def prove(cand: dict, mu_b: float, boxes: int):
        # every piece must be proved for the candidate to hold, so each proof may use all the
        # attempt has left (one that is not proved ends the attempt)
        used = 0
        for Q in _shifts(P, cover, mu_b, cand["eta"], cand["mu_r"]):
            if boxes - used <= 0 or budget.seconds() <= 0:
                return Status.UNKNOWN, used, None
            sub = Problem(system=problem.system, network=problem.network, lam=problem.lam,
                          P=problem.P, device=problem.device, shift=Q)
            out = prove_mpdi(sub, lam=cand["alpha"] / 4.0, max_boxes=boxes - used,
                             deadline=budget.deadline, estimate_points=0,
                             task="dissipation proof")
            budget.capped = budget.capped or out.stats.stopped_by_cap
            used += out.stats.boxes_processed
            if out.status != Status.PROVED:
                cex = out.counterexample
                point = None if cex is None else torch.as_tensor([cex.xhat + cex.y],
                                                                 dtype=_F64)
                return out.status, used, point
        return Status.PROVED, used, None

    return _Route("cover", lambda smp: plan_of(cover, smp), prove,
                  pieces=len(cover.vertices), delta=cover.delta)


def _constant_dk_dy(problem: Problem) -> bool:
    """Whether dk/dy is constant by construction (the network's output layer is zero: a
    linear gain), where the two certificates are one inequality and the cover's n x n proof
    is the cheaper."""
    return not bool(torch.any(problem.network.layers[-1].weight != 0))


def prove_dissipation(problem: Problem, *, vbar: float, eps_P: float = 0.0,
                      max_boxes: int = DEFAULT_BOXES, deadline: float | None = None,
                      samples: int = 4096, seed: int = 0, route: str = "auto"
                      ) -> DissipationOutcome:
    """Find and prove (alpha, mu, mu_r) minimising sqrt((mu vbar^2 + mu_r eps_P^2) / alpha)
    (module docstring): the path certificate first; the cover certificate where dk/dy is
    constant by construction (the same inequality, a smaller matrix), and where the path
    attempts did not prove as planned (only its candidates that aim lower). `eps_P`: a sound
    bound of sup ||P^(1/2) k(x, h(x))|| (0 for a structural gain). `max_boxes`: the prover's
    box budget for all attempts; `deadline`: an optional `time.perf_counter()` cap. `route`
    "path" or "cover" runs that certificate alone (comparisons). PROVED when a candidate is
    proved; UNKNOWN otherwise."""
    if route not in ("auto", "path", "cover"):
        raise ValueError(f"route must be 'auto', 'path' or 'cover', not {route!r}")
    if not problem.structural and not math.isfinite(eps_P):
        return DissipationOutcome(Status.UNKNOWN, "no sound bound of the residual (eps_bar_P)")
    if not math.isfinite(vbar) or vbar < 0:
        return DissipationOutcome(Status.UNKNOWN, f"the noise bound {vbar!r} is not a finite "
                                  "number >= 0")
    host = problem.on("cpu")  # the samples and the cover on the CPU, the proofs where asked
    budget = _Budget(max_boxes, deadline)
    pts = _Samples.at(host, _samples(host, samples, seed))
    tried: list[dict] = []
    best, as_planned = None, False
    constant = _constant_dk_dy(problem)
    if route == "path" or (route == "auto" and not constant):
        best, as_planned = _attempts(_path_route(problem, host, eps_P, vbar, budget), host,
                                     pts, eps_P, vbar, budget, tried)
    if route == "cover" or (route == "auto" and not as_planned):
        cover = _cover_route(problem, host, pts, eps_P, vbar, budget, constant)
        if cover is not None:
            below = math.inf if best is None else best.candidates[-1]["rank"]
            best = _attempts(cover, host, pts, eps_P, vbar, budget, tried, below)[0] or best
    if best is not None:
        best.candidates, best.boxes = tried, budget.spent
        best.stopped_by_cap = budget.capped
        return best
    why = ("no rate alpha > 0 with a finite noise gain at the sampled points (D is not "
           "negative definite there)" if not tried else "no candidate (alpha, mu) proved "
           f"within {max_boxes:,} boxes" + (" or the wall-clock cap" if deadline else ""))
    if budget.capped:
        why = "stopped by the wall-clock cap of the run; " + why
    return DissipationOutcome(Status.UNKNOWN, why, candidates=tried, boxes=budget.spent,
                              stopped_by_cap=budget.capped)
