"""Sound lower bounds of the checked quantities at concrete points: what makes a witness.

A sampled float64 value is not evidence: the 2x2 closed form or LAPACK can err by about
u ||D||, so a tie (exact lam_max(D) = -1e-17) can come out as +4e-16. A point counts as a
counterexample (VIOLATED / FAILED) only when a SOUND LOWER bound of the quantity there is
> 0 (or >= 0 where the condition is "<= 0 fails"). Otherwise it is a near-tie: the caller
keeps searching or says UNKNOWN.

How the bounds are made sound:

- the matrix (D, He{P J}, dk/dy, ...) is evaluated on the degenerate box [z, z] with the
  interval machinery of `certify.enclose` / `certify.arith.intervals` (outward rounding, see
  `certify.arith.intervals.ROUNDING`), so the exact matrix at z lies inside the interval matrix;
- lam_max(A) >= v^T A v / v^T v for every v != 0 and every symmetric A in the interval
  matrix: v is a float eigenvector of the midpoint (any v is valid, a good one is tight), the
  numerator is evaluated in interval arithmetic (its lower end taken) and divided by an upper
  (numerator > 0) or lower (numerator <= 0) bound of ||v||^2, rounded down; the diagonal
  entries (v = e_i) are candidates too;
- norms: ||J||_2 >= ||J u|| / ||u|| for any float u, with ||J u|| bounded below by the
  magnitude-minimum of the interval vector J u.

NaN or Inf anywhere gives NaN, which never counts as a witness.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from certify.arith.intervals import Interval, down, imatmul, up
from certify.spec.enclosures import jacobian_h_enclosure

_F64 = torch.float64
_NAN = float("nan")


def is_witness(sound_lower: float | None, strict: bool = True) -> bool:
    """True when a sound lower bound decides a violation: > 0 (or >= 0 when not strict)."""
    if sound_lower is None or not math.isfinite(sound_lower):
        return False
    return sound_lower > 0 if strict else sound_lower >= 0


def _finite_rows(A: Interval) -> torch.Tensor:
    flat_lo = A.lo.reshape(A.lo.shape[0], -1)
    flat_hi = A.hi.reshape(A.hi.shape[0], -1)
    return torch.isfinite(flat_lo).all(-1) & torch.isfinite(flat_hi).all(-1)


def quadratic_form(A: Interval, v: torch.Tensor) -> Interval:
    """Enclosure of v^T A v for interval matrices A [B, n, n] and point vectors v [B, n]."""
    row = Interval(v[:, None, :], v[:, None, :])
    col = Interval(v[:, :, None], v[:, :, None])
    out = imatmul(imatmul(row, A), col)
    return Interval(out.lo[:, 0, 0], out.hi[:, 0, 0])


def rayleigh_lower(A: Interval) -> torch.Tensor:
    """Sound lower bound of lam_max(S) for every symmetric S in the interval matrix A [B, n, n].

    Best of the diagonal lower ends and the Rayleigh quotient at a float eigenvector of the
    midpoint; NaN where A has a non-finite entry.
    """
    B = A.lo.shape[0]
    ok = _finite_rows(A)
    lo = torch.where(ok[:, None, None], A.lo, torch.zeros_like(A.lo))
    hi = torch.where(ok[:, None, None], A.hi, torch.zeros_like(A.hi))
    A = Interval(lo, hi)
    best = torch.diagonal(A.lo, dim1=-2, dim2=-1).amax(-1)  # e_i^T S e_i = S_ii
    mid = 0.5 * (A.lo + A.hi)
    mid = 0.5 * (mid + mid.transpose(-1, -2))
    with torch.no_grad():
        _, vecs = torch.linalg.eigh(mid)
    v = vecs[..., -1]
    v = v / v.abs().amax(-1, keepdim=True).clamp_min(1e-300)  # scale away underflow
    num = quadratic_form(A, v).lo
    nrm = imatmul(Interval(v[:, None, :], v[:, None, :]), Interval(v[:, :, None], v[:, :, None]))
    nlo, nhi = nrm.lo[:, 0, 0], nrm.hi[:, 0, 0]
    q = torch.where(num > 0, down(num / nhi), down(num / nlo.clamp_min(1e-300)))
    q = torch.where(nlo > 0, q, torch.full_like(q, -math.inf))
    best = torch.maximum(best, q)
    return torch.where(ok, best, torch.full((B,), _NAN, dtype=_F64, device=best.device))


def _point_box(z: torch.Tensor, device: torch.device | str | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Degenerate boxes [z, z] (float64) on `device` (default: z's own, or the CPU)."""
    if isinstance(z, torch.Tensor):
        z = z.detach().to(dtype=_F64, device=device or z.device)
    else:
        z = torch.as_tensor(np.asarray(z, dtype=np.float64), dtype=_F64, device=device or "cpu")
    if z.ndim == 1:
        z = z[None]
    return z, z.clone()


