"""Sound upper bounds of lam_max for point and interval symmetric matrices (batched).

Rounding: n <= 2 closed forms rounded outward; n = 3 an approximate closed form certified by
Sylvester's criterion on mu I - S with a priori error bounds of the minors (`_lam3_certified`;
LAPACK where that fails); otherwise LAPACK eigvalsh plus a margin of
8 (n + 1) u ||A||_F (Weyl plus backward stability); spectral radii of non-negative matrices by a
Collatz-Wielandt quotient max_i (R u)_i / u_i rounded up (valid for any u > 0).
"""

from __future__ import annotations

import torch

from certify.arith.interval_ops import nan_min
from certify.arith.intervals import TINY, Interval, U, down, gamma, up, widen_down, widen_up
from certify.arith.linalg import dwarfed, eigvalsh

MAX_VERTEX_DIM = 8  # beyond 2^8 vertices per box, the first-order term joins the remainder


def lam_max_upper_point(S: torch.Tensor) -> torch.Tensor:
    """Sound upper bound of lam_max of point symmetric matrices [..., n, n] -> [...]."""
    n = S.shape[-1]
    if n == 1:
        return S[..., 0, 0]
    if n == 2:
        a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        return _lam2_upper(a, b.abs(), c)
    if n == 3 and S.numel() > 0:
        mu, ok = _lam3_certified(S)
        if bool(ok.all()):
            return mu
        flat, okf = S.reshape(-1, 3, 3), ok.reshape(-1)
        out = mu.reshape(-1).clone()
        out[~okf] = _lam_max_upper_lapack(flat[~okf])
        return out.reshape(mu.shape)
    return _lam_max_upper_lapack(S)


