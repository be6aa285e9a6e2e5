"""Choosing the metric P (METHOD §4): kernel-condition SDP and the classic LMI observer.

Both problems are affine in Jf, so imposing them at the vertices of interval enclosures of
Jf on sub-boxes covering {x in X : h(x) in Y} covers every point, not only samples. The
answer is then re-checked in numpy at every (unpruned) vertex: PROVED means that re-check
passed with the margin. Where no constant P exists the result says why, with a witness:
a point whose linearisation has a mode that the output cannot see and that does not decay
faster than 2 lam (PBH test), e.g. reverse Duffing on the line x2 = 0.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from certify.design import sdp
from certify.prove.side import kernel_basis_with_error
from certify.results import MetricResult, Status
from certify.search.witness import invisible_mode_certified
from certify.spec.enclosures import h_enclosure, jacobian_f_enclosure
from certify.spec.system import System

DEFAULT_MARGIN = 1e-2
DEFAULT_KAPPA_MAX = 1e4
MAX_VERTEX_BITS = 12  # at most 2^12 vertices per sub-box


# ----------------------------------------------------------------------------------------
# shared helpers (also used by the necessary-condition check)
# ----------------------------------------------------------------------------------------

def output_matrix(system: System) -> np.ndarray:
    """C = dh/dx for linear h ([p, n]); raises ValueError for nonlinear h."""
    if not system.h_is_linear:
        raise ValueError("h is nonlinear: dh/dx is not constant")
    return system.jac_h(torch.zeros(1, system.n, dtype=torch.float64))[0].numpy()


def kernel_basis(C: np.ndarray) -> np.ndarray:
    """Orthonormal basis of ker C as columns [n, n - rank] (see `kernel_basis_with_error`)."""
    return kernel_basis_with_error(C)[0]


def sub_boxes(system: System, per_dim: int, manifold: bool = True
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """X cut into per_dim^n equal sub-boxes; with `manifold`, drop those whose h-enclosure
    misses Y (they hold no point of {x in X : h(x) in Y}).

    Returns lo, hi [B, n] (float64). Faces are shared exactly; the outer faces are X's own.
    """
    n = system.n
    X = torch.as_tensor(system.X, dtype=torch.float64)
    ticks = [torch.linspace(float(X[i, 0]), float(X[i, 1]), per_dim + 1, dtype=torch.float64)
             for i in range(n)]
    for i in range(n):
        ticks[i][0], ticks[i][-1] = X[i, 0], X[i, 1]
    idx = torch.cartesian_prod(*[torch.arange(per_dim)] * n).reshape(-1, n)
    lo = torch.stack([ticks[i][idx[:, i]] for i in range(n)], 1)
    hi = torch.stack([ticks[i][idx[:, i] + 1] for i in range(n)], 1)
    if not manifold:
        return lo, hi
    Y = torch.as_tensor(system.Y, dtype=torch.float64)
    hl, hh = h_enclosure(system, lo, hi)
    miss = ((hh < Y[:, 0]) | (hl > Y[:, 1])).any(-1)
    return lo[~miss], hi[~miss]


def default_subdivisions(n: int, max_boxes: int = 1024) -> int:
    return max(1, int(math.floor(max_boxes ** (1.0 / n) + 1e-9)))


@dataclass
class Vertices:
    """Matrices whose convex hull contains Jf over the sub-boxes (per box vertices, pruned)."""

    all: np.ndarray  # [V, n, n] every vertex of every sub-box's enclosure (for the re-check)
    pruned: np.ndarray  # [V', n, n] hull vertices (for the SDP)
    boxes: int
    varying: int  # number of Jacobian entries that vary and matter


def enclosure_vertices(system: System, lo: torch.Tensor, hi: torch.Tensor,
                       relevant: np.ndarray | None = None) -> Vertices:
    """Vertices of the interval enclosures of Jf on the boxes [B, n].

    Only `relevant` entries ([n, n] bool; default all) are enumerated; the others are set to
    the box midpoint (callers pass the entries their constraint does not depend on).
    """
    n = system.n
    Jlo, Jhi = jacobian_f_enclosure(system, lo, hi)
    Jlo, Jhi = Jlo.numpy(), Jhi.numpy()
    if not (np.all(np.isfinite(Jlo)) and np.all(np.isfinite(Jhi))):
        raise ValueError("the enclosure of Jf is not finite on some sub-box")
    rel = np.ones((n, n), bool) if relevant is None else np.asarray(relevant, bool)
    vary = rel & np.any(Jlo != Jhi, axis=0)
    ij = np.argwhere(vary)
    d = len(ij)
    if d > MAX_VERTEX_BITS:
        raise ValueError(f"{d} Jacobian entries vary over X: too many for vertex enumeration "
                         f"(limit {MAX_VERTEX_BITS})")
    base = np.where(rel, Jlo, 0.5 * (Jlo + Jhi))  # relevant constant entries: lo == hi
    bits = np.array(list(itertools.product((0, 1), repeat=d)), dtype=bool).reshape(2 ** d, d)
    B = Jlo.shape[0]
    V = np.repeat(base[:, None], len(bits), axis=1)  # [B, 2^d, n, n]
    for k, (i, j) in enumerate(ij):
        V[:, :, i, j] = np.where(bits[None, :, k], Jhi[:, None, i, j], Jlo[:, None, i, j])
    allv = V.reshape(-1, n, n)
    pts = allv[:, ij[:, 0], ij[:, 1]] if d else np.zeros((len(allv), 0))
    _, first = np.unique(pts, axis=0, return_index=True)
    uniq = allv[np.sort(first)]
    pruned = uniq
    if d == 1:
        vals = uniq[:, ij[0, 0], ij[0, 1]]
        pruned = uniq[[int(np.argmin(vals)), int(np.argmax(vals))]]
    elif 2 <= d <= 8 and len(uniq) > 2 ** d:
        # Hull in the coordinates that really vary: entries that are constant up to the
        # enclosure's outward rounding would make the point set flat for Qhull. Dropping a
        # vertex here only weakens the SDP's constraint set; the re-check uses `all`.
        pts = uniq[:, ij[:, 0], ij[:, 1]]
        rng = pts.max(0) - pts.min(0)
        keep = rng > 1e-9 * (1.0 + np.abs(pts).max(0))
        try:
            from scipy.spatial import ConvexHull

            if keep.sum() == 1:
                c = pts[:, keep][:, 0]
                pruned = uniq[[int(np.argmin(c)), int(np.argmax(c))]]
            elif keep.sum() >= 2:
                pruned = uniq[np.sort(ConvexHull(pts[:, keep]).vertices)]
        except Exception:  # degenerate point sets: keep them all (still correct)
            pruned = uniq
    elif d == 0:
        pruned = uniq[:1]
    return Vertices(all=uniq, pruned=pruned, boxes=B, varying=d)


def _lam_max(S: np.ndarray) -> np.ndarray:
    return np.linalg.eigvalsh(0.5 * (S + np.swapaxes(S, -1, -2)))[..., -1]


def kernel_values(J: np.ndarray, P: np.ndarray, Z: np.ndarray, lam: float) -> np.ndarray:
    """lam_max(Z^T (He{P J} + 2 lam P) Z) for J [V, n, n] -> [V]."""
    PJ = P[None] @ J
    S = 0.5 * (PJ + np.swapaxes(PJ, -1, -2)) + 2.0 * lam * P[None]
    return _lam_max(Z.T[None] @ S @ Z[None])


def observer_values(J: np.ndarray, P: np.ndarray, K: np.ndarray, C: np.ndarray,
                    lam: float) -> np.ndarray:
    """lam_max(He{P (J - K C)} + 2 lam P) for J [V, n, n] -> [V]."""
    A = P[None] @ (J - (K @ C)[None])
    return _lam_max(0.5 * (A + np.swapaxes(A, -1, -2)) + 2.0 * lam * P[None])


# ----------------------------------------------------------------------------------------
# the reason when no constant P exists
# ----------------------------------------------------------------------------------------

def _grid(system: System, points: int) -> torch.Tensor:
    """Odd-sized tensor grid over X (contains the centre lines), masked to h(x) in Y."""
    n = system.n
    per = max(3, int(round(points ** (1.0 / n))) | 1)
    k = torch.arange(per, dtype=torch.float64) / (per - 1)
    axes = []
    for a, b in system.X:
        ax = float(a) + (float(b) - float(a)) * k
        ax[per // 2] = 0.5 * (float(a) + float(b))  # the centre line exactly
        ax[-1] = float(b)
        axes.append(ax)
    x = torch.cartesian_prod(*axes).reshape(-1, n)
    hx = system.h(x)
    Y = torch.as_tensor(system.Y, dtype=torch.float64)
    return x[((hx >= Y[:, 0]) & (hx <= Y[:, 1])).all(-1)]


def unobservable_witness(system: System, lam: float, x: torch.Tensor, C: np.ndarray
                         ) -> tuple[np.ndarray, complex, float] | None:
    """A point whose linearisation has a mode invisible in y and slower than -2 lam.

    PBH test at every x [B, n]: for each eigenvalue mu of Jf(x) with Re mu >= -2 lam, the
    smallest singular value of [Jf - mu I; C]. Returns (x, mu, sigma) at the smallest such
    sigma if it is ~0 relative to ||Jf|| + ||C|| (1e-9), else None.
    """
    found = _pbh(system, lam, x, C)
    return None if found is None else found[0]


def _pbh(system: System, lam: float, x: torch.Tensor, C: np.ndarray
         ) -> tuple[tuple[np.ndarray, complex, float], np.ndarray] | None:
    """`unobservable_witness`'s answer and the mask [B] of every x that is one (numerically)."""
    J = system.jac_f(x).numpy()
    n = J.shape[-1]
    mu = np.linalg.eigvals(J)  # [B, n]
    scale = np.linalg.norm(J, axis=(1, 2)) + np.linalg.norm(C) + 1e-300
    smins = np.empty((len(J), n))
    for k in range(n):  # loop over the n modes, vectorised over points
        A = J.astype(complex) - mu[:, k, None, None] * np.eye(n)[None]
        stack = np.concatenate([A, np.broadcast_to(C.astype(complex), (len(J),) + C.shape)], 1)
        smin = np.linalg.svd(stack, compute_uv=False)[:, -1] / scale
        smins[:, k] = np.where(mu[:, k].real >= -2.0 * lam, smin, np.inf)
    hit = smins.min(1) <= 1e-9
    if not hit.any():
        return None
    # among the witnesses, the one nearest the centre of X (the simplest to read)
    centre = torch.as_tensor(system.X.mean(1), dtype=torch.float64)
    dist = torch.linalg.vector_norm(x - centre, dim=1).numpy()
    i = int(np.argmin(np.where(hit, dist, np.inf)))
    k = int(np.argmin(smins[i]))
    return (x[i].numpy().copy(), complex(mu[i, k]), float(smins[i, k])), hit