def closed_loop_interval(problem, z: torch.Tensor) -> Interval:
    """Enclosure of J_cl = Jf(xhat) + dk/dxhat(xhat, y) at points z = (xhat, y) [B, n+p]; with
    a noise input the path certificate's J~ [B, m, m] (`certify.enclose.path`)."""
    from certify.enclose.network_interval import gain_enclosure
    from certify.enclose.path import closed_loop_box

    lo, hi = _point_box(z, problem.device)
    g, _ = gain_enclosure(problem.system, problem.network, lo, hi, order=1)
    return closed_loop_box(problem, g)


def d_interval(P: torch.Tensor, J: Interval, lam: float,
               shift: torch.Tensor | None = None) -> Interval:
    """Enclosure of D = He{P J} + 2 lam P (+ Q, `shift`, a point matrix added exactly as an
    interval) for interval J [B, n, n] and a point matrix P."""
    from certify.arith.interval_ops import const_lam, iadd, isym

    B = J.lo.shape[0]
    P = torch.as_tensor(P, dtype=_F64, device=J.lo.device)
    Pb = Interval(P.expand(B, *P.shape), P.expand(B, *P.shape))
    S = isym(imatmul(Pb, J))
    if lam != 0:
        S = iadd(S, Interval(*_scaled(Pb, const_lam(2.0 * float(lam), Pb))))
    if shift is not None:
        Q = torch.as_tensor(shift, dtype=_F64, device=J.lo.device).expand(B, *P.shape)
        S = iadd(S, Interval(Q, Q))
    return S


def _scaled(P: Interval, c: Interval) -> tuple[torch.Tensor, torch.Tensor]:
    from certify.arith.intervals import imul

    out = imul(P, c)
    return out.lo, out.hi


def mpdi_lower(problem, z: torch.Tensor, lam: float | None = None) -> torch.Tensor:
    """Sound lower bound of lam_max(D(xhat, y)) at points z [B, n+p] (rate `lam`, default the
    problem's) -> [B]; > 0 proves the MPDI fails at that point."""
    lam = problem.lam if lam is None else float(lam)
    J = closed_loop_interval(problem, z)
    return rayleigh_lower(d_interval(problem.P_t, J, lam, problem.shift_t))


def rate_sign_lower(problem, z: torch.Tensor) -> torch.Tensor:
    """Sound lower bound of lam_max(He{P J_cl}) at z [B, n+p]; >= 0 proves that the pointwise
    rate -lam_max(He{P J}, P)/2 is <= 0 there (P > 0: both have the same sign)."""
    return mpdi_lower(problem, z, lam=0.0)


def residual_lower(problem, x: torch.Tensor) -> torch.Tensor:
    """Sound lower bound of ||k(x, h(x))||_2 at points x [B, n] -> [B].

    h(x) is enclosed first; k is enclosed over {x} x [h(x)], which contains k(x, h(x))."""
    from certify.enclose.network_interval import gain_enclosure
    from certify.spec.enclosures import h_enclosure

    x, _ = _point_box(x)
    hl, hh = h_enclosure(problem.system, x, x)
    lo = torch.cat([x, hl], 1)
    hi = torch.cat([x, hh], 1)
    g, _ = gain_enclosure(problem.system, problem.network, lo, hi, order=1)
    return _norm_lower(g.k)


def _norm_lower(v: Interval) -> torch.Tensor:
    """Sound lower bound of ||w||_2 over the interval vector v [B, m]."""
    ok = torch.isfinite(v.lo).all(-1) & torch.isfinite(v.hi).all(-1)
    m = torch.where(ok[:, None], v.mig(), torch.zeros_like(v.lo))
    # scale by a power of two (exact) so that the squares neither overflow nor underflow
    e = torch.frexp(m.amax(-1, keepdim=True).clamp_min(2.0 ** -1000)).exponent
    m = torch.ldexp(m, -e)
    s = down(down(m * m).sum(-1) * (1.0 - 2.0 ** -50 * (v.lo.shape[-1] + 2)))
    out = torch.ldexp(down(torch.sqrt(s.clamp_min(0.0))), e[:, 0])
    out = down(out).clamp_min(0.0)  # ldexp is exact unless it underflows: one ulp covers it
    return torch.where(ok, out, torch.full_like(out, _NAN))


