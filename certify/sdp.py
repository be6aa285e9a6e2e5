"""Semidefinite programs (cvxpy + Clarabel): LipSDP-Neuron, metric synthesis, LMI observer.

The only module that imports cvxpy. Every problem returns an `SdpResult`; the solver's
native outcome is mapped onto `Status` and anything inaccurate or unrecognised fails
closed (UNKNOWN, never a bound). Solver answers are never trusted as they stand: LipSDP is
re-checked on the full LMI rebuilt in numpy (`check_lipsdp_lmi`), the metric problems by
their callers at every vertex.

LipSDP-Neuron (Fazlyab et al. 2019) for the MLP in y with xhat frozen,

    y -> x1 = phi(W0y y + c0) -> ... -> xH = phi(W_{H-1} x_{H-1} + c) -> out = Wo xH + K y,

phi slope-restricted in [0, 1], gives one LMI M(t, rho) <= 0 in the stacked increments
(dy, dx1, ..., dxH) (another sector [alpha, beta], `slope=`: alpha >= 0 is solved as [0, 1]
with the hidden weights scaled by beta; alpha < 0 adds -2 alpha beta W^T T W on the
(i-1, i-1) blocks and scales T W by alpha + beta, solved by Clarabel; the re-check always
rebuilds the [alpha, beta] LMI on the unscaled weights):

    M = -rho E00 + [K Wo]^T [K Wo] (on the dy, dxH blocks)
        + sum_i ( -2 T_i on (i, i);  T_i W_{i-1} on (i, i-1) and its transpose ),

and then sqrt(rho) bounds the L2 -> L2 Lipschitz constant for every xhat (biases do not
enter). M is block-tridiagonal plus the (dy, dxH) corner; adding dy to every clique makes
the sparsity graph a fan, which is chordal with maximal cliques {dy, dx_{c-1}, dx_c},
c = 2..H. By Agler's theorem M <= 0 iff M is a sum of clique-supported NSD pieces, so the
solver sees H-1 LMIs of size p + n_{c-1} + n_c (61 for 5x30, p = 1) instead of one of size
p + sum n_i (151) (the "Chordal-LipSDP" idea of Xue et al. 2022).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.results import Status


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


def _solve(prob: cp.Problem, t0: float, **solver_opts: Any) -> tuple[Status, str, SdpResult]:
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
# LipSDP-Neuron
# ----------------------------------------------------------------------------------------

def lipsdp_lmi(Ws: Sequence[np.ndarray], W_out: np.ndarray, K: np.ndarray | None,
               t: Sequence[np.ndarray], rho: float,
               slope: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """The full LipSDP-Neuron matrix M(t, rho) in numpy (size p + sum n_i); M <= 0 proves L.

    Ws = [W0y, W1, ..., W_{H-1}] (each producing a hidden layer), W_out [m, n_H], K [m, p]
    (a linear skip term K y, or None), t = [t_1..t_H] the neuron multipliers (>= 0),
    slope = the activation's sector [alpha, beta].
    """
    sa, sb = float(slope[0]), float(slope[1])
    p = Ws[0].shape[1]
    widths = [W.shape[0] for W in Ws]
    offs = np.cumsum([0, p, *widths])
    N = int(offs[-1])
    M = np.zeros((N, N))
    M[:p, :p] -= rho * np.eye(p)
    for i, (W, ti) in enumerate(zip(Ws, t)):
        r = slice(offs[i + 1], offs[i + 2])
        c = slice(offs[i], offs[i + 1])
        TW = ti[:, None] * W
        M[r, c] += (sa + sb) * TW
        M[c, r] += (sa + sb) * TW.T
        M[r, r] -= 2.0 * np.diag(ti)
        if sa * sb != 0.0:
            M[c, c] -= (2.0 * sa * sb) * (W.T @ TW)
    Kx = np.zeros((W_out.shape[0], p)) if K is None else np.asarray(K, dtype=np.float64)
    O = np.concatenate([Kx, W_out], axis=1)  # acts on (dy, dxH)
    idx = np.r_[0:p, offs[-2]:offs[-1]]
    M[np.ix_(idx, idx)] += O.T @ O
    return M


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Run dense small-matrix algebra on one thread (restored afterwards).

    At N ~ 150 threading buys nothing and, on a loaded 2-core machine, oversubscription
    made each factorisation ~40x slower (measured: 0.27 s vs 6 ms for the same step).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _top_eig(M: np.ndarray) -> float:
    """Largest eigenvalue of a symmetric matrix (LAPACK syevd, one thread)."""
    with _one_thread():
        return float(torch.linalg.eigvalsh(torch.as_tensor(M, dtype=torch.float64))[-1])


def _check_tolerance(M: np.ndarray, O: np.ndarray) -> float:
    """How negative lam_max(M) must be to survive rounding in building M and in eigvalsh.

    The entries of M carry one rounding each except the O^T O block, whose dot products
    err by at most gamma_m |O|^T |O|; LAPACK's symmetric eigensolver errs by a small
    multiple of N u ||M||_2. Eight times N u (||M||_F + || |O|^T|O| ||_F) covers both.
    """
    N = M.shape[0] + O.shape[0]
    absO = np.abs(O)
    return 8.0 * N * _U * (np.linalg.norm(M) + np.linalg.norm(absO.T @ absO)) + 1e-300


def check_lipsdp_lmi(Ws: Sequence[np.ndarray], W_out: np.ndarray, K: np.ndarray | None,
                     t: Sequence[np.ndarray], rho: float, max_inflations: int = 12,
                     slope: tuple[float, float] = (0.0, 1.0)
                     ) -> tuple[float | None, float, float]:
    """Rebuild M at (max(t, 0), rho) and inflate rho until lam_max(M) <= -tolerance.

    Returns (rho_verified or None, lam_max at it (or at the last try), tolerance). Negative
    multipliers would void the S-procedure, so they are clipped to zero first. Raising rho
    only lowers the (dy, dy) block; when the hidden block is negative definite the smallest
    feasible rho is the Schur complement's lam_max, used as the first inflation target.
    """
    t = [np.maximum(np.asarray(ti, dtype=np.float64), 0.0) for ti in t]
    p = Ws[0].shape[1]
    Kx = np.zeros((W_out.shape[0], p)) if K is None else np.asarray(K, dtype=np.float64)
    O = np.concatenate([Kx, W_out], axis=1)
    rho = float(max(rho, 0.0))
    M = lipsdp_lmi(Ws, W_out, K, t, rho, slope)
    # a sector with alpha beta != 0 adds the products W^T T W: their rounding, like O^T O's
    ab = 2.0 * abs(float(slope[0]) * float(slope[1]))
    extra = sum(8.0 * M.shape[0] * _U * ab * np.linalg.norm(np.abs(W).T @ (ti[:, None] * np.abs(W)))
                for W, ti in zip(Ws, t)) if ab else 0.0
    tol = _check_tolerance(M, O) + extra
    top = _top_eig(M)
    if np.isfinite(top) and top <= -tol:
        return rho, top, tol
    # Smallest rho for these multipliers, from the Schur complement on the hidden block.
    Mhh, Mh0 = M[p:, p:], M[p:, :p]
    try:
        Lc = np.linalg.cholesky(-Mhh)
        X = np.linalg.solve(Lc, Mh0)
        rho_min = _top_eig(M[:p, :p] + rho * np.eye(p) + X.T @ X)
    except np.linalg.LinAlgError:
        return None, top, tol  # hidden block not negative definite: no rho can help
    base = max(rho, rho_min, 0.0)
    scale = max(base, 1e-12)
    for k in range(max_inflations):
        trial = base + scale * 10.0 ** (k - max_inflations + 1)  # 1e-11 .. 1 relative
        M = lipsdp_lmi(Ws, W_out, K, t, trial, slope)
        tol = _check_tolerance(M, O) + extra
        top = _top_eig(M)
        if np.isfinite(top) and top <= -tol:
            return trial, top, tol
    return None, top, tol


def _lipsdp_clarabel(Ws: list[np.ndarray], W_out: np.ndarray, Kx: np.ndarray,
                     delta: float, t0: float, slope: tuple[float, float] = (0.0, 1.0)
                     ) -> tuple[SdpResult, list[np.ndarray] | None, float | None]:
    """Chordal (fan-clique) LipSDP-Neuron through cvxpy + Clarabel. Returns (result, t, rho)."""
    apb, ab2 = float(slope[0]) + float(slope[1]), 2.0 * float(slope[0]) * float(slope[1])
    p = Ws[0].shape[1]
    H = len(Ws)
    widths = [W.shape[0] for W in Ws]
    t = [cp.Variable(w, nonneg=True, name=f"t{i + 1}") for i, w in enumerate(widths)]
    rho = cp.Variable(nonneg=True, name="rho")
    T = [cp.diag(ti) for ti in t]
    WoK = W_out.T @ Kx  # (H, 0) block of the output term
    # Targets of the diagonal hidden blocks (with the strictness margin) and (i, 0) blocks.
    Dg = [-2 * T[i] + delta * np.eye(widths[i]) for i in range(H)]
    Dg[H - 1] = Dg[H - 1] + W_out.T @ W_out
    R00 = Kx.T @ Kx - rho * np.eye(p)
    if ab2 != 0.0:  # sector [alpha, beta]: -2 alpha beta W_i^T T_i W_i on the input block of W_i
        R00 = R00 - ab2 * (Ws[0].T @ T[0] @ Ws[0])
        for i in range(H - 1):
            Dg[i] = Dg[i] - ab2 * (Ws[i + 1].T @ T[i + 1] @ Ws[i + 1])
    TW = [T[i] @ Ws[i] if apb == 1.0 else apb * (T[i] @ Ws[i]) for i in range(H)]
    constraints = []
    if H == 1:
        G = TW[0] + WoK
        constraints.append(-cp.bmat([[R00, G.T], [G, Dg[0]]]) >> 0)
    else:
        # Free splitting variables of the blocks shared by two cliques, and of (0, 0).
        S = {i: cp.Variable((widths[i], widths[i]), symmetric=True) for i in range(1, H - 1)}
        F = {i: cp.Variable((widths[i], p)) for i in range(1, H - 1)}
        R = {c: cp.Variable((p, p), symmetric=True) for c in range(1, H - 1)}
        for c in range(1, H):  # clique {y, hidden c-1, hidden c} (0-based hidden layers)
            a, b = c - 1, c
            r00 = R[c] if c < H - 1 else (R00 - sum(R.values()) if R else R00)
            ra0 = TW[0] if a == 0 else -F[a]
            rb0 = WoK if b == H - 1 else F[b]
            raa = Dg[0] if a == 0 else Dg[a] - S[a]
            rbb = Dg[H - 1] if b == H - 1 else S[b]
            rba = TW[b]
            Mc = cp.bmat([[r00, ra0.T, rb0.T], [ra0, raa, rba.T], [rb0, rba, rbb]])
            constraints.append(-Mc >> 0)
    prob = cp.Problem(cp.Minimize(rho), constraints)
    status, _, res = _solve(prob, t0)
    if status is not Status.PROVED or res.raw_value is None:
        return res, None, None
    return res, [np.asarray(ti.value, dtype=np.float64) for ti in t], float(rho.value)


def _schur_rho(M0: np.ndarray, Aa: np.ndarray, t: np.ndarray, p: int) -> float | None:
    """Smallest rho with M(t, rho) <= 0 (None if the hidden block is not negative definite)."""
    M = torch.as_tensor(M0, dtype=torch.float64).clone()
    B = torch.as_tensor(Aa * t[None, :], dtype=torch.float64)
    M[:, p:] += B
    M[p:, :] += B.T
    L, info = torch.linalg.cholesky_ex(-M[p:, p:])
    if int(info) != 0:
        return None
    X = torch.linalg.solve_triangular(L, M[p:, :p], upper=False)
    return float(torch.linalg.eigvalsh(M[:p, :p] + X.T @ X)[-1])


def _lipsdp_pdip(Ws: list[np.ndarray], W_out: np.ndarray, Kx: np.ndarray, delta: float,
                 t0: float, rel_gap: float = 1e-9, max_iter: int = 80
                 ) -> tuple[SdpResult, list[np.ndarray] | None, float | None]:
    """LipSDP-Neuron by a primal-dual interior-point method (HKM direction, Mehrotra
    predictor-corrector) on the dense LMI, exploiting that it has few variables.

    Dual form: maximise -rho s.t. S = -M(t, rho) - delta diag(0, I) >= 0 with y = (t, rho),
    only sum n_i + 1 of them; the Schur matrix H_ij = tr(F_i X F_j S^-1) is built from dense
    N x N products using the rank-2 structure F_k = e_k a_k^T + a_k e_k^T (a_k = row of the
    weight producing neuron k, minus e_k). About 30 iterations of a few milliseconds each
    at N = 151, where Clarabel's KKT system carries a dense svec(k)^2 block per PSD cone
    (k = 61 for 5x30: about two seconds per iteration). The dual iterates stay strictly
    feasible (S is recomputed from y and Cholesky-checked), so the multipliers are usable
    whenever it stops; the answer is re-checked independently afterwards anyway.
    """
    p = Ws[0].shape[1]
    widths = [W.shape[0] for W in Ws]
    H, m = len(Ws), int(sum(widths))
    N = p + m
    offs = np.cumsum([0, p, *widths])
    f64 = torch.float64
    Aa_np = np.zeros((N, m))
    for i, W in enumerate(Ws):
        cols = np.arange(offs[i + 1], offs[i + 2]) - p
        Aa_np[offs[i]:offs[i + 1], cols] = W.T
        Aa_np[offs[i + 1] + np.arange(widths[i]), cols] -= 1.0
    M0_np = lipsdp_lmi(Ws, W_out, Kx, [np.zeros(w) for w in widths], 0.0)
    M0_np[p:, p:] += delta * np.eye(m)
    Aa = torch.as_tensor(Aa_np, dtype=f64)
    C = -torch.as_tensor(M0_np, dtype=f64)  # S = C - sum y_i F_i
    ar = torch.arange(m)
    hid = ar + p
    eyeN = torch.eye(N, dtype=f64)

    def slack(y: torch.Tensor) -> torch.Tensor:
        S = C.clone()
        B = Aa * y[:m][None, :]
        S[:, p:] -= B
        S[p:, :] -= B.T
        S[:p, :p] += y[m] * torch.eye(p, dtype=f64)
        return S

    def trF(Y: torch.Tensor) -> torch.Tensor:
        """[tr(F_i Y)] for a (not necessarily symmetric) N x N matrix Y -> [m + 1]."""
        AY = Aa.T @ Y
        AYt = Aa.T @ Y.T
        return torch.cat([AY[ar, hid] + AYt[ar, hid], (-torch.trace(Y[:p, :p])).reshape(1)])

    def apply_F(dy: torch.Tensor) -> torch.Tensor:
        """sum_i dy_i F_i."""
        Mx = torch.zeros(N, N, dtype=f64)
        B = Aa * dy[:m][None, :]
        Mx[:, p:] += B
        Mx[p:, :] += B.T
        Mx[:p, :p] -= dy[m] * torch.eye(p, dtype=f64)
        return Mx

    def max_step(Z: torch.Tensor, dZ: torch.Tensor) -> float:
        L, info = torch.linalg.cholesky_ex(Z)
        if int(info) != 0:
            return 0.0
        Li = torch.linalg.solve_triangular(L, eyeN, upper=False)
        lmin = float(torch.linalg.eigvalsh(Li @ (0.5 * (dZ + dZ.T)) @ Li.T)[0])
        return 1.0 if lmin >= 0 else min(1.0, -1.0 / lmin)

    def fail(msg: str) -> tuple[SdpResult, None, None]:
        return (SdpResult(Status.ERROR, msg, None, solver="lipsdp-ipm",
                          seconds=time.perf_counter() - t0), None, None)

    # Strictly feasible dual start: layer-wise multipliers from norm bounds, shrunk per
    # layer while the Schur-complement rho keeps falling; rho a little above its minimum.
    norms = [float(np.linalg.norm(W, 2)) for W in Ws]
    s = np.zeros(H)
    nxt = float(np.linalg.norm(W_out, 2)) ** 2
    for h in range(H - 1, -1, -1):
        s[h] = 2.0 * nxt + 1e-3 * (1.0 + nxt) + 2.0 * delta
        nxt = s[h] * norms[h] ** 2
    best_t = np.repeat(s, widths)
    best_r = _schur_rho(M0_np, Aa_np, best_t, p)
    if best_r is None:
        return fail("no strictly feasible start found")
    for h in range(H - 1, -1, -1):
        for _ in range(40):
            trial = best_t.copy()
            trial[offs[h + 1] - p:offs[h + 2] - p] *= 0.5
            r = _schur_rho(M0_np, Aa_np, trial, p)
            if r is None or r >= best_r:
                break
            best_t, best_r = trial, r
    y = torch.as_tensor(np.concatenate([best_t, [best_r + 0.5 * abs(best_r) + 1e-6]]),
                        dtype=f64)
    for _ in range(60):
        if int(torch.linalg.cholesky_ex(slack(y))[1]) == 0:
            break
        y[m] = 2.0 * y[m] + 1e-6
    else:
        return fail("no strictly feasible start found")
    b = torch.zeros(m + 1, dtype=f64)
    b[m] = -1.0
    S = slack(y)
    X = eyeN * (float(torch.trace(S)) / N)
    it, converged = 0, False
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` is reported after the loop
        L, info = torch.linalg.cholesky_ex(S)
        if int(info) != 0:
            return fail("lost dual feasibility")
        Li = torch.linalg.solve_triangular(L, eyeN, upper=False)
        Si = Li.T @ Li
        mu = float(torch.sum(X * S)) / N
        rp = b - trF(X)
        gap = float(torch.sum(X * S))
        if gap <= rel_gap * max(abs(float(y[m])), 1e-12) and \
                float(torch.linalg.vector_norm(rp)) <= 1e-9 * (1.0 + float(y[m])):
            converged = True
            break
        AX, ASi = Aa.T @ X, Aa.T @ Si
        PXe, PSe = AX[:, p:], ASi[:, p:]
        Hm = torch.empty((m + 1, m + 1), dtype=f64)
        Hm[:m, :m] = (PXe * PSe.T + (AX @ Aa) * Si[p:, p:] + X[p:, p:] * (ASi @ Aa)
                      + PXe.T * PSe)
        htr = -((AX[:, :p] * Si[p:, :p]).sum(1) + (X[p:, :p] * ASi[:, :p]).sum(1))
        Hm[:m, m], Hm[m, :m] = htr, htr
        Hm[m, m] = torch.sum(X[:p, :p] * Si[:p, :p])
        Hm = 0.5 * (Hm + Hm.T)
        sc = torch.sqrt(torch.clamp(torch.diagonal(Hm), min=1e-300))
        Lh = None
        for reg in (0.0, 1e-14, 1e-11, 1e-8):
            Lh, inf2 = torch.linalg.cholesky_ex(Hm / sc[:, None] / sc[None, :]
                                                + reg * torch.eye(m + 1, dtype=f64))
            if int(inf2) == 0:
                break
        else:
            break

        def direction(rhs: torch.Tensor, extra: torch.Tensor | None, sigma_mu: float,
                      sc: torch.Tensor = sc, Lh: torch.Tensor = Lh, Si: torch.Tensor = Si,
                      X: torch.Tensor = X) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            """HKM search direction for the Schur right-hand side `rhs`."""
            dy = torch.cholesky_solve((rhs / sc)[:, None], Lh)[:, 0] / sc
            dS = -apply_F(dy)
            dX = sigma_mu * Si - X - X @ dS @ Si
            if extra is not None:
                dX = dX - extra
            return dy, dS, 0.5 * (dX + dX.T)

        gSi = trF(Si)
        dy_a, dS_a, dX_a = direction(b, None, 0.0)  # predictor (affine scaling)
        ap, ad = max_step(X, dX_a), max_step(S, dS_a)
        mu_aff = float(torch.sum((X + ap * dX_a) * (S + ad * dS_a))) / N
        sigma = min(1.0, max(0.0, mu_aff / mu)) ** 3
        Q = dX_a @ dS_a @ Si
        dy, dS, dX = direction(b - sigma * mu * gSi + trF(Q), Q, sigma * mu)  # corrector
        ap = min(1.0, 0.95 * max_step(X, dX))
        ad = min(1.0, 0.95 * max_step(S, dS))
        X = X + ap * dX
        X = 0.5 * (X + X.T)
        y_new = y + ad * dy
        for _ in range(30):  # keep S strictly feasible as recomputed from y
            S_new = slack(y_new)
            if int(torch.linalg.cholesky_ex(S_new)[1]) == 0:
                break
            ad *= 0.5
            y_new = y + ad * dy
        else:
            break
        y, S = y_new, S_new
    rho = float(y[m])
    res = SdpResult(Status.PROVED if converged else Status.UNKNOWN,
                    "solved" if converged else "interior point stopped before the gap closed",
                    None, solver="lipsdp-ipm", raw_status="optimal" if converged else "stalled",
                    seconds=time.perf_counter() - t0, solve_seconds=time.perf_counter() - t0,
                    iterations=it, raw_value=float(np.sqrt(max(rho, 0.0))))
    yn = y.numpy()
    ts = [yn[int(offs[i + 1] - p):int(offs[i + 2] - p)].copy() for i in range(H)]
    return res, ts, rho


def lipsdp_neuron(Ws: Sequence[np.ndarray], W_out: np.ndarray, K: np.ndarray | None = None,
                  *, method: str = "ipm", strictness: float = 1e-7,
                  slope: tuple[float, float] = (0.0, 1.0)) -> SdpResult:
    """Verified LipSDP-Neuron bound on the L2 Lipschitz constant of y -> W_out x_H + K y.

    Ws = [W0y, W1, ..., W_{H-1}] (W0y: the y-columns of the first layer), W_out [m, n_H],
    K [m, p] or None. `method`: "ipm" (default; dense primal-dual interior point, fast) or
    "clarabel" (the chordal fan-clique form through cvxpy + Clarabel; exact same LMI, about
    30 s on 5x30). Either way the full LMI is rebuilt in numpy at the returned multipliers
    (`check_lipsdp_lmi`, rho inflated until lam_max(M) <= -tolerance). `value` =
    sqrt(verified rho) rounded up; `None` (status UNKNOWN) if it cannot be verified.
    `strictness` asks the hidden block to be <= -strictness * max(1, ||W_out||^2) * I so
    that the rebuilt LMI keeps a strict margin (costs a relative ~1e-7 in the bound).
    `slope` = [alpha, beta], the activation's slope range (tanh: [0, 1]).
    """
    t0 = time.perf_counter()
    Ws = [np.asarray(W, dtype=np.float64) for W in Ws]
    W_out = np.asarray(W_out, dtype=np.float64)
    p = Ws[0].shape[1] if Ws else 0
    Kx = np.zeros((W_out.shape[0], p)) if K is None else np.asarray(K, dtype=np.float64)
    if not Ws or any(not np.all(np.isfinite(W)) for W in [*Ws, W_out, Kx]):
        return SdpResult(Status.ERROR, "LipSDP needs >= 1 hidden layer and finite weights",
                         None, seconds=time.perf_counter() - t0)
    sa, sb = float(slope[0]), float(slope[1])
    if not (np.isfinite(sa) and np.isfinite(sb) and sa <= sb and sb > 0):
        raise ValueError(f"slope must be [alpha, beta] with alpha <= beta, beta > 0; got {slope}")
    # alpha >= 0: the sector [0, beta] is the [0, 1] one for the hidden weights scaled by beta
    Wsolve = Ws if sa < 0 or sb == 1.0 else [sb * W for W in Ws]
    check_slope = (sa, sb) if sa < 0 else (0.0, sb)
    if sa < 0:
        method = "clarabel"  # the interior-point solver is written for the [0, 1] structure
    if method == "clarabel":
        delta = strictness * max(1.0, float(np.linalg.norm(W_out, 2)) ** 2)
        res, t_val, rho_val = _lipsdp_clarabel(Wsolve, W_out, Kx, delta, t0,
                                               (sa, sb) if sa < 0 else (0.0, 1.0))
    elif method == "ipm":
        delta = strictness * max(1.0, float(np.linalg.norm(W_out, 2)) ** 2)
        with _one_thread():
            res, t_val, rho_val = _lipsdp_pdip(Wsolve, W_out, Kx, delta, t0)
    else:
        raise ValueError(f"method must be 'ipm' or 'clarabel'; got {method!r}")
    if t_val is None or rho_val is None:
        return res
    res.raw_value = float(np.sqrt(max(rho_val, 0.0)))
    rho_ok, top, tol = check_lipsdp_lmi(Ws, W_out, Kx, t_val, rho_val, slope=check_slope)
    res.check_max_eig, res.check_tolerance = top, tol
    res.variables = {"t": t_val, "rho": rho_val, "rho_verified": rho_ok}
    res.seconds = time.perf_counter() - t0
    if rho_ok is None:
        res.status, res.verified, res.value = Status.UNKNOWN, False, None
        res.message = (f"LipSDP answer not verified: the rebuilt LMI has lam_max {top:.3g} > "
                       f"-{tol:.2g} and inflating rho did not repair it")
        return res
    res.status, res.verified = Status.PROVED, True
    res.value = float(np.nextafter(np.sqrt(rho_ok), np.inf))
    res.message = (f"verified: rebuilt LMI lam_max {top:.3g} <= -{tol:.2g}"
                   + (f" after raising rho by {rho_ok / rho_val - 1:.2g} (relative)"
                      if rho_ok > rho_val else ""))
    return res


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
    status, _, res = _solve(prob, t0)
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
    status, _, res = _solve(prob, t0)
    if status is Status.PROVED and P.value is not None and Y.value is not None:
        Pv = 0.5 * (P.value + P.value.T)
        Yv = np.asarray(Y.value)
        res.variables = {"P": Pv, "Y": Yv, "K": np.linalg.solve(Pv, Yv),
                         "kappa": float(kappa.value)}
        res.value = float(kappa.value)
    return res
