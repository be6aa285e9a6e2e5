"""Designing a metric that follows the state: a polynomial M(x) (and a linear gain) for the
Riemannian path certificate of `certify.prove.metric`, by gridded semidefinite programs.

At points (x, w) of the domain (a grid or samples of the box, w on the tube around h(x)),
with the observer's F = f + k, J_F and B = dk/dw there, the certificate's inequality

    [[dM/dt + 2 He{M J_F} + alpha M, M B], [B^T M, -mu I]] <= 0,   dM/dt = sum_i dM/dx_i F_i,

is affine in the metric's coefficients M_k (M(x) = sum_k x^(a_k) M_k) and mu for a fixed gain
and rate (`metric_step`), and, for a fixed metric, affine in a linear gain K
(k = K (w - h(x)): J_F = Jf - K H, B = K, F = f + K (w - h)) and mu (`gain_step`). Both are
posed straight to Clarabel as cones of small PSD blocks (one per point: a few thousand
3 x 3 blocks solve in seconds, where a modelling layer spends minutes building them), the
normalisation M(x) >= I at the grid's states. `design_metric` scans alpha and alternates the
two steps. A design is a candidate only: the prover decides it (`certify.prove.metric`),
between the grid points too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.model.metric import PolyMetric, all_monomials, even_monomials
from certify.spec.system import System

_SQRT2 = math.sqrt(2.0)


def _svec_index(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and scales of Clarabel's PSD-triangle vectorisation of an m x m matrix
    (upper triangle by columns, off-diagonal entries times sqrt 2)."""
    r, c, s = [], [], []
    for j in range(m):
        for i in range(j + 1):
            r.append(i)
            c.append(j)
            s.append(1.0 if i == j else _SQRT2)
    return np.array(r), np.array(c), np.array(s)


def _sym_basis(n: int) -> np.ndarray:
    out = []
    for i in range(n):
        for j in range(i, n):
            E = np.zeros((n, n))
            E[i, j] = E[j, i] = 1.0
            out.append(E)
    return np.array(out)


def _solve_psd(C: np.ndarray, C0: np.ndarray, extra: list[tuple[np.ndarray, np.ndarray]],
               ) -> tuple[str, np.ndarray | None]:
    """min x[-1] subject to sum_v x_v C[:, v] + C0 <= 0 (blocks [N, d, d] each) and, for each
    (A [Q, nv, m, m], A0 [Q, m, m]) in `extra`, sum_v x_v A[:, v] + A0 >= 0."""
    import clarabel
    import scipy.sparse as sp

    N, nv, d, _ = C.shape
    ri, ci, sc = _svec_index(d)
    rows = [(C[:, :, ri, ci] * sc).transpose(0, 2, 1).reshape(N * len(ri), nv)]
    rhs = [-(C0[:, ri, ci] * sc).reshape(-1)]
    cones = [clarabel.PSDTriangleConeT(d)] * N
    for A, A0 in extra:
        Q, _, m, _ = A.shape
        rj, cj, sj = _svec_index(m)
        rows.append(-(A[:, :, rj, cj] * sj).transpose(0, 2, 1).reshape(Q * len(rj), nv))
        rhs.append((A0[:, rj, cj] * sj).reshape(-1))
        cones += [clarabel.PSDTriangleConeT(m)] * Q
    q = np.zeros(nv)
    q[-1] = 1.0
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(sp.csc_matrix((nv, nv)), q, sp.csc_matrix(np.vstack(rows)),
                                    np.concatenate(rhs), cones, settings)
    sol = solver.solve()
    status = str(sol.status)
    if status not in ("Solved", "AlmostSolved"):
        return status, None
    return status, np.array(sol.x)


@dataclass
class DesignPoints:
    """The points of a design, with the plant's terms there: x [N, n], w [N, p], f [N, n],
    Jf [N, n, n], H = dh/dx [N, p, n], r = w - h(x) [N, p]; `states` [Q, n] the grid's
    states (where M >= I)."""

    x: np.ndarray
    w: np.ndarray
    f: np.ndarray
    Jf: np.ndarray
    H: np.ndarray
    r: np.ndarray
    states: np.ndarray


