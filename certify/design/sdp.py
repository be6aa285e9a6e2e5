"""Semidefinite programs through cvxpy + Clarabel: the solver interface, metric synthesis, the
LMI observers (for a rate, and for the dissipation bound).

The package's cvxpy interface (`certify.design.lipsdp` uses it too). Every problem returns an
`SdpResult`; the solver's native outcome is mapped onto `Status` and anything inaccurate or
unrecognised fails closed (UNKNOWN, never a bound). Solver answers are never trusted as they
stand: LipSDP is re-checked on the full LMI rebuilt in numpy, the metric and observer problems
by their callers at every vertex, and every design is proved by the prover before it is called
certified.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from certify.results import Status

__all__ = ["SdpResult", "solve", "metric_sdp", "observer_sdp", "DissipationSdp",
           "dissipation_sdp"]


class _OnFirstUse:
    """A module imported on its first attribute access: cvxpy takes ~2.7 s to import and is
    needed only when an SDP goes through it (the hand-written LipSDP solver does not)."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str) -> Any:
        import importlib

        module = importlib.import_module(self._name)
        self.__dict__.update(module.__dict__)  # later lookups skip __getattr__
        return getattr(module, attr)


cp = _OnFirstUse("cvxpy")

SOLVER = "CLARABEL"
_U = np.finfo(np.float64).eps


@dataclass
class SdpResult:
    """One SDP solve: the mapped outcome, the value and the solver's own account of it.

    `status`: PROVED = solved to optimality (for LipSDP also re-checked, see `verified`),
    VIOLATED = the solver proved the constraints infeasible, UNKNOWN = inaccurate,
    unbounded, out of iterations or unrecognised (not a bound), ERROR = the solver failed.
    """

    status: Status
    message: str
    value: float | None  # the (verified, where applicable) optimal value; None: no bound
    solver: str = SOLVER
    raw_status: str = ""
    seconds: float = 0.0  # wall time: build + compile + solve
    solve_seconds: float = 0.0  # the solver's own solve time
    iterations: int | None = None
    raw_value: float | None = None  # the solver's value before any re-check
    verified: bool | None = None  # None: not a problem with a re-check here
    check_max_eig: float | None = None  # largest eigenvalue of the rebuilt LMI
    check_tolerance: float | None = None  # it must be <= -check_tolerance
    variables: dict[str, Any] = field(default_factory=dict)

    def stats(self) -> dict[str, Any]:
        """Plain-data solver facts for result records."""
        return {"solver": self.solver, "raw_status": self.raw_status,
                "seconds": self.seconds, "solve_seconds": self.solve_seconds,
                "iterations": self.iterations, "raw_value": self.raw_value,
                "verified": self.verified, "check_max_eig": self.check_max_eig,
                "check_tolerance": self.check_tolerance, "message": self.message}


_STATUS_MAP = {  # cvxpy.settings.OPTIMAL, .INFEASIBLE (spelled out: no import needed here)
    "optimal": Status.PROVED,
    "infeasible": Status.VIOLATED,
}


def solve(prob: cp.Problem, t0: float, **solver_opts: Any) -> tuple[Status, str, SdpResult]:
    """Solve with Clarabel and map the outcome; never raises on solver trouble."""
    try:
        prob.solve(solver=SOLVER, **solver_opts)
        raw = str(prob.status)
        status = _STATUS_MAP.get(raw, Status.UNKNOWN)
        msg = {Status.PROVED: "solved", Status.VIOLATED: "infeasible"}.get(
            status, f"solver status {raw!r} is not a usable answer (inaccurate or unrecognised)")
    except cp.error.SolverError as exc:
        raw, status, msg = "solver_error", Status.ERROR, f"solver failed: {exc}"
    stats = prob.solver_stats if prob.status is not None else None
    res = SdpResult(
        status=status, message=msg, value=None, raw_status=raw,
        seconds=time.perf_counter() - t0,
        solve_seconds=float(getattr(stats, "solve_time", 0.0) or 0.0),
        iterations=getattr(stats, "num_iters", None),
    )
    if status is Status.PROVED and prob.value is not None and np.isfinite(prob.value):
        res.raw_value = float(prob.value)
    elif status is Status.PROVED:
        res.status, res.message = Status.UNKNOWN, "solver returned no finite value"
    return status, msg, res


# ----------------------------------------------------------------------------------------
# Metric synthesis and the LMI observer
# ----------------------------------------------------------------------------------------

def _sym(M: Any) -> Any:
    return 0.5 * (M + M.T)


def metric_sdp(vertices: np.ndarray, Z: np.ndarray, lam: float, *, margin: float,
               kappa_max: float) -> SdpResult:
    """Constant P with Z^T (He{P J} + 2 lam P) Z <= -margin I at every vertex J, I <= P <= kappa I.

    vertices [V, n, n] (Jacobian matrices whose convex hull contains Jf over the region),
    Z [n, d] orthonormal kernel basis of dh. Minimises kappa (>= cond P). Variables: P, kappa.
    """
    t0 = time.perf_counter()
    V, n, _ = vertices.shape
    d = Z.shape[1]
    P = cp.Variable((n, n), symmetric=True, name="P")
    kappa = cp.Variable(name="kappa")
    cons = [P >> np.eye(n), kappa * np.eye(n) - P >> 0, kappa <= kappa_max]
    if d == 1:
        z = Z[:, 0]
        # z^T He{P J} z = sum_ij P_ij (J z z^T)_ij (symmetrised), linear in P: one row per vertex.
        A = 0.5 * (np.einsum("vik,k,j->vij", vertices, z, z)
                   + np.einsum("vjk,k,i->vij", vertices, z, z))  # [V, n, n]
        A = A + 2.0 * lam * np.outer(z, z)[None]
        rows = A.reshape(V, n * n)
        cons.append(rows @ cp.vec(P, order="C") <= -margin)
    else:
        for J in vertices:
            S = Z.T @ _sym(P @ J) @ Z + 2.0 * lam * (Z.T @ P @ Z)
            cons.append(-_sym(S) - margin * np.eye(d) >> 0)
    prob = cp.Problem(cp.Minimize(kappa), cons)
    status, _, res = solve(prob, t0)
    if status is Status.PROVED and P.value is not None:
        Pv = 0.5 * (P.value + P.value.T)
        res.variables = {"P": Pv, "kappa": float(kappa.value)}
        res.value = float(kappa.value)
    return res


