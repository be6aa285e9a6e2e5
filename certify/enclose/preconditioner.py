"""The congruence A = M D M^T and the conversion back to lam_max(D).

By Sylvester's law of inertia D <= 0 iff M D M^T <= 0 for every invertible M, so the float
error of M costs tightness, never soundness. Q = M P and C = M P M^T are interval products
(outward rounded). Three choices of M (`candidate_preconditioners`): M ~ L^-1 (P = L L^T, the
generalised eigenvalue; the rate prover needs it), M = I (D itself) and M = diag(P_ii^-1/2).
Which one gives the tightest box bounds depends on the problem (on the chain families M = I
closes more boxes of a given size than M ~ L^-1, on others the reverse), so the
MPDI prover picks one by probing (`certify.enclose.mpdi.choose_preconditioner`).

Back to D (`to_lam_max_D`): D = M^-1 A M^-T, so A <= a I gives lam_max(D) <= a / sigma_min(M)^2
for a >= 0 and <= a / ||M||_2^2 for a < 0; `pos_scale` and `neg_scale` are upper bounds of
1 / sigma_min(M)^2 and lower bounds of 1 / ||M||_2^2 (exact for M = I and for a diagonal M up
to one rounding, taken outward; for the float M ~ L^-1 from C = M P M^T itself: c_min I <= C <=
lam_max(P) M M^T gives 1 / sigma_min(M)^2 <= lam_max(P) / c_min, and lam_min(P) M M^T <= C <=
c_max I gives 1 / ||M||_2^2 >= lam_min(P) / c_max, with lam_max(P), lam_min(P) bounded by the
certified point eigenvalue bound of `certify.arith.eigen` and c_min, c_max from the interval C:
no assumption on how accurately M inverts L).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from certify.arith.eigen import lam_max_upper_point, rho_upper
from certify.arith.interval_ops import const_lam, iadd, isym, point
from certify.arith.intervals import Interval, down, imatmul, imul, up


@dataclass
class Preconditioner:
    """M, Q = M P and C = M P M^T (as intervals) for the congruence A = M D M^T."""

    identity: bool
    M: torch.Tensor
    Q: Interval
    C: Interval
    c_min: float  # lower bound of lam_min(C)
    c_max: float  # upper bound of lam_max(C)
    pos_scale: float = 1.0  # >= 1 / sigma_min(M)^2
    neg_scale: float = 1.0  # <= 1 / ||M||_2^2
    kind: str = "cholesky"  # "identity", "cholesky", "none" (M = I, P != I), "diagonal"
    #: M Q M^T for the problem's constant term Q (`Problem.shift`), outward rounded; None: Q = 0
    shift: Interval | None = None
    # (M = diag(P_ii^-1/2)) or "scaled" (M = diag(|D_ii|^-1/2), `certify.enclose.mpdi`)


def make_preconditioner(P: torch.Tensor) -> Preconditioner:
    P = P.to(torch.float64)
    n = P.shape[0]
    eye = torch.eye(n, dtype=torch.float64, device=P.device)
    if torch.equal(P, eye):
        return Preconditioner(True, eye, point(eye), point(eye), 1.0, 1.0, 1.0, 1.0,
                              "identity")
    L = torch.linalg.cholesky(P)
    M = torch.linalg.solve_triangular(L, eye, upper=False)
    Q = imatmul(point(M), point(P))
    C = imatmul(Q, point(M.T))
    dev = Interval(C.lo - eye, C.hi - eye)
    e = float(rho_upper(torch.maximum(dev.lo.abs(), dev.hi.abs())))
    c_min = math.nextafter(1.0 - e, -math.inf)  # scalars: one ulp outward, as down / up
    c_max = math.nextafter(1.0 + e, math.inf)
    p_max = float(lam_max_upper_point(P))  # >= lam_max(P)
    p_min = float(-lam_max_upper_point(-P))  # <= lam_min(P)
    pos = math.nextafter(p_max / c_min, math.inf) if c_min > 0 else float("inf")
    neg = max(0.0, math.nextafter(p_min / c_max, -math.inf))
    return Preconditioner(False, M, Q, C, c_min, c_max, pos, neg)


def diagonal_preconditioner(P: torch.Tensor, m: torch.Tensor, kind: str = "diagonal"
                            ) -> Preconditioner:
    """M = diag(m) (m > 0, used exactly as given): M = I is `m = 1` (D itself)."""
    P = P.to(torch.float64)
    m = m.to(torch.float64)
    M = torch.diag(m)
    Q = imatmul(point(M), point(P))
    C = imatmul(Q, point(M.T))
    mmin, mmax = m.min(), m.max()  # float64 scalars
    pos = float(up(1.0 / down(mmin * mmin)))
    neg = float(down(1.0 / up(mmax * mmax)))
    return Preconditioner(False, M, Q, C, 0.0, float("inf"), pos, neg, kind)


def candidate_preconditioners(P: torch.Tensor) -> list[Preconditioner]:
    """The choices of M tried for the MPDI prover (P = I: the identity only)."""
    P = P.to(torch.float64)
    first = make_preconditioner(P)
    if first.identity:
        return [first]
    n = P.shape[0]
    return [first, diagonal_preconditioner(P, torch.ones(n, dtype=torch.float64, device=P.device),
                                                   "none"),
            diagonal_preconditioner(P, P.diagonal().rsqrt())]


def with_shift(pc: Preconditioner, Q: torch.Tensor | None) -> Preconditioner:
    """`pc` carrying M Q M^T (an interval enclosure, `imatmul` rounds outward) for the
    constant term Q of D; `pc` itself when Q is None."""
    if Q is None:
        return pc
    Q = Q.to(torch.float64)
    if pc.identity:
        S = point(Q)
    else:
        S = imatmul(imatmul(point(pc.M), point(Q)), point(pc.M.T.contiguous()))
    return dataclasses.replace(pc, shift=S)


def constant_term(pc: Preconditioner, lam: float) -> Interval:
    """M (2 lam P + Q) M^T as an interval: 2 lam C, plus `pc.shift` when the problem has a
    constant term Q. Every stage adds this same enclosure to its bound of He{Q_pc J M^T}."""
    lamC = imul(pc.C, const_lam(2.0 * lam, pc.C))
    return lamC if pc.shift is None else iadd(lamC, pc.shift)


def congruence(pc: Preconditioner, Jm: Interval) -> Interval:
    """He{Q J M^T} for interval J [B, n, n] (or [B, d, n, n] stacked)."""
    if pc.identity:
        return isym(Jm)
    QJ = imatmul(Interval(pc.Q.lo.expand_as(Jm.lo), pc.Q.hi.expand_as(Jm.hi)), Jm)
    MT = pc.M.T.expand_as(Jm.lo)
    return isym(imatmul(QJ, point(MT)))


def to_lam_max_D(upper_A: torch.Tensor, P: torch.Tensor, pc: Preconditioner) -> torch.Tensor:
    """Convert a bound on lam_max(M D M^T) to one on lam_max(D) (same sign; D = M^-1 A M^-T;
    `P` is kept for the callers: the scales were fixed when `pc` was made)."""
    if pc.identity:
        return upper_A
    return torch.where(upper_A >= 0, up(upper_A * pc.pos_scale), up(upper_A * pc.neg_scale))