def lam_max_at_most(S: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Certified test of lam_max(S) <= t for point symmetric matrices S [..., n, n] (lower
    triangle used, as LAPACK) and levels t [...] -> bool [...] (True: proved; False: not
    decided; NaN/Inf anywhere never passes). One float Cholesky factorisation per matrix, no
    eigenvalues (much cheaper than an eigenvalue solver).

    Proof. X = t I - S is formed with the diagonal rounded down, x_ii = down(t - s_ii), so
    t I - S = X + (a non-negative diagonal) >= X. Let c = 2 gamma_{n+1} tr+(X) + c_u with
    tr+(X) the sum of max(x_ii, 0) rounded up, c_u = 4 n (2 n + 2 + max_i x_ii) 2^-1000, and
    Y = X - c I with its diagonal rounded down again (X - c I >= Y). If the float Cholesky
    factorisation of Y runs to completion (LAPACK potrf: info = 0, every pivot positive,
    finite factor R), then R^T R = Y + dY with |dY| <= gamma_{n+1} |R^T| |R| (Higham,
    Accuracy and Stability of Numerical Algorithms, 2nd ed., Thm 10.3: any order of the
    inner products, with or without FMA), and (|R^T||R|)_ij <= ||r_i|| ||r_j|| with
    ||r_i||^2 = y_ii + dy_ii <= y_ii / (1 - gamma_{n+1}), so ||dY||_2 <= gamma_{n+1} /
    (1 - gamma_{n+1}) tr(Y) <= 2 gamma_{n+1} tr+(X) (the trace argument of Rump, "Verification
    of positive definiteness", BIT 46 (2006) 433-452; c_u covers gradual underflow, an
    absolute error of at most 2^-1074 per product, quotient and square root, as there, with
    a factor 2^74 to spare). Hence lam_min(Y) >= -||dY||_2 >= -c, lam_min(X) >=
    lam_min(Y) + c >= 0 and lam_max(S) <= t. IEEE double arithmetic rounding to nearest
    is assumed (as everywhere in `certify.arith.intervals.ROUNDING`)."""
    n = S.shape[-1]
    S = S.to(torch.float64)
    t = torch.as_tensor(t, dtype=torch.float64, device=S.device).expand(S.shape[:-2])
    if S.numel() == 0:
        return torch.zeros(S.shape[:-2], dtype=torch.bool, device=S.device)
    diag = torch.diagonal(S, dim1=-2, dim2=-1)
    xd = down(t[..., None] - diag)  # [..., n]
    pos = xd.clamp_min(0.0)
    tr = up(pos.sum(-1) * (1.0 + 2.0 * gamma(n)))
    cu = up(4.0 * n * (2.0 * n + 2.0 + pos.amax(-1)) * 2.0**-1000)
    c = up(up(2.0 * gamma(n + 1) * tr) + cu)
    Y = -S
    Y.diagonal(dim1=-2, dim2=-1).copy_(down(xd - c[..., None]))
    L, info = torch.linalg.cholesky_ex(Y)
    # a NaN/Inf entry of Y reaches a pivot (a NaN, -inf or +inf one), so it shows on the
    # diagonal of L when LAPACK does not report it (OpenBLAS tests only pivot <= 0)
    Ld = torch.diagonal(L, dim1=-2, dim2=-1)
    return (info == 0) & torch.isfinite(Ld).all(-1) & (Ld > 0).all(-1)


def vertex_max_upper(S: torch.Tensor, t: torch.Tensor, step: torch.Tensor | None = None,
                     ladder: tuple[float, ...] = (0.25, 1.0, 4.0)
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """(upper bound of max_v lam_max(S[:, v]) [B], decided [B]) for vertex matrices
    S [B, V, n, n] and levels t [B]: every vertex is first tested against t by
    `lam_max_at_most`; decided: every vertex passed (the bound is then t). With `step` [B],
    the vertices that fail are tested again at t + k step for k in `ladder` (the first level
    passed is their bound: a value for ranking the box, not needed for the decision); only
    the vertices above every level get eigenvalue bounds (`lam_max_upper_point`)."""
    B, V = S.shape[:2]
    lv = t[:, None].expand(B, V).clone()
    ok = lam_max_at_most(S, lv)
    decided = ok.all(-1)
    todo = ~ok
    if step is not None:
        for k in ladder:
            if not bool(todo.any()):
                break
            lvl = up(t + k * step)[:, None].expand(B, V)
            passed = torch.zeros_like(todo)
            passed[todo] = lam_max_at_most(S[todo], lvl[todo])
            lv = torch.where(passed, lvl, lv)
            todo = todo & ~passed
    if bool(todo.any()):
        lv = lv.clone()
        lv[todo] = lam_max_upper_point(S[todo])
    return lv.amax(-1), decided


def _lam_max_upper_lapack(S: torch.Tensor) -> torch.Tensor:
    """LAPACK eigvalsh plus the margin 8 (n + 1) u ||S||_F (module docstring)."""
    n = S.shape[-1]
    bad = ~torch.isfinite(S).reshape(*S.shape[:-2], -1).all(-1)
    S = torch.where(bad[..., None, None], torch.zeros_like(S), S)  # LAPACK refuses NaN
    ev = eigvalsh(S)[..., -1]
    norm = torch.linalg.matrix_norm(S)  # Frobenius
    margin = 8.0 * (n + 1) * U * up(norm * (1.0 + 4.0 * n * U)) + TINY
    out = up(ev + margin)
    return torch.where(bad, torch.full_like(out, float("nan")), out)


def _lam3_certified(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(mu, ok) for symmetric 3x3 matrices [..., 3, 3] (lower triangle used, as eigvalsh):
    where ok, lam_max(S) < mu is proved; elsewhere mu is meaningless.

    mu = an approximate lam_max (trigonometric closed form) plus a relative 2^-30; the proof
    is Sylvester's criterion for mu I - S: with m_i = down(mu - s_ii) <= the exact diagonal
    (so M <= mu I - S entrywise on the diagonal, equal elsewhere), M > 0 iff its leading
    minors are positive, and each float minor is trusted only when it exceeds its rounding
    error gamma_8 * (sum of the absolute values of its terms) (at most 5 roundings per
    term; the bound itself computed with a further factor 1 + gamma_8; terms near underflow
    are refused). NaN/Inf: not ok."""
    a, b, c = S[..., 0, 0], S[..., 1, 1], S[..., 2, 2]
    d, e, f = S[..., 1, 0], S[..., 2, 0], S[..., 2, 1]
    q = (a + b + c) / 3.0
    p1 = d * d + e * e + f * f
    p2 = (a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * p1
    p = torch.sqrt(p2 / 6.0)
    ps = torch.where(p > 0, p, torch.ones_like(p))
    ba, bb, bc = (a - q) / ps, (b - q) / ps, (c - q) / ps
    bd, be, bf = d / ps, e / ps, f / ps
    det_b = ba * (bb * bc - bf * bf) - bd * (bd * bc - bf * be) + be * (bd * bf - bb * be)
    phi = torch.acos((0.5 * det_b).clamp(-1.0, 1.0)) / 3.0
    lam = torch.where(p > 0, q + 2.0 * p * torch.cos(phi), q)
    scale = a.abs() + b.abs() + c.abs() + d.abs() + e.abs() + f.abs()
    mu = up(lam + (2.0**-30) * scale + 1e-290)
    m0, m1, m2 = down(mu - a), down(mu - b), down(mu - c)
    g8 = gamma(8) * (1.0 + gamma(8))
    D2 = m0 * m1 - d * d
    e2 = g8 * (m0.abs() * m1.abs() + d * d)
    D3 = m0 * (m1 * m2 - f * f) - d * (d * m2 + f * e) - e * (d * f + m1 * e)
    per = m0.abs() * (m1.abs() * m2.abs() + f * f) + d.abs() * (d.abs() * m2.abs()
                                                                + (f * e).abs()) \
        + e.abs() * ((d * f).abs() + m1.abs() * e.abs())
    e3 = g8 * per
    # terms far from underflow (there the relative error bounds would not hold)
    ok = (m0 > 0) & (D2 - e2 > 0) & (D3 - e3 > 0) & (e2 > 1e-250) & (e3 > 1e-250) \
        & torch.isfinite(mu) & torch.isfinite(e3)
    return mu, ok


def _lam2_upper(a: torch.Tensor, babs: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Upper bound of (a+c)/2 + sqrt(((a-c)/2)^2 + b^2), rounded up (increasing in a, c, |b|).

    Where a negative diagonal entry dwarfs the others (`certify.arith.linalg.dwarfed`: -1e39
    beside -0.5, where this form rounds to about +1e23), the smaller of it and the same value
    written without cancellation, max(a, c) + b^2 / (d + hypot(d, b)) with d = |a - c| / 2:
    d and the hypot rounded down (the libm result widened by LIBM_ULPS), the quotient,
    product and sum rounded up, and |b| in its place (an upper bound: hypot(d, b) >= |b|)
    where d, the hypot or their sum overflows or vanishes. Elsewhere the textbook bound
    alone, bit for bit."""
    m = up(0.5 * up(a + c))
    dlt = up((a - c).abs()) * 0.5
    hyp = widen_up(torch.hypot(dlt, babs))
    out = up(m + hyp)
    swap = dwarfed(a, babs, c)
    if bool(swap.any()):
        ac, cc, bb = a[swap], c[swap], babs[swap]
        d = down((ac - cc).abs()) * 0.5
        den = down(d + widen_down(torch.hypot(d, bb)))
        ok = torch.isfinite(den) & (den > 0)
        term = torch.where(ok, torch.minimum(up(bb * up(bb / torch.where(ok, den, 1.0))), bb),
                           bb)
        top = torch.maximum(ac, cc)
        alt = torch.where(bb == 0, top, up(top + term))  # b = 0: max(a, c) itself, exact
        out = out.clone()
        out[swap] = torch.where(torch.isnan(alt), out[swap], torch.minimum(out[swap], alt))
    return out


def lam_max_upper_interval(A: Interval, level: float | None = None) -> torch.Tensor:
    """Sound upper bound of max lam_max over an interval symmetric matrix [..., n, n].

    n <= 2: exact (lam_max is increasing in the diagonal and in |b|). Otherwise the smaller of
    lam_max(centre) + rho(radius), Gershgorin and (n <= MAX_HERTZ_DIM) `hertz_upper`.

    level (a decision: only "bound <= level" matters): by interlacing, the family's max
    lam_max is at least that of each 2 x 2 principal sub-family, which is exact in closed form
    (`_lam2_upper`); where one exceeds the level no bound decides the box and the cheap
    Gershgorin bound is returned, without eigenvalues (the choice only changes a bound that
    does not decide, and saves the eigenproblems of boxes no bound closes: `bench/prove_suite.py`
    on the 2x10 four-state chain)."""
    n = A.lo.shape[-1]
    if n == 1:
        return A.hi[..., 0, 0]
    if n == 2:
        bmag = torch.maximum(A.lo[..., 0, 1].abs(), A.hi[..., 0, 1].abs())
        bmag = torch.maximum(bmag, torch.maximum(A.lo[..., 1, 0].abs(), A.hi[..., 1, 0].abs()))
        return _lam2_upper(A.hi[..., 0, 0], bmag, A.hi[..., 1, 1])
    gersh = gershgorin_upper(A)
    if level is not None and A.lo.ndim == 3:
        hopeless = _pairs_lower(A) > level
        if bool(hopeless.any()):
            keep = ~hopeless
            if bool(keep.any()):
                gersh[keep] = _interval_eig_bound(Interval(A.lo[keep], A.hi[keep]), gersh[keep])
            return gersh
    return _interval_eig_bound(A, gersh)


def _pairs_lower(A: Interval) -> torch.Tensor:
    """max over i < j of the exact max lam_max of the 2 x 2 principal sub-family (i, j) [B]:
    a lower bound (up to its upward rounding) of every upper bound of the whole family's."""
    n = A.lo.shape[-1]
    i, j = torch.triu_indices(n, n, 1)
    mag = torch.maximum(A.lo.abs(), A.hi.abs())
    bmag = torch.maximum(mag[:, i, j], mag[:, j, i])
    dg = torch.diagonal(A.hi, dim1=-2, dim2=-1)
    return _lam2_upper(dg[:, i], bmag, dg[:, j]).amax(-1)


def _interval_eig_bound(A: Interval, gersh: torch.Tensor) -> torch.Tensor:
    """The smaller of `gersh` (Gershgorin), lam_max(centre) + rho(radius) and (n <=
    MAX_HERTZ_DIM) `hertz_upper`, for n >= 3."""
    n = A.lo.shape[-1]
    c, r = A.midrad()
    c = 0.5 * (c + c.transpose(-1, -2))  # exact symmetric centre (any point matrix works)
    r = up(torch.maximum(torch.maximum(A.hi - c, c - A.lo),
                         torch.maximum(A.hi - c, c - A.lo).transpose(-1, -2)))
    cr = up(lam_max_upper_point(c) + rho_upper(r))
    best = nan_min(cr, gersh)
    if n <= MAX_HERTZ_DIM:
        best = nan_min(best, hertz_upper(c, r))
    return best


MAX_HERTZ_DIM = 6  # 2^(n-1) eigenproblems per matrix
_SIGNS: dict[tuple[int, torch.device], torch.Tensor] = {}


def _sign_patterns(n: int, device: torch.device) -> torch.Tensor:
    """z in {+-1}^n with z_1 = 1: [2^(n-1), n] on `device` (cached per device)."""
    key = (n, torch.device(device))
    if key not in _SIGNS:
        idx = torch.arange(2 ** (n - 1), device="cpu")
        bits = (idx[:, None] >> torch.arange(n - 1, device="cpu")[None, :]) & 1
        z = torch.cat([torch.ones(len(idx), 1, device="cpu"), 1.0 - 2.0 * bits], 1)
        _SIGNS[key] = z.to(dtype=torch.float64, device=device)
    return _SIGNS[key]


def hertz_upper(C: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Upper bound of lam_max(S) over all symmetric S with |S - C| <= R (entrywise) [..., n, n].

    For a unit x with sign pattern z: x^T S x <= x^T C x + |x|^T R |x|
    = x^T (C + D_z R D_z) x <= lam_max(C + D_z R D_z), and z, -z give the same matrix, so the
    maximum over the 2^(n-1) patterns with z_1 = 1 bounds the whole family (Hertz 1992: it is
    attained). C symmetric, R symmetric and >= 0. Rounding: n = 2 closed form rounded outward;
    otherwise the float sums C + z_i z_j R_ij err by at most u |C| + R entrywise, covered by
    adding 2u ||(|C| + R)||_F (Weyl), then `lam_max_upper_point`'s own margin.
    """
    n = C.shape[-1]
    if n == 1:
        return up(C[..., 0, 0] + R[..., 0, 0])
    if n == 2:
        return _lam2_upper(up(C[..., 0, 0] + R[..., 0, 0]),
                           up(torch.maximum(C[..., 0, 1].abs(), C[..., 1, 0].abs())
                              + torch.maximum(R[..., 0, 1], R[..., 1, 0])),
                           up(C[..., 1, 1] + R[..., 1, 1]))
    Z = _sign_patterns(n, C.device)  # [V, n]
    zz = Z[:, :, None] * Z[:, None, :]  # [V, n, n]
    M = C.unsqueeze(-3) + zz * R.unsqueeze(-3)  # [..., V, n, n]
    lm = lam_max_upper_point(M).amax(-1)
    margin = up(2.0 * U * torch.linalg.matrix_norm(C.abs() + R) * (1.0 + 4 * U) + TINY)
    return up(lm + margin)


def gershgorin_upper(A: Interval) -> torch.Tensor:
    n = A.lo.shape[-1]
    mag = torch.maximum(A.lo.abs(), A.hi.abs())
    eye = torch.eye(n, dtype=torch.bool, device=mag.device)
    off = torch.where(eye, torch.zeros_like(mag), mag).sum(-1)
    off = up(off * (1.0 + 2.0 * gamma(n)) + n * TINY)
    diag = torch.diagonal(A.hi, dim1=-2, dim2=-1)
    return up(diag + off).max(-1).values


def rho_upper(R: torch.Tensor, iters: int = 8) -> torch.Tensor:
    """Spectral radius bound of non-negative matrices [..., n, n] (Collatz-Wielandt, rounded up).

    rho(R) <= max_i (R u)_i / u_i for any u > 0; u from a few power iterations.
    """
    n = R.shape[-1]
    if n <= 2 and torch.equal(R, R.transpose(-1, -2)):
        return lam_max_upper_point(R).clamp_min(0.0)
    u = torch.ones(*R.shape[:-1], 1, dtype=R.dtype, device=R.device)
    for _ in range(iters):
        u = R @ u
        u = u / u.amax(-2, keepdim=True).clamp_min(1e-300)
    u = u + 1e-6  # strictly positive
    Ru = (R @ u).squeeze(-1)
    Ru = up(Ru * (1.0 + 2.0 * gamma(n)) + n * TINY)
    q = up(Ru / u.squeeze(-1)).amax(-1)
    return q



_VERTEX_CACHE: dict[tuple[int, torch.device], torch.Tensor] = {}


def cube_vertices(d: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """The 2^d vertices of [-1, 1]^d: [V, d] float64 on `device` (cached per device)."""
    key = (d, torch.device(device))
    if key not in _VERTEX_CACHE:
        idx = torch.arange(2**d, device="cpu")
        bits = (idx[:, None] >> torch.arange(d, device="cpu")[None, :]) & 1
        _VERTEX_CACHE[key] = (2.0 * bits - 1.0).to(dtype=torch.float64, device=device)
    return _VERTEX_CACHE[key]


def taylor_upper(Ac: Interval, dA: Interval, zr: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Second-order bound: max over vertices of lam_max(A(c) + sum d_m G_m) + rho(remainder).

    Ac [B, n, n] encloses A at the box centres; dA [B, d, n, n] encloses dA/dz_m over the
    boxes; zr [B, d] radii. Returns (bound [B], split score [B, d]).
    """
    B, d, n, _ = dA.lo.shape
    G, R = dA.midrad()
    G = 0.5 * (G + G.transpose(-1, -2))
    R = up(torch.maximum(torch.maximum(dA.hi - G, G - dA.lo),
                         torch.maximum(dA.hi - G, G - dA.lo).transpose(-1, -2)))
    C0, Cr = Ac.midrad()
    C0 = 0.5 * (C0 + C0.transpose(-1, -2))
    Cr = up(torch.maximum(torch.maximum(Ac.hi - C0, C0 - Ac.lo),
                          torch.maximum(Ac.hi - C0, C0 - Ac.lo).transpose(-1, -2)))
    zr4 = zr[:, :, None, None]
    rG = zr4 * G  # [B, d, n, n]
    g = gamma(d + 5)
    absum = C0.abs() + rG.abs().sum(1)
    rem = Cr + (zr4 * R).sum(1)
    rem = up(rem * (1.0 + g) + g * absum * (1.0 + g) + (d + 2) * TINY)
    if d <= MAX_VERTEX_DIM:
        V = cube_vertices(d, rG.device)  # [V, d]
        S = C0[:, None] + torch.einsum("vd,bdij->bvij", V, rG)  # [B, V, n, n]
        S = 0.5 * (S + S.transpose(-1, -2))
        lv = lam_max_upper_point(S).amax(-1)
    else:
        rem = up(rem + rG.abs().sum(1) * (1.0 + g))
        lv = lam_max_upper_point(C0)
    bound = up(lv + rho_upper(rem))
    # split score: first-order variation plus remainder, per dimension
    gn = torch.linalg.matrix_norm(rG) + torch.linalg.matrix_norm(zr4 * R)  # [B, d]
    return bound, gn