def dk_dy_norm_lower(problem, z: torch.Tensor) -> torch.Tensor:
    """Sound lower bound of ||dk/dy(xhat, y)||_2 at points z [B, n+p] -> [B]: ||J u|| / ||u||
    with u the top right singular vector of the midpoint."""
    from certify.enclose.network_interval import gain_enclosure

    lo, hi = _point_box(z, problem.device)
    g, _ = gain_enclosure(problem.system, problem.network, lo, hi, order=1)
    J = g.dk_dy  # [B, n, p]
    ok = _finite_rows(J)
    mid = torch.where(ok[:, None, None], 0.5 * (J.lo + J.hi), torch.zeros_like(J.lo))
    with torch.no_grad():
        _, _, Vh = torch.linalg.svd(mid)
    u = Vh[:, 0, :]  # [B, p]
    u = u / u.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    Ju = imatmul(J, Interval(u[:, :, None], u[:, :, None]))
    num = _norm_lower(Interval(Ju.lo[..., 0], Ju.hi[..., 0]))
    unorm = up(torch.sqrt(up(up((u * u).sum(-1)) * (1.0 + 2.0 ** -50 * (u.shape[-1] + 2)))))
    # u has a unit entry, so ||u|| is in [1, sqrt(p)]: no overflow here
    out = down(num / unorm).clamp_min(0.0)
    return torch.where(ok, out, torch.full_like(out, _NAN))


def manifold_lower(system, P: np.ndarray | torch.Tensor, lam: float, x: torch.Tensor
                   ) -> torch.Tensor:
    """Sound lower bound of q(x) = max over unit v in ker dh(x) of v^T S v,
    S = He{P Jf(x)} + 2 lam P, at points x [B, n] -> [B].

    v = Z w with Z a float kernel basis of the midpoint of [dh(x)] and w the top float
    eigenvector of Z^T S Z; v is then projected exactly onto ker dh(x) in the analysis: with
    e = ||dh v|| / sigma_min (a bound on the distance of v to that kernel, from the interval
    dh(x) and a sound lower bound of its smallest singular value), the projection u satisfies
    u^T S u >= v^T S v - (2 e ||v|| + e^2) ||S||_F and ||u|| <= ||v||. Returns NaN when dh(x)
    may lose rank or anything is non-finite; -inf when ker dh = {0}.
    """
    from certify.spec.enclosures import jacobian_f_enclosure

    x, _ = _point_box(x)
    B, n = x.shape
    Pt = (P.to(dtype=_F64, device=x.device) if isinstance(P, torch.Tensor)
          else torch.as_tensor(np.asarray(P, dtype=np.float64), dtype=_F64, device=x.device))
    jf = Interval(*jacobian_f_enclosure(system, x, x))
    S = d_interval(Pt, jf, lam)
    Jh = Interval(*jacobian_h_enclosure(system, x, x))  # [B, p, n]
    p = Jh.lo.shape[1]
    if p >= n:
        return torch.full((B,), -math.inf, dtype=_F64, device=x.device)
    ok = _finite_rows(S) & _finite_rows(Jh)
    Smid = torch.where(ok[:, None, None], 0.5 * (S.lo + S.hi), torch.zeros_like(S.lo))
    Jmid = torch.where(ok[:, None, None], 0.5 * (Jh.lo + Jh.hi), torch.zeros_like(Jh.lo))
    with torch.no_grad():
        _, sv, Vh = torch.linalg.svd(Jmid, full_matrices=True)
        Z = Vh[:, p:, :].transpose(-1, -2)  # [B, n, n-p]
        Smid = 0.5 * (Smid + Smid.transpose(-1, -2))
        _, W = torch.linalg.eigh(Z.transpose(-1, -2) @ Smid @ Z)
    v = (Z @ W[..., -1:])[..., 0]  # [B, n]
    v = v / v.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    num = quadratic_form(S, v).lo
    nrm = imatmul(Interval(v[:, None, :], v[:, None, :]), Interval(v[:, :, None], v[:, :, None]))
    nlo, nhi = nrm.lo[:, 0, 0], nrm.hi[:, 0, 0]
    # distance of v to ker dh(x): ||dh v|| <= mag(Jh v), sigma_min(dh) >= sv_min - ||rad||_F
    Jv = imatmul(Jh, Interval(v[:, :, None], v[:, :, None]))
    jv = up(torch.sqrt(up(up((Jv.mag()[..., 0] ** 2).sum(-1)) * (1 + 2.0 ** -48))))
    rad = up(torch.maximum(Jh.hi - Jmid, Jmid - Jh.lo))
    radF = up(torch.sqrt(up((rad * rad).sum((-1, -2)) * (1 + 2.0 ** -48))))
    smin = down(sv[:, p - 1] * (1 - 2.0 ** -40) - 2.0 ** -40 * sv[:, 0] - radF)
    e = up(jv / smin)
    Smag = S.mag()
    SF = up(torch.sqrt(up((Smag * Smag).sum((-1, -2)) * (1 + 2.0 ** -48))))
    vn = up(torch.sqrt(nhi))
    loss = up(up(2.0 * e * vn + e * e) * SF)
    num = down(num - loss)
    # u = v - (component off the kernel), ||u|| in [?, ||v||]: divide a positive numerator by
    # ||v||^2 (upper), a negative one by a lower bound of ||u||^2 >= (||v|| - e)^2
    ulo = down(torch.sqrt(nlo)) - e
    q = torch.where(num > 0, down(num / nhi),
                    down(num / down(ulo.clamp_min(1e-300) ** 2)))
    bad = ~ok | ~(smin > 0) | ~(ulo > 0) | ~torch.isfinite(q)
    return torch.where(bad, torch.full_like(q, _NAN), q)