def undetectable_at_every_rate(system: System, grid_points: int = 40_000) -> str | None:
    """Why no observer with an exact boundary condition contracts in ANY constant metric at
    ANY rate > 0 on this box, or None when no such reason is found (linear h only).

    The reason is a point of {x in X : h(x) in Y} where Jf has a real mode mu >= 0 whose
    eigenvector v the output does not see (C v = 0): there v^T (He{P Jf} + 2 lam P) v =
    (mu + 2 lam) v^T P v > 0 for every P > 0 and lam > 0, so the kernel condition (METHOD
    §3.5) fails whatever P, lam and gain (reverse Duffing on the line x2 = 0). The point is
    found by the PBH test on a grid and confirmed exactly (`invisible_mode_certified` at
    lam = 0); when the grid points found are those with one coordinate at one value, the
    text names that set.
    """
    if not system.h_is_linear:
        return None
    C = output_matrix(system)
    if kernel_basis(C).shape[1] == 0:
        return None
    x = _grid(system, grid_points)
    found = _pbh(system, 0.0, x, C)
    if found is None:
        return None
    (xw, mu, _), hit = found
    if not invisible_mode_certified(system, C, 0.0, xw, mu):
        return None
    xs = x.numpy()
    # a coordinate value that the grid points found are exactly the grid points of (a line)
    lines = [j for j in range(system.n)
             if hit.sum() > 1 and np.array_equal(hit, xs[:, j] == xw[j])]
    where = them = ""
    if lines:
        name, value = system.states[lines[0]], float(xw[lines[0]])
        where = (f"; the PBH test finds the same at every point of the search grid with "
                 f"{name} = {value:g} and nowhere else")
        them = f" the points with {name} = {value:g}"
    return (f"no observer with an exact boundary condition contracts in any constant metric "
            f"at any rate > 0 on this box: at xhat = {_fmt(xw)} the linearisation has the mode "
            f"{mu.real:.4g}, which the output does not see (C v = 0 for its eigenvector v: "
            f"not detectable there){where}; choose a box that excludes{them or ' such points'}")