def observer_sdp(vertices: np.ndarray, C: np.ndarray, lam: float, *, margin: float,
                 kappa_max: float, gain_max: float | None = None,
                 objective: str = "kappa") -> SdpResult:
    """Joint LMI observer: He{P J - Y C} + 2 lam P <= -margin I at every vertex J.

    I <= P <= kappa I, ||Y||_2 <= gain_max (when given); K = P^-1 Y. `objective`: "kappa"
    (minimise the condition bound) or "gain" (minimise ||Y||_2 + kappa / kappa_max).
    vertices [V, n, n], C [p, n] (constant output Jacobian). Variables: P, Y, K, kappa.
    """
    t0 = time.perf_counter()
    V, n, _ = vertices.shape
    p = C.shape[0]
    P = cp.Variable((n, n), symmetric=True, name="P")
    Y = cp.Variable((n, p), name="Y")
    kappa = cp.Variable(name="kappa")
    cons = [P >> np.eye(n), kappa * np.eye(n) - P >> 0, kappa <= kappa_max]
    if gain_max is not None:
        cons.append(cp.sigma_max(Y) <= gain_max)
    for J in vertices:
        S = _sym(P @ J - Y @ C) + 2.0 * lam * P
        cons.append(-_sym(S) - margin * np.eye(n) >> 0)
    if objective == "kappa":
        obj = cp.Minimize(kappa)
    elif objective == "gain":
        obj = cp.Minimize(cp.sigma_max(Y) + kappa / kappa_max)
    else:
        raise ValueError(f"objective must be 'kappa' or 'gain'; got {objective!r}")
    prob = cp.Problem(obj, cons)
    status, _, res = solve(prob, t0)
    if status is Status.PROVED and P.value is not None and Y.value is not None:
        Pv = 0.5 * (P.value + P.value.T)
        Yv = np.asarray(Y.value)
        res.variables = {"P": Pv, "Y": Yv, "K": np.linalg.solve(Pv, Yv),
                         "kappa": float(kappa.value)}
        res.value = float(kappa.value)
    return res


class DissipationSdp:
    """The linear observer for the noise-to-error bound, built once for a set of vertices and
    solved at any rate alpha: minimise mu over (P, Y = P K, mu) subject to P >= I and, at
    every vertex J,

        [[J^T P + P J - C^T Y^T - Y C + alpha P, -Y], [-Y^T, -mu I]] <= -margin I.

    With e' = (J - K C) e - K v and V = e^T P e this is V' <= -alpha V + mu ||v||^2 for every
    J in the vertices' convex hull (the block is affine in J), so ||e|| tends to at most
    vbar sqrt(mu / (alpha lam_min(P))). P >= I fixes the scale (P, Y, mu are homogeneous), so
    minimising mu minimises mu / lam_min(P). vertices [V, n, n], C [p, n]; ||Y||_2 <=
    gain_max when given. alpha is a cvxpy parameter (alpha P is parameter-affine), so the
    problem is compiled once and each `solve` only re-solves. Variables of an answer: P, Y,
    K = P^-1 Y, mu; value mu.
    """

    def __init__(self, vertices: np.ndarray, C: np.ndarray, *, margin: float,
                 gain_max: float | None = None) -> None:
        V, n, _ = vertices.shape
        p = C.shape[0]
        self.n, self.p = n, p
        self.P = cp.Variable((n, n), symmetric=True, name="P")
        self.Y = cp.Variable((n, p), name="Y")
        self.mu = cp.Variable(name="mu")
        self.alpha = cp.Parameter(nonneg=True, name="alpha")
        P, Y, mu = self.P, self.Y, self.mu
        cons = [P >> np.eye(n)]
        if gain_max is not None:
            cons.append(cp.sigma_max(Y) <= gain_max)
        eye = np.eye(n + p)
        for J in vertices:
            top = 2.0 * _sym(P @ J - Y @ C) + self.alpha * P
            M = cp.bmat([[top, -Y], [-Y.T, -mu * np.eye(p)]])
            cons.append(-_sym(M) - margin * eye >> 0)
        self.problem = cp.Problem(cp.Minimize(mu), cons)

    def solve(self, alpha: float) -> SdpResult:
        t0 = time.perf_counter()
        self.alpha.value = float(alpha)
        status, _, res = solve(self.problem, t0)
        P, Y, mu = self.P, self.Y, self.mu
        if status is Status.PROVED and P.value is not None and Y.value is not None:
            Pv = 0.5 * (P.value + P.value.T)
            Yv = np.asarray(Y.value).reshape(self.n, self.p)
            res.variables = {"P": Pv, "Y": Yv, "K": np.linalg.solve(Pv, Yv),
                             "mu": float(mu.value)}
            res.value = float(mu.value)
        return res


def dissipation_sdp(vertices: np.ndarray, C: np.ndarray, alpha: float, *, margin: float,
                    gain_max: float | None = None) -> SdpResult:
    """`DissipationSdp` solved at one rate alpha."""
    return DissipationSdp(vertices, C, margin=margin, gain_max=gain_max).solve(alpha)
