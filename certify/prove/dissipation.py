"""The joint dissipation certificate: V' <= -alpha V + mu ||v||^2 (+ mu_r ||P^(1/2) r||^2).

With e = x - xhat, measured output y_e = h(x) + v and the observer
xhat' = f(xhat) + k(xhat, y_e), the mean-value theorem gives e' = A e - B v - r with
A = int_0^1 (Jf + dk/dxhat)(xhat + s e, h(x)) ds (y held at h(x): a point of X x Y while x
and xhat are in the convex box X and h(x) in Y), B = int_0^1 dk/dy(xhat, h(x) + s v) ds
(a point of the closed convex hull of dk/dy over X x Y while h(x) + v stays in Y) and
r = k(x, h(x)) (0 for a structural gain; ||P^(1/2) r|| <= eps_bar_P otherwise). A and B
average at *different* points, so the inequality must hold for A and B independently:

  V' - (-alpha V + mu ||v||^2 + mu_r ||s||^2) = [e; v; s]^T M [e; v; s] <= 0, where
  s = P^(1/2) r and
  M = [[2 He{P A} + alpha P, -P B, -P^(1/2)], [-B^T P, -mu I, 0], [-P^(1/2), 0, -mu_r I]],

and by the Schur complement M <= 0 iff D(alpha/4) + P B B^T P / (2 mu) + P / (2 mu_r) <= 0
with D(lam) = He{P (Jf + dk/dxhat)} + 2 lam P (the MPDI's matrix). It is affine in A, so it
suffices at every point (xhat, y) of X x Y (the MPDI prover's job) and, being affine in B
before the Schur step, at the vertices b of a polytope containing dk/dy(X x Y); where the
enclosure is not a small polytope it is covered by a ball ||B - b_c||_2 <= delta around one
centre, handled by Young's inequality: 2 |e^T P (B - b_c) v| <= delta^2 ||P e||^2 / eta +
eta ||v||^2, i.e. the constant term delta^2 P^2 / (2 eta) and eta added to mu.

Each piece is proved by `prove_mpdi` on the problem with that constant term (`Problem.shift`,
rounded upward in the PSD order by `upper_shift`) at lam = alpha / 4; alpha and mu are chosen
from samples (the closed form mu >= (P b)^T (-D_eff)^-1 (P b) / 2 at each point) and then
decided by the prover, raising mu when a proof fails. Consequence, while the conditions hold:
V(t) <= e^(-alpha t) V(0) + (1 - e^(-alpha t)) (mu vbar^2 + mu_r eps_bar_P^2) / alpha.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.arith.golden import golden_section
from certify.arith.intervals import gamma
from certify.arith.text import lower_text, upper_text
from certify.enclose.network_interval import gain_enclosure
from certify.model.kernels import contraction_matrix, gain_terms
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status

__all__ = ["Cover", "DissipationOutcome", "dk_dy_cover", "prove_dissipation", "upper_shift"]

_F64 = torch.float64
#: at most this many vertices of the polytope covering dk/dy (one MPDI proof each); above,
#: a centre and a ball
MAX_VERTICES = 16
#: directions of the outer polygon when dk/dy has two entries
POLYGON_SIDES = 8
#: a ball cover (one proof) is used when its sampled bound is within this factor of the
#: polytope's (one proof per vertex)
BALL_ALLOWANCE = 1.03
#: the attempts, in turn: (room, growth): the slowest sampled rate whose bound is within
#: `room` of the best one, with its sampled mu times `growth` (the bound grows like sqrt(mu))
SCHEDULE = ((1.0, 1.02), (1.02, 1.05), (1.05, 1.1), (1.1, 1.5))
#: rates alpha sampled (geometric, up to 4x the fastest sampled rate), then golden-section
#: steps around the best
ALPHA_GRID = 24
ALPHA_REFINE = 14
#: an enclosure narrower than this relative to its centre is a point up to rounding: one
#: centre and a ball (one proof) rather than a polytope
NARROW = 1e-6
TINY_SCALE = 1e-9


@dataclass(frozen=True)
class Cover:
    """A set containing dk/dy(X x Y): conv(vertices) + {||Delta||_2 <= delta}.

    vertices [V, n, p] float64; delta >= 0 (0 for a polytope)."""

    vertices: np.ndarray
    delta: float


@dataclass
class DissipationOutcome:
    """The result of `prove_dissipation` (`status` PROVED when every piece is proved)."""

    status: Status
    message: str
    alpha: float | None = None
    mu: float | None = None  # the total noise gain: mu_b + eta
    mu_residual: float | None = None
    vertices: int = 0
    delta: float = 0.0
    candidates: list[dict] = field(default_factory=list)
    boxes: int = 0
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


def _samples(problem: Problem, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    s = problem.system
    box = np.concatenate([s.X, s.Y], 0).astype(np.float64)
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(count, box.shape[0], generator=gen, dtype=_F64)
    z = torch.as_tensor(box[:, 0]) + u * torch.as_tensor(box[:, 1] - box[:, 0])
    corners = torch.as_tensor(np.array(np.meshgrid(*box, indexing="ij")).reshape(
        box.shape[0], -1).T, dtype=_F64)
    z = torch.cat([z, corners], 0)
    return z[:, :s.n], z[:, s.n:]


def _mu_needed(D: np.ndarray, PB: np.ndarray) -> np.ndarray:
    """max over points of (P b)^T (-D)^-1 (P b) / 2 per vertex: D [S, n, n], PB [V, n, p]
    -> [V] (inf where some -D is not positive definite). For p > 1 the spectral form
    lam_max(B^T P (-D)^-1 P B) / 2."""
    negD = -D
    try:
        L = np.linalg.cholesky(negD)  # [S, n, n]
    except np.linalg.LinAlgError:
        return np.full(PB.shape[0], np.inf)
    out = []
    for V in PB:
        Z = np.linalg.solve(L, np.broadcast_to(V, (L.shape[0],) + V.shape))  # L^-1 P b
        G = np.einsum("sij,sik->sjk", Z, Z)
        out.append(float(np.linalg.eigvalsh(G)[:, -1].max()) / 2.0)
    return np.array(out)


def _plan(problem: Problem, cover: Cover, eps_P: float, vbar: float, samples: int, seed: int
          ) -> list[dict]:
    """Candidate (alpha, mu_b, eta, mu_r) ranked by their sampled bound (smallest first)."""
    P = np.asarray(problem.P, dtype=np.float64)
    s = problem.system
    xhat, y = _samples(problem, samples, seed)
    terms = gain_terms(s, problem.on("cpu").network, xhat, y, with_dy=False)
    Jcl = s.jac_f(xhat) + terms.dk_dx
    D0 = contraction_matrix(Jcl, torch.zeros_like(Jcl), torch.as_tensor(P), 0.0).numpy()
    if not np.all(np.isfinite(D0)):
        return []
    P2 = P @ P
    PB = np.einsum("ij,vjk->vik", P, cover.vertices)
    # D(lam) = D0 + 2 lam P; the fastest sampled rate: lam_max of the pencil (D0, -P) < 0
    Linv = np.linalg.inv(np.linalg.cholesky(P))
    pencil = np.linalg.eigvalsh(Linv @ D0 @ Linv.T)[:, -1].max()
    lam_s = -pencil / 2.0
    if not lam_s > 0:
        return []
    nP2 = float(np.linalg.norm(P2, 2))
    nP = float(np.linalg.norm(P, 2))

    def at(alpha: float) -> dict | None:
        """The best (mu_b, eta, mu_r) at this alpha and its sampled bound (None: none)."""
        D = D0 + 0.5 * alpha * P  # 2 (alpha / 4) P
        margin = float(np.linalg.eigvalsh(D)[:, -1].max())  # < 0 where alpha is feasible
        if not margin < 0:
            return None
        fracs_r = (0.02,) if not problem.structural else (0.0,)
        fracs_b = (0.0,) if cover.delta == 0 else (1e-6, 1e-3, 0.05, 0.2, 0.5)
        best = None
        for frac_r in fracs_r:
            for frac_b in fracs_b:
                # each extra term takes a fraction of the margin: its P^2 term <= frac |margin|
                eta = cover.delta ** 2 * nP2 / (2 * frac_b * -margin) if frac_b else 0.0
                mu_r = nP / (2 * frac_r * -margin) if frac_r else 0.0
                Deff = D.copy()
                if eta:
                    Deff = Deff + cover.delta ** 2 * P2 / (2 * eta)
                if mu_r:
                    Deff = Deff + P / (2 * mu_r)
                mu_b = float(_mu_needed(Deff, PB).max())
                if not math.isfinite(mu_b):
                    continue
                num = (mu_b + eta) * vbar ** 2 + mu_r * eps_P ** 2
                bound = math.sqrt(num / alpha)
                if best is None or bound < best["bound"]:
                    best = dict(alpha=float(alpha), mu_b=mu_b, eta=eta, mu_r=mu_r, bound=bound)
        return best

    grid = 4.0 * lam_s * np.geomspace(0.02, 0.98, ALPHA_GRID)
    out = [c for c in (at(float(a)) for a in grid) if c is not None]
    if out:  # golden-section refinement in log alpha between the best point's neighbours
        k = int(np.argmin([c["bound"] for c in out]))
        i = int(np.searchsorted(grid, out[k]["alpha"]))
        lo, hi = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, len(grid) - 1)])

        def value(u: float) -> float:
            c = at(math.exp(u))
            if c is not None:
                out.append(c)
            return c["bound"] if c is not None else math.inf
        golden_section(value, lo, hi, ALPHA_REFINE)
    return sorted(out, key=lambda c: c["bound"])


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


def prove_dissipation(problem: Problem, *, vbar: float, eps_P: float = 0.0,
                      max_boxes: int, deadline: float | None = None, samples: int = 4096,
                      seed: int = 0) -> DissipationOutcome:
    """Find and prove (alpha, mu, mu_r) minimising sqrt((mu vbar^2 + mu_r eps_P^2) / alpha)
    (see the module docstring). `eps_P`: a sound bound of sup ||P^(1/2) k(x, h(x))|| (0 for
    a structural gain). PROVED when every piece of the cover is proved for one candidate;
    UNKNOWN otherwise (the budget of `max_boxes` boxes over all proofs spent, the run's
    wall-clock cap `deadline` passed, or no candidate at the samples)."""
    if not problem.structural and not math.isfinite(eps_P):
        return DissipationOutcome(Status.UNKNOWN, "no sound bound of the residual (eps_bar_P)")
    host = problem.on("cpu")  # the cover and the samples on the CPU, the proofs where asked
    cover = dk_dy_cover(host)
    if cover is None:
        return DissipationOutcome(Status.UNKNOWN, "dk/dy has no finite enclosure on X x Y")
    try:
        plan = _plan(host, cover, eps_P, vbar, samples, seed)
    except np.linalg.LinAlgError:
        plan = []
    if len(cover.vertices) > 1:  # one proof (an ellipsoid or a ball) if nearly as good
        for one in (ellipsoid_cover(cover), dk_dy_cover(host, ball=True)):
            if one is None:
                continue
            try:
                plan_1 = _plan(host, one, eps_P, vbar, samples, seed)
            except np.linalg.LinAlgError:
                continue
            if plan_1 and (not plan or plan_1[0]["bound"] <= BALL_ALLOWANCE * plan[0]["bound"]):
                cover, plan = one, plan_1
                break
    if not plan:
        return DissipationOutcome(Status.UNKNOWN, "no rate alpha > 0 with a finite noise gain "
                                  "at the sampled points (D is not negative definite there)",
                                  vertices=len(cover.vertices), delta=cover.delta)
    P = np.asarray(problem.P, dtype=np.float64)
    tried: list[dict] = []
    boxes = 0
    capped = False
    for attempt, (room, grow) in enumerate(SCHEDULE):
        # each attempt gets an equal share of the boxes left; after a failed one (a point
        # where the shifted D is not negative definite, or out of boxes) the next gives the
        # prover more room: the slowest rate whose sampled bound is within `room` of the best
        # (the MPDI at alpha/4 keeps more margin everywhere), and a larger mu
        budget = (max_boxes - boxes) // (len(SCHEDULE) - attempt)
        if budget <= 0 or capped:
            break
        cand = min((c for c in plan if c["bound"] <= room * plan[0]["bound"]),
                   key=lambda c: c["alpha"])
        mu_b = cand["mu_b"] * grow
        shifts = _shifts(P, cover, mu_b, cand["eta"], cand["mu_r"])
        status = Status.PROVED
        left = budget
        # every piece must be proved for the candidate to hold, so each proof may take all
        # the attempt has left (one that is not proved ends the attempt whatever the rest
        # would do; a proved one stops early)
        for Q in shifts:
            if left <= 0:
                status = Status.UNKNOWN
                break
            sub = Problem(system=problem.system, network=problem.network, lam=problem.lam,
                          P=problem.P, device=problem.device, shift=Q)
            out = prove_mpdi(sub, lam=cand["alpha"] / 4.0, max_boxes=left, deadline=deadline,
                             task="dissipation proof")
            boxes += out.stats.boxes_processed
            left -= out.stats.boxes_processed
            capped = capped or out.stats.stopped_by_cap
            if out.status != Status.PROVED:
                status = out.status
                break
        mu = mu_b + cand["eta"]
        bound = math.sqrt((mu * vbar ** 2 + cand["mu_r"] * eps_P ** 2) / cand["alpha"])
        tried.append(dict(alpha=cand["alpha"], mu=mu, bound=bound, status=status.value))
        if status == Status.PROVED:
            return DissipationOutcome(
                Status.PROVED, f"V' <= -{lower_text(cand['alpha'], 4)} V + "
                f"{upper_text(mu, 4)} ||v||^2"
                + (f" + {upper_text(cand['mu_r'], 4)} ||P^(1/2) r||^2" if cand["mu_r"] else "")
                + f" proved over X x Y ({len(shifts)} piece(s) covering dk/dy)",
                alpha=cand["alpha"], mu=mu, mu_residual=cand["mu_r"] or None,
                vertices=len(cover.vertices), delta=cover.delta, candidates=tried,
                boxes=boxes)
    within = "before the wall-clock cap" if capped else f"within {max_boxes:,} boxes"
    return DissipationOutcome(Status.UNKNOWN, f"no candidate (alpha, mu) proved {within}",
                              vertices=len(cover.vertices), delta=cover.delta,
                              candidates=tried, boxes=boxes, stopped_by_cap=capped)