def _fmt(v: np.ndarray | list[float]) -> str:
    return "(" + ", ".join(f"{float(a):.4g}" for a in v) + ")"


def _diagnose(system: System, lam: float, margin: float, Z: np.ndarray, C: np.ndarray,
              grid_points: int, kappa_max: float) -> tuple[Status, str, list[float] | None,
                                                           list[float] | None]:
    """Why the vertex SDP failed: a pointwise witness, a sampled infeasibility, or neither."""
    x = _grid(system, grid_points)
    w = unobservable_witness(system, lam, x, C)
    if w is not None and invisible_mode_certified(system, C, lam, w[0], w[1]):
        xw, mu, _ = w
        yw = system.h(torch.as_tensor(xw[None])).numpy()[0]
        tiny = 1e-12 * (1.0 + abs(mu))
        mode = f"{mu.real:.4g}" if abs(mu.imag) <= tiny else f"{mu.real:.4g}{mu.imag:+.4g}i"
        msg = (f"no constant metric exists: at xhat = {_fmt(xw)} (y = {_fmt(yw)}) the "
               f"linearisation has the mode {mode}, which the output "
               f"does not see (C v = 0 for its eigenvector v) and which does not decay faster "
               f"than -2 lam = {-2 * lam:.4g}; along v the kernel condition reads "
               f"v^T (He{{P Jf}} + 2 lam P) v >= 0 for every P > 0, so neither a constant P "
               f"nor any C^1 gain with exact boundary condition can contract at rate {lam:g} "
               f"there (the linearisation is not detectable at this rate). A non-zero rate "
               f"needs a box that excludes such points, or a smaller lam.")
        return Status.VIOLATED, msg, xw.tolist(), yw.tolist()
    # no pointwise obstruction: is it the enclosure, or do real points already conflict?
    J = system.jac_f(x).numpy()
    take = np.linspace(0, len(J) - 1, min(len(J), 400)).astype(int)
    res = sdp.metric_sdp(J[take], Z, lam, margin=margin, kappa_max=kappa_max)
    if w is not None:
        return (Status.UNKNOWN, f"numerical evidence, not a proof: at xhat = {_fmt(w[0])} the "
                f"linearisation seems to have a mode {w[1].real:.4g} that the output does not "
                f"see (PBH residual {w[2]:.2g}) and that is not faster than -2 lam; it could "
                "not be confirmed in exact interval arithmetic", w[0].tolist(), None)
    if res.status is Status.VIOLATED:
        return (Status.UNKNOWN, f"numerical evidence, not a proof: the solver (Clarabel) "
                f"reports that no constant metric with cond P <= {kappa_max:g} satisfies "
                f"the kernel condition with margin {margin:g} even at {len(take)} sampled "
                "points of X; the infeasibility certificate is not verified", None, None)
    return (Status.UNKNOWN, "the SDP over the vertex enclosure failed "
            f"({res.message}) but sampled points admit a metric: the interval enclosure of "
            "Jf is too coarse; raise `subdivisions` or reduce the margin", None, None)