def design_points(system: System, tau: float | None, *, per_axis: int | None = None,
                  offsets: int = 5, samples: int = 1500, seed: int = 0) -> DesignPoints:
    """A grid of the state box (n <= 3; else `samples` random states and the corners) and, per
    state, `offsets` outputs on the tube w = h(x) + t, |t| <= tau along each output (the whole
    Y without a tube, `offsets` per output axis)."""
    n, p = system.n, system.p
    X = np.asarray(system.X, dtype=np.float64)
    if n <= 3:
        k = per_axis or {1: 41, 2: 21, 3: 9}[n]
        axes = [np.linspace(X[i, 0], X[i, 1], k if i else k) for i in range(n)]
        states = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n)
    else:
        rng = np.random.default_rng(seed)
        corners = np.stack(np.meshgrid(*X, indexing="ij"), -1).reshape(-1, n)
        states = np.concatenate([X[:, 0] + rng.random((samples, n)) * (X[:, 1] - X[:, 0]),
                                 corners])
    xs = torch.as_tensor(states)
    h = system.h(xs).numpy()
    if tau is None:
        Y = np.asarray(system.Y, dtype=np.float64)
        ts = np.stack(np.meshgrid(*[np.linspace(Y[j, 0], Y[j, 1], offsets) for j in range(p)],
                                  indexing="ij"), -1).reshape(-1, p)
        w = np.repeat(np.zeros_like(h), len(ts), 0) + np.tile(ts, (len(h), 1))
    else:
        t = np.linspace(-tau, tau, offsets)
        ts = np.stack(np.meshgrid(*[t] * p, indexing="ij"), -1).reshape(-1, p)
        w = np.repeat(h, len(ts), 0) + np.tile(ts, (len(h), 1))
    x = np.repeat(states, len(ts), 0)
    xt = torch.as_tensor(x)
    return DesignPoints(x=x, w=w, f=system.f(xt).numpy(), Jf=system.jac_f(xt).numpy(),
                        H=system.jac_h(xt).numpy(), r=w - system.h(xt).numpy(), states=states)