def manifold_witness_lower(system, P: np.ndarray, lam: float, x: torch.Tensor) -> float:
    """Sound lower bound of q at one point x, or NaN when h(x) is not soundly inside Y
    (then x is no witness on the output manifold)."""
    from certify.spec.enclosures import h_enclosure

    x, _ = _point_box(x)
    x = x.reshape(1, -1)
    hl, hh = h_enclosure(system, x, x)
    Y = torch.as_tensor(system.Y, dtype=_F64, device=x.device)
    if not bool(((hl >= Y[:, 0]) & (hh <= Y[:, 1])).all()):
        return _NAN
    return float(manifold_lower(system, P, lam, x)[0])


def invisible_mode_certified(system, C: np.ndarray, lam: float, x: np.ndarray,
                             mu: complex) -> bool:
    """Soundly confirm a PBH witness: a real eigenpair (mu, v) of Jf(x) with C v = 0 and
    mu >= -2 lam (then v^T (He{P Jf} + 2 lam P) v = (mu + 2 lam) v^T P v >= 0 for every
    P > 0). v is the float null vector of [Jf - mu I; C] with tiny entries snapped to 0, read
    as an exact rational vector; Jf(x) is evaluated EXACTLY by sympy at the rational point x
    (every float is a dyadic rational), and C v = 0, Jf v = mu v and mu + 2 lam >= 0 are
    decided exactly. Complex modes, or entries sympy cannot decide, give False.
    """
    import sympy

    if abs(complex(mu).imag) > 0:
        return False
    x = np.asarray(x, dtype=np.float64)
    J = system.jac_f(torch.as_tensor(x)[None])[0].numpy()
    if not np.all(np.isfinite(J)):
        return False
    n = J.shape[0]
    Cf = np.asarray(C, dtype=np.float64)
    stack = np.concatenate([J - complex(mu).real * np.eye(n), Cf])
    v = np.linalg.svd(stack)[2][-1]
    v = np.where(np.abs(v) < 1e-12 * np.abs(v).max(), 0.0, v)
    v = v / v[np.argmax(np.abs(v))]
    R = sympy.Rational
    vq = sympy.Matrix([R(float(a)) for a in v])
    subs = {s: R(float(a)) for s, a in zip(system.symbols, x)}

    def exact(e: sympy.Expr) -> sympy.Expr:  # floats are dyadic rationals: read exactly
        return e.xreplace({f: R(f) for f in e.atoms(sympy.Float)}).xreplace(subs)

    try:
        Jq = sympy.Matrix(n, n, [exact(e) for e in system.jf_expr])
        Cq = sympy.Matrix(Cf.shape[0], n, [R(float(a)) for a in Cf.ravel()])
        if any(e != 0 for e in Cq * vq):
            return False
        Jv = Jq * vq
        k = int(np.argmax(np.abs(v)))  # v_k = 1
        muq = Jv[k]
        resid = [sympy.simplify(Jv[i] - muq * vq[i]) for i in range(n)]
        if any(r.is_zero is not True for r in resid):
            return False
        margin = sympy.simplify(muq + 2 * R(float(lam)))
        return bool(margin.is_nonnegative is True)
    except (TypeError, ValueError, ZeroDivisionError):  # pragma: no cover - undecidable
        return False