# ----------------------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------------------

def synthesize_metric(system: System, lam: float, *, margin: float = DEFAULT_MARGIN,
                      kappa_max: float = DEFAULT_KAPPA_MAX, subdivisions: int | None = None,
                      grid_points: int = 40_000) -> MetricResult:
    """Constant P with Z^T (He{P Jf(x)} + 2 lam P) Z <= -margin I on all of {x in X: h(x) in Y}.

    Z spans ker dh (linear h only). Imposed at the vertices of interval enclosures of Jf on
    `subdivisions`^n sub-boxes; minimises kappa with I <= P <= kappa I. PROVED when the
    answer passes the numpy re-check at every vertex (lam_max <= -margin/2 and P > 0);
    VIOLATED with a witness when no constant P exists; UNKNOWN otherwise.
    """
    t0 = time.perf_counter()
    n = system.n
    if not lam > 0:
        raise ValueError(f"lam must be > 0; got {lam}")
    if not system.h_is_linear:
        return MetricResult(Status.UNKNOWN, "metric synthesis needs a linear output map h "
                            "(constant ker dh)", None, None, margin, lam,
                            seconds=time.perf_counter() - t0)
    C = output_matrix(system)
    Z = kernel_basis(C)
    if Z.shape[1] == 0:
        return MetricResult(Status.PROVED, "dh has full column rank: the kernel condition is "
                            "empty and P = I serves", np.eye(n).tolist(), 1.0, margin, lam,
                            seconds=time.perf_counter() - t0)
    per = subdivisions or default_subdivisions(n)
    lo, hi = sub_boxes(system, per)
    relevant = np.repeat((np.abs(Z).sum(1) > 0)[None, :], n, axis=0)  # J_ij matters iff Z_j != 0
    try:
        verts = enclosure_vertices(system, lo, hi, relevant)
    except ValueError as exc:
        return MetricResult(Status.UNKNOWN, f"metric synthesis: {exc}", None, None, margin,
                            lam, seconds=time.perf_counter() - t0)
    res = sdp.metric_sdp(verts.pruned, Z, lam, margin=margin, kappa_max=kappa_max)
    info = {**res.stats(), "sub_boxes": verts.boxes, "vertices": len(verts.all),
            "sdp_vertices": len(verts.pruned), "subdivisions": per}
    if res.status is not Status.PROVED:
        status, msg, wx, wy = _diagnose(system, lam, margin, Z, C, grid_points, kappa_max)
        return MetricResult(status, msg, None, None, margin, lam, solver=info, witness=wx,
                            witness_y=wy, seconds=time.perf_counter() - t0)
    P = res.variables["P"]
    top = float(kernel_values(verts.all, P, Z, lam).max())
    pmin = float(np.linalg.eigvalsh(P)[0])
    info["check_max_vertex_value"] = top
    cond = float(np.linalg.cond(P))
    if not (top <= -0.5 * margin and pmin > 0):
        return MetricResult(Status.UNKNOWN, f"the SDP answer failed the re-check (max vertex "
                            f"value {top:.3g} > {-0.5 * margin:g} or P not positive definite)",
                            P.tolist(), cond, margin, lam, solver=info,
                            seconds=time.perf_counter() - t0)
    msg = (f"constant metric found: cond P = {cond:.4g}; kernel condition <= {top:.3g} at all "
           f"{len(verts.all)} vertices of the Jf enclosures on {verts.boxes} sub-boxes "
           f"covering {{x in X : h(x) in Y}} (re-checked in numpy, margin {margin:g})")
    return MetricResult(Status.PROVED, msg, P.tolist(), cond, margin, lam, solver=info,
                        seconds=time.perf_counter() - t0)


