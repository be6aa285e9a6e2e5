"""LipSDP-Neuron's LMI in numpy: its construction, its independent re-check, the exact
power-of-two scaling of extreme weights, and the dense primal-dual interior-point method
that solves it (the fast default route).

Split from `certify.design.sdp` (the cvxpy side, the driver and its fallbacks). The IPM's answer
is never trusted as it stands: `certify.design.lipsdp.lipsdp_neuron` rebuilds the LMI here at the
returned multipliers (`check_lipsdp_lmi`) and falls back to cvxpy + Clarabel when the IPM
fails (an exception, no strictly feasible start, or an answer that does not verify).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

_U = np.finfo(np.float64).eps


@dataclass
class IpmOutcome:
    """What the interior-point method ended with: multipliers t, rho (None if it found no
    strictly feasible start or lost feasibility), whether the gap closed, and why not."""

    converged: bool
    message: str
    t: list[np.ndarray] | None
    rho: float | None
    iterations: int = 0
    seconds: float = 0.0


def pow2_exponent(A: np.ndarray, big: float = 2.0**32) -> int:
    """e with 2^-e A well scaled (max |entry| in [1/2, 1)), or 0 when A is moderate already
    or the scaling would not be exact (an entry would lose bits by underflow)."""
    mag = float(np.abs(A).max(initial=0.0))
    if mag == 0.0 or (1.0 / big <= mag <= big):
        return 0
    e = int(np.frexp(mag)[1])
    scaled = np.ldexp(A, -e)
    return e if np.array_equal(np.ldexp(scaled, e), A) else 0


def norm2_upper(A: np.ndarray) -> float:
    """A sound upper bound of ||A||_2 (SVD relative error covered by 64 (m + n) u)."""
    if A.size == 0 or not np.any(A):
        return 0.0
    m, n = A.shape
    return float(np.linalg.norm(A, 2) * (1.0 + 64.0 * (m + n) * _U) + 1e-300)


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


def _top_eig(M: np.ndarray) -> float:
    """Largest eigenvalue of a symmetric matrix (LAPACK syevd, one thread)."""
    with one_thread():
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


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run dense small-matrix algebra on one thread (restored afterwards).

    At N ~ 150 threading buys nothing, and on a loaded machine oversubscription makes each
    factorisation many times slower (`bench/lipsdp.py`).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def schur_rho(M0: np.ndarray, Aa: np.ndarray, t: np.ndarray, p: int) -> float | None:
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


def lipsdp_pdip(Ws: Sequence[np.ndarray], M0: np.ndarray, W_out_norm: float, delta: float,
                rel_gap: float = 1e-9, max_iter: int = 80) -> IpmOutcome:
    """LipSDP-Neuron by a primal-dual interior-point method (HKM direction, Mehrotra
    predictor-corrector) on the dense LMI, exploiting that it has few variables.

    Ws: the hidden layers [W0y, W1, ..]; M0: the full LMI M(0, 0) (`lipsdp_lmi`
    at zero multipliers, output term included); W_out_norm: ||W_out||_2 (for the start).
    Dual form: maximise -rho s.t. S = -M(t, rho) - delta diag(0, I) >= 0 with y = (t, rho),
    only sum n_i + 1 of them; the Schur matrix H_ij = tr(F_i X F_j S^-1) is built from dense
    N x N products using the rank-2 structure F_k = e_k a_k^T + a_k e_k^T (a_k = row of the
    weight producing neuron k, minus e_k). About 30 iterations of a few milliseconds each
    at N = 151, where Clarabel's KKT system carries a dense svec(k)^2 block per PSD cone
    (k = 61 for 5x30: about two seconds per iteration). The dual iterates stay strictly
    feasible (S is recomputed from y and Cholesky-checked), so the multipliers are usable
    whenever it stops; the answer is re-checked independently afterwards anyway.
    """
    t0 = time.perf_counter()
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
    M0_np = np.array(M0, dtype=np.float64)
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

    def fail(msg: str) -> IpmOutcome:
        return IpmOutcome(False, msg, None, None, seconds=time.perf_counter() - t0)

    # Strictly feasible dual start: layer-wise multipliers from norm bounds, shrunk per
    # layer while the Schur-complement rho keeps falling; rho a little above its minimum.
    norms = [float(np.linalg.norm(W, 2)) for W in Ws]
    s = np.zeros(H)
    nxt = W_out_norm * W_out_norm
    for h in range(H - 1, -1, -1):
        s[h] = 2.0 * nxt + 1e-3 * (1.0 + nxt) + 2.0 * delta
        nxt = s[h] * norms[h] ** 2
    best_t = np.repeat(s, widths)
    best_r = schur_rho(M0_np, Aa_np, best_t, p)
    if best_r is None:
        return fail("no strictly feasible start found")
    for h in range(H - 1, -1, -1):
        for _ in range(40):
            trial = best_t.copy()
            trial[offs[h + 1] - p:offs[h + 2] - p] *= 0.5
            r = schur_rho(M0_np, Aa_np, trial, p)
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
    yn = y.numpy()
    ts = [yn[int(offs[i + 1] - p):int(offs[i + 2] - p)].copy() for i in range(H)]
    return IpmOutcome(converged, "solved" if converged else
                      "interior point stopped before the gap closed", ts, rho, iterations=it,
                      seconds=time.perf_counter() - t0)