def monomial_features(exponents: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x^(a_k) [N, K] and its gradient [N, K, n]."""
    N, n = x.shape
    phi = np.ones((N, len(exponents)))
    for i in range(n):
        phi = phi * x[:, i:i + 1] ** exponents[None, :, i]
    grad = np.zeros((N, len(exponents), n))
    for i in range(n):
        e = exponents.copy()
        coef = e[:, i].astype(np.float64)
        e[:, i] = np.maximum(e[:, i] - 1, 0)
        g = np.ones((N, len(e)))
        for j in range(n):
            g = g * x[:, j:j + 1] ** e[None, :, j]
        grad[:, :, i] = g * coef
    return phi, grad


def metric_step(pts: DesignPoints, exponents: np.ndarray, F: np.ndarray, J: np.ndarray,
                B: np.ndarray, alpha: float) -> tuple[PolyMetric, float] | None:
    """The metric with monomials `exponents` minimising mu at rate alpha for the observer's
    F [N, n], J_F [N, n, n], B [N, n, p] at the points, M >= I at the grid's states."""
    N, n = F.shape
    p = B.shape[2]
    d = n + p
    basis = _sym_basis(n)
    nb = len(basis)
    K = len(exponents)
    nv = K * nb + 1
    phi, grad = monomial_features(exponents, pts.x)
    rate = np.einsum("Nkn,Nn->Nk", grad, F)  # dphi_k/dt along F
    C = np.zeros((N, nv, d, d))
    for k in range(K):
        for b, S in enumerate(basis):
            v = k * nb + b
            SJ = np.einsum("ij,Njl->Nil", S, J)
            C[:, v, :n, :n] = (rate[:, k, None, None] * S + phi[:, k, None, None]
                               * (SJ + SJ.transpose(0, 2, 1) + alpha * S))
            SB = phi[:, k, None, None] * np.einsum("ij,Njl->Nil", S, B)
            C[:, v, :n, n:] = SB
            C[:, v, n:, :n] = SB.transpose(0, 2, 1)
    C[:, -1, n:, n:] = -np.eye(p)
    phiQ, _ = monomial_features(exponents, pts.states)
    A = np.zeros((len(phiQ), nv, n, n))
    for k in range(K):
        for b, S in enumerate(basis):
            A[:, k * nb + b] = phiQ[:, k, None, None] * S
    A0 = -np.broadcast_to(np.eye(n), (len(phiQ), n, n))
    status, x = _solve_psd(C, np.zeros((N, d, d)), [(A, A0)])
    if x is None:
        return None
    coeffs = np.einsum("kb,bij->kij", x[:-1].reshape(K, nb), basis)
    return PolyMetric(exponents, coeffs), float(x[-1])


def gain_step(pts: DesignPoints, metric: PolyMetric, alpha: float,
              schedule: np.ndarray | None = None) -> tuple[np.ndarray, float] | None:
    """The gain schedule minimising mu at rate alpha for the metric: k = K(x) (w - h(x)) with
    K(x) = sum_j x^(b_j) K_j over the exponents `schedule` [J, n] (None: a constant K, the
    linear gain). Returns the coefficients K_j [J, n, p] (or K [n, p] for a constant gain)
    and mu. With r = w - h: F = f + K r, J_F = Jf + (dK/dx) r - K H, B = K, all affine in
    the K_j."""
    N, n = pts.f.shape
    p = pts.H.shape[1]
    d = n + p
    sched = np.zeros((1, n), dtype=np.int64) if schedule is None else np.asarray(schedule)
    psi, dpsi = monomial_features(sched, pts.x)  # [N, J], [N, J, n]
    xt = torch.as_tensor(pts.x)
    M = metric.value(xt).numpy()
    dM = metric.partials(xt).numpy()  # [N, n(i), n, n]
    nJ = len(sched)
    nv = nJ * n * p + 1
    C = np.zeros((N, nv, d, d))
    C0 = np.zeros((N, d, d))
    MJ = M @ pts.Jf
    C0[:, :n, :n] = np.einsum("Nkij,Nk->Nij", dM, pts.f) + MJ + MJ.transpose(0, 2, 1) + alpha * M
    for j in range(nJ):
        for a in range(n):
            for b in range(p):
                v = (j * n + a) * p + b
                E = np.zeros((n, p))
                E[a, b] = 1.0
                Kx = psi[:, j, None, None] * E  # this coefficient's K(x) [N, n, p]
                Kr = Kx @ pts.r[:, :, None]  # [N, n, 1]
                dKr = np.einsum("Ni,ab,Nb->Nai", dpsi[:, j], E, pts.r)  # (dK/dx r) [N, n, n]
                Jk = dKr - Kx @ pts.H
                MJk = M @ Jk
                C[:, v, :n, :n] = (np.einsum("Nkij,Nk->Nij", dM, Kr[:, :, 0]) + MJk
                                   + MJk.transpose(0, 2, 1))
                MB = M @ Kx
                C[:, v, :n, n:] = MB
                C[:, v, n:, :n] = MB.transpose(0, 2, 1)
    C[:, -1, n:, n:] = -np.eye(p)
    status, x = _solve_psd(C, C0, [])
    if x is None:
        return None
    coeffs = x[:-1].reshape(nJ, n, p)
    return (coeffs[0] if schedule is None else coeffs), float(x[-1])


def schedule_terms(pts: DesignPoints, schedule: np.ndarray, coeffs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F, J_F, B at the points for the gain schedule k = K(x) (w - h(x)) (`gain_step`)."""
    psi, dpsi = monomial_features(np.asarray(schedule), pts.x)
    Kx = np.einsum("Nj,jab->Nab", psi, coeffs)
    dK = np.einsum("Nji,jab->Nabi", dpsi, coeffs)
    F = pts.f + np.einsum("Nab,Nb->Na", Kx, pts.r)
    J = pts.Jf + np.einsum("Nabi,Nb->Nai", dK, pts.r) - Kx @ pts.H
    return F, J, Kx


def linear_terms(pts: DesignPoints, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F, J_F, B at the points for the linear gain k = K (w - h(x))."""
    return schedule_terms(pts, np.zeros((1, pts.x.shape[1]), dtype=np.int64),
                          np.asarray(K, dtype=np.float64)[None])


def design_constant_metric(system: System, K: np.ndarray, *, alphas: np.ndarray | None = None,
                           per_axis: int | None = None
                           ) -> tuple[np.ndarray, float, float] | None:
    """The constant metric P >= I of the dissipation inequality over X x Y for the linear gain
    k = K (w - h(x)) (its matrix does not depend on w: the grid's states suffice), with the
    rate alpha of a scan (geometric, then a local one around the best) that minimises
    mu / alpha: (P, alpha, mu), None when no rate is feasible. A candidate: the dissipation
    check proves it."""
    pts = design_points(system, 0.0, per_axis=per_axis, offsets=1)
    F, J, B = linear_terms(pts, K)
    zero = np.zeros((1, system.n), dtype=np.int64)

    def solve(a: float):
        return metric_step(pts, zero, F, J, B, a)

    grid = np.geomspace(0.2, 8.0, 9) if alphas is None else np.asarray(alphas, dtype=float)
    best = _best_alpha(solve, grid)
    if best is None:
        return None
    local = _best_alpha(solve, best[0] * np.array([0.8, 0.9, 1.0, 1.12, 1.25]))
    alpha, (metric, mu), _ = local if local is not None else best
    return metric.coefficients[0], alpha, mu


@dataclass
class MetricDesign:
    """A designed metric and gain schedule (`schedule` exponents [J, n], `K` coefficients
    [J, n, p]; one zero exponent: the linear gain K[0]), its rate, noise gain and sampled
    bound per unit noise sqrt(mu / alpha) (M >= I at the grid: m_min about 1)."""

    metric: PolyMetric
    schedule: np.ndarray
    K: np.ndarray
    alpha: float
    mu: float

    @property
    def per_unit_noise(self) -> float:
        return math.sqrt(self.mu / self.alpha)

    @property
    def linear(self) -> bool:
        return len(self.schedule) == 1 and not self.schedule.any()


def _best_alpha(solve, alphas) -> tuple[float, object, float] | None:
    best = None
    for a in alphas:
        out = solve(float(a))
        if out is None:
            continue
        value = math.sqrt(out[-1] / a)
        if best is None or value < best[2]:
            best = (float(a), out, value)
    return best


def design_metric(system: System, K0: np.ndarray, *, degree: int = 2, tau: float | None = 0.6,
                  even: bool = True, rounds: int = 3, alphas: np.ndarray | None = None,
                  schedule_degree: int | None = None, pts: DesignPoints | None = None
                  ) -> MetricDesign | None:
    """A polynomial metric of `degree` (monomials of even degree only when `even`) and a gain
    starting from the linear K0 [n, p]: linear, or with `schedule_degree` a schedule K(x) of
    that degree (every monomial); `metric_step` and `gain_step` alternate `rounds` times at
    the best alpha of a scan (then a local one around it). None when no step is feasible."""
    pts = pts or design_points(system, tau)
    exps = even_monomials(system.n, degree) if even else all_monomials(system.n, degree)
    n, p = system.n, system.p
    sched = (np.zeros((1, n), dtype=np.int64) if schedule_degree is None
             else all_monomials(n, schedule_degree))
    coeffs = np.zeros((len(sched), n, p))
    coeffs[0] = np.asarray(K0, dtype=np.float64).reshape(n, p)
    alphas = np.linspace(0.5, 4.0, 8) if alphas is None else alphas

    def with_gain(coeffs):
        F, J, B = schedule_terms(pts, sched, coeffs)
        return lambda a: metric_step(pts, exps, F, J, B, a)

    best = _best_alpha(with_gain(coeffs), alphas)
    if best is None:
        return None
    alpha, (metric, mu), _ = best
    for _ in range(rounds):
        g = gain_step(pts, metric, alpha, None if schedule_degree is None else sched)
        if g is None:
            break
        coeffs = g[0][None] if schedule_degree is None else g[0]
        local = _best_alpha(with_gain(coeffs), alpha * np.array([0.85, 0.93, 1.0, 1.08, 1.17]))
        if local is None:
            break
        alpha, (metric, mu), _ = local
    return MetricDesign(metric=metric, schedule=sched, K=coeffs, alpha=alpha, mu=mu)