def observer_lmi(system: System, lam: float, *, margin: float = DEFAULT_MARGIN,
                 kappa_max: float = DEFAULT_KAPPA_MAX, gain_max: float | None = 1e3,
                 subdivisions: int | None = None, objective: str = "kappa",
                 grid_points: int = 40_000) -> MetricResult:
    """Classic LMI observer: He{P Jf(x) - Y C} + 2 lam P <= -margin I on all of X, K = P^-1 Y.

    Same vertex enclosure as `synthesize_metric` (all Jacobian entries matter here);
    I <= P <= kappa I, ||Y||_2 <= gain_max. PROVED when the numpy re-check with the returned
    (P, K) passes at every vertex; `K` is filled. Linear h only.
    """
    t0 = time.perf_counter()
    if not lam > 0:
        raise ValueError(f"lam must be > 0; got {lam}")
    if not system.h_is_linear:
        return MetricResult(Status.UNKNOWN, "the LMI observer needs a linear output map h",
                            None, None, margin, lam, seconds=time.perf_counter() - t0)
    C = output_matrix(system)
    n = system.n
    per = subdivisions or default_subdivisions(n)
    lo, hi = sub_boxes(system, per, manifold=False)  # D does not depend on y: all of X
    try:
        verts = enclosure_vertices(system, lo, hi)
    except ValueError as exc:
        return MetricResult(Status.UNKNOWN, f"LMI observer: {exc}", None, None, margin, lam,
                            seconds=time.perf_counter() - t0)
    res = sdp.observer_sdp(verts.pruned, C, lam, margin=margin, kappa_max=kappa_max,
                           gain_max=gain_max, objective=objective)
    info = {**res.stats(), "sub_boxes": verts.boxes, "vertices": len(verts.all),
            "sdp_vertices": len(verts.pruned), "subdivisions": per, "gain_max": gain_max}
    if res.status is not Status.PROVED:
        Z = kernel_basis(C)
        status, msg, wx, wy = (_diagnose(system, lam, margin, Z, C, grid_points, kappa_max)
                               if Z.shape[1] else (Status.UNKNOWN, res.message, None, None))
        return MetricResult(status, msg, None, None, margin, lam, solver=info, witness=wx,
                            witness_y=wy, seconds=time.perf_counter() - t0)
    P, K = res.variables["P"], res.variables["K"]
    top = float(observer_values(verts.all, P, K, C, lam).max())
    info["check_max_vertex_value"] = top
    info["gain_norm"] = float(np.linalg.norm(K, 2))
    cond = float(np.linalg.cond(P))
    if not (top <= -0.5 * margin and float(np.linalg.eigvalsh(P)[0]) > 0):
        return MetricResult(Status.UNKNOWN, f"the LMI answer failed the re-check (max vertex "
                            f"value {top:.3g} > {-0.5 * margin:g})", P.tolist(), cond, margin,
                            lam, K=K.tolist(), solver=info, seconds=time.perf_counter() - t0)
    msg = (f"LMI observer found: cond P = {cond:.4g}, ||K||_2 = {info['gain_norm']:.4g}; "
           f"lam_max(He{{P (Jf - K C)}} + 2 lam P) <= {top:.3g} at all {len(verts.all)} "
           f"vertices of the Jf enclosures on {verts.boxes} sub-boxes (re-checked in numpy)")
    return MetricResult(Status.PROVED, msg, P.tolist(), cond, margin, lam, K=K.tolist(),
                        solver=info, seconds=time.perf_counter() - t0)


