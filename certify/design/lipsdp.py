"""LipSDP-Neuron: a verified bound on the Lipschitz constant of the gain network in y.

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

Two routes solve the same LMI: a dense primal-dual interior point written for it
(`certify.design.lipsdp_ipm`, the default) and the chordal form through cvxpy + Clarabel
(`certify.design.sdp.solve`), the fallback. Either answer is rebuilt in numpy and verified.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from certify.design.lipsdp_ipm import (
    check_lipsdp_lmi,
    lipsdp_lmi,
    lipsdp_pdip,
    norm2_upper,
    one_thread,
    pow2_exponent,
)
from certify.design.sdp import SOLVER, SdpResult, cp, solve
from certify.results import Status

__all__ = ["lipsdp_neuron", "lipsdp_lmi", "check_lipsdp_lmi", "largest_clique"]

#: the largest clique LMI the cvxpy + Clarabel route is asked to solve: its memory grows
#: steeply with the clique size (a 6x128 network asked for gigabytes and was killed); beyond
#: this the global bound is UNKNOWN, never a crash, and the local bound is used
CLARABEL_MAX_CLIQUE = 96


def largest_clique(Ws: Sequence[np.ndarray]) -> int:
    """Size of the largest LMI of the chordal (fan-clique) form: p + n_{c-1} + n_c."""
    p = Ws[0].shape[1]
    widths = [W.shape[0] for W in Ws]
    if len(widths) == 1:
        return p + widths[0]
    return p + max(a + b for a, b in zip(widths[:-1], widths[1:]))


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
    status, _, res = solve(prob, t0)
    if status is not Status.PROVED or res.raw_value is None:
        return res, None, None
    return res, [np.asarray(ti.value, dtype=np.float64) for ti in t], float(rho.value)


def lipsdp_neuron(Ws: Sequence[np.ndarray], W_out: np.ndarray, K: np.ndarray | None = None,
                  *, method: str = "ipm", strictness: float = 1e-7,
                  slope: tuple[float, float] = (0.0, 1.0)) -> SdpResult:
    """Verified LipSDP-Neuron bound on the L2 Lipschitz constant of y -> W_out x_H + K y.

    Ws = [W0y, W1, ..., W_{H-1}] (W0y: the y-columns of the first layer), W_out [m, n_H],
    K [m, p] or None. `method`: "ipm" (default; dense primal-dual interior point, fast, with
    cvxpy + Clarabel as the fallback when it fails or its answer does not verify) or
    "clarabel" (the chordal fan-clique form through cvxpy + Clarabel; exact same LMI, about
    30 s on 5x30). Either way the full LMI is rebuilt in numpy at the returned multipliers
    (`check_lipsdp_lmi`, rho inflated until lam_max(M) <= -tolerance). `value` =
    sqrt(verified rho) rounded up; `None` (status UNKNOWN/ERROR, with the reason) if it
    cannot be verified. `strictness` asks the hidden block to be <= -strictness *
    max(1, ||W_out||^2) * I so that the rebuilt LMI keeps a strict margin.

    Degenerate and extreme networks: a zero layer anywhere on the path makes the MLP constant
    in y, so L = ||K||_2 exactly (no SDP); huge or tiny first and output layers are scaled
    by powers of two (exact) and the bound scaled back.
    `slope` = [alpha, beta], the activation's slope range (tanh: [0, 1]).
    """
    t0 = time.perf_counter()
    if method not in ("ipm", "clarabel"):
        raise ValueError(f"method must be 'ipm' or 'clarabel'; got {method!r}")
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
    if sa < 0:
        method = "clarabel"  # the interior-point solver is written for the [0, 1] structure
    if any(not np.any(W) for W in [*Ws, W_out]):
        L = norm2_upper(Kx)
        return SdpResult(Status.PROVED, "a layer is exactly zero: the MLP is constant in y, "
                         "so L = ||K||_2 exactly", L, solver="closed-form", raw_value=L,
                         verified=True, seconds=time.perf_counter() - t0)
    a = pow2_exponent(Ws[0])
    b = pow2_exponent(np.concatenate([W_out, Kx], axis=1))
    Ws_s = [np.ldexp(Ws[0], -a), *Ws[1:]]
    Wo_s, K_s = np.ldexp(W_out, -b), np.ldexp(Kx, -(a + b))
    if not np.array_equal(np.ldexp(K_s, a + b), Kx):
        a = b = 0
        Ws_s, Wo_s, K_s = Ws, W_out, Kx
    res = _lipsdp_verified(Ws_s, Wo_s, K_s, method, strictness, t0, (sa, sb))
    if res.status is Status.PROVED and res.value is not None and (a or b):
        res.value = float(np.ldexp(res.value, a + b))  # exact (or inf)
        res.raw_value = None if res.raw_value is None else float(np.ldexp(res.raw_value, a + b))
        res.message += f" (weights scaled by 2^{-a} (first layer) and 2^{-b} (output))"
        if not np.isfinite(res.value):
            res.status, res.value = Status.UNKNOWN, None
            res.message = "the LipSDP bound overflows float64 after scaling back"
    res.seconds = time.perf_counter() - t0
    return res


def _lipsdp_verified(Ws: list[np.ndarray], W_out: np.ndarray, Kx: np.ndarray, method: str,
                     strictness: float, t0: float, slope: tuple[float, float]) -> SdpResult:
    """Solve (IPM, then Clarabel if the IPM fails or does not verify) and re-check."""
    with np.errstate(over="raise", invalid="raise"):
        try:
            wn = float(np.linalg.norm(W_out, 2))
            delta = strictness * max(1.0, wn * wn)
        except (FloatingPointError, OverflowError) as exc:
            return SdpResult(Status.ERROR, f"LipSDP: weights too large for float64 ({exc})",
                             None, seconds=time.perf_counter() - t0)
    tried: list[str] = []
    res: SdpResult | None = None
    if method == "ipm":
        res = _run_solver("ipm", Ws, W_out, Kx, delta, wn, t0, slope)
        if res.status is Status.PROVED:
            return res
        tried.append(f"interior point: {res.message}")
    clique = largest_clique(Ws)
    if clique > CLARABEL_MAX_CLIQUE:
        why = (f"the chordal form's largest LMI would be {clique} x {clique} (above "
               f"{CLARABEL_MAX_CLIQUE}: Clarabel's memory grows past several GB there), so it "
               "is not tried")
        if res is None:
            return SdpResult(Status.UNKNOWN, f"LipSDP not solved: {why}", None,
                             seconds=time.perf_counter() - t0)
        res.message = f"{tried[0]}; {why}"
        return res
    fallback = _run_solver("clarabel", Ws, W_out, Kx, delta, wn, t0, slope)
    if fallback.status is Status.PROVED or res is None:
        if tried:
            fallback.message += f" (fallback after {tried[0]})"
        return fallback
    res.message = f"{tried[0]}; Clarabel fallback: {fallback.message}"
    return res


def _run_solver(which: str, Ws: list[np.ndarray], W_out: np.ndarray, Kx: np.ndarray,
                delta: float, wn: float, t0: float, slope: tuple[float, float]) -> SdpResult:
    """One solver, its answer re-checked; a solver fault becomes an ERROR result.

    Sector [alpha, beta]: alpha >= 0 is solved as the [0, 1] sector with every hidden layer's
    input weights scaled by beta (phi(z) = psi(beta z) with psi' in [0, 1]); alpha < 0 goes to
    Clarabel with the general quadratic constraint. The re-check always rebuilds the
    [alpha, beta] LMI on the unscaled weights.
    """
    sa, sb = slope
    Wsolve = Ws if sa < 0 or sb == 1.0 else [sb * W for W in Ws]
    check_slope = (sa, sb) if sa < 0 else (0.0, sb)
    try:
        if which == "ipm":
            M0 = lipsdp_lmi(Wsolve, W_out, Kx, [np.zeros(W.shape[0]) for W in Wsolve], 0.0)
            with one_thread():
                out = lipsdp_pdip(Wsolve, M0, wn, delta)
            res = SdpResult(Status.PROVED if out.converged else Status.UNKNOWN, out.message,
                            None, solver="lipsdp-ipm",
                            raw_status="optimal" if out.converged else "stalled",
                            seconds=time.perf_counter() - t0, solve_seconds=out.seconds,
                            iterations=out.iterations)
            if out.t is None:
                res.status = Status.ERROR
            t_val, rho_val = out.t, out.rho
        else:
            res, t_val, rho_val = _lipsdp_clarabel(Wsolve, W_out, Kx, delta, t0,
                                                   (sa, sb) if sa < 0 else (0.0, 1.0))
        if t_val is None or rho_val is None:
            return res
        res.raw_value = float(np.sqrt(max(rho_val, 0.0)))
        rho_ok, top, tol = check_lipsdp_lmi(Ws, W_out, Kx, t_val, rho_val, slope=check_slope)
    except (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        name = "interior point" if which == "ipm" else "Clarabel"
        return SdpResult(Status.ERROR, f"{name} failed: {type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:120] if str(exc) else ''}", None,
                         solver="lipsdp-ipm" if which == "ipm" else SOLVER,
                         seconds=time.perf_counter() - t0)
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