# ----------------------------------------------------------------------------------------
# the LMI observer with its memory bounded (many states)
# ----------------------------------------------------------------------------------------

#: vertex LMIs the SDP of `bounded_observer_lmi` gets at most (cvxpy's canonicalisation took
#: 160 s for 4096 6x6 LMIs, and 3^6 sub-boxes x 4096 vertices grew past 16 GB)
MAX_SDP_VERTICES = 1024

#: above this many vertex LMIs (sub-boxes x 2^entries, before pruning) `observer_lmi`'s
#: default subdivision is replaced by `bounded_observer_lmi` (lorenz, vdp, vdp2 stay below)
MAX_DEFAULT_VERTICES = 2**16


def varying_entries(system: System) -> tuple[np.ndarray, np.ndarray]:
    """(varies, all_differ) [n, n] bool over all of X: entries of the Jf enclosure wider than
    its outward rounding, and entries whose enclosure has lo != hi at all (the coupling
    constants of vdp2/vdp3 differ by one rounding, which doubles the vertices per entry)."""
    lo, hi = sub_boxes(system, 1, manifold=False)
    Jlo, Jhi = (t[0].numpy() for t in jacobian_f_enclosure(system, lo, hi))
    width = Jhi - Jlo
    return width > 1e-9 * (1.0 + np.maximum(np.abs(Jlo), np.abs(Jhi))), width > 0


def default_vertex_count(system: System) -> int:
    """Vertex LMIs `observer_lmi` would build by default (sub-boxes x 2^varying entries)."""
    _, differ = varying_entries(system)
    return default_subdivisions(system.n) ** system.n * 2 ** int(differ.sum())


def bounded_observer_lmi(system: System, lam: float, *, margin: float, kappa_max: float,
                         gain_max: float | None, subdivisions: int | None = None,
                         objective: str = "kappa") -> Any:
    """`observer_lmi` with its memory bounded: vertices are enumerated
    only over the Jacobian entries that really vary (wider than rounding), and X is cut into
    the most sub-boxes per side that keep at most MAX_SDP_VERTICES vertex LMIs. The answer is
    re-checked in numpy at every vertex of the full enclosures (rounding-wide entries too),
    as `observer_lmi` does; the prover proves the observer anyway."""

    t0 = time.perf_counter()
    if not lam > 0:
        raise ValueError(f"lam must be > 0; got {lam}")
    varies, _ = varying_entries(system)
    per_box = 2 ** int(varies.sum())
    per = subdivisions or max(1, int((MAX_SDP_VERTICES / per_box) ** (1.0 / system.n) + 1e-9))
    lo, hi = sub_boxes(system, per, manifold=False)
    verts = enclosure_vertices(system, lo, hi, relevant=varies)
    C = output_matrix(system)
    res = sdp.observer_sdp(verts.pruned, C, lam, margin=margin, kappa_max=kappa_max,
                           gain_max=gain_max, objective=objective)
    info = {**res.stats(), "sub_boxes": verts.boxes, "subdivisions": per,
            "sdp_vertices": len(verts.pruned), "gain_max": gain_max}
    if res.status is not Status.PROVED:
        return MetricResult(res.status, f"bounded LMI observer: {res.message}", None, None,
                            margin, lam, solver=info, seconds=time.perf_counter() - t0)
    P, K = res.variables["P"], res.variables["K"]
    full = enclosure_vertices(system, lo, hi).all
    top = float(observer_values(full, P, K, C, lam).max())
    info.update(check_max_vertex_value=top, vertices=len(full),
                gain_norm=float(np.linalg.norm(K, 2)))
    if not (top <= -0.5 * margin and float(np.linalg.eigvalsh(P)[0]) > 0):
        return MetricResult(Status.UNKNOWN, f"the LMI answer failed the re-check (max vertex "
                            f"value {top:.3g} > {-0.5 * margin:g})", None, None, margin, lam,
                            solver=info, seconds=time.perf_counter() - t0)
    msg = (f"LMI observer found: cond P = {np.linalg.cond(P):.4g}, ||K||_2 = "
           f"{info['gain_norm']:.4g}; lam_max <= {top:.3g} at all {len(full)} vertices of the "
           f"Jf enclosures on {verts.boxes} sub-boxes (re-checked in numpy)")
    return MetricResult(Status.PROVED, msg, P.tolist(), float(np.linalg.cond(P)), margin, lam,
                        K=K.tolist(), solver=info, seconds=time.perf_counter() - t0)
