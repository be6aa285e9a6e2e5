"""The congruence A = M D M^T (M ~ L^-1, P = L L^T) and the conversion back to lam_max(D).

By Sylvester's law of inertia D <= 0 iff M D M^T <= 0 for every invertible M, so the float
error of M costs tightness, never soundness. Q = M P and C = M P M^T are interval products
(outward rounded).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.bounds.eigen import rho_upper
from certify.bounds.interval_ops import isym, point
from certify.intervals import Interval, down, imatmul, up


@dataclass
class Preconditioner:
    """M, Q = M P and C = M P M^T (as intervals) for the congruence A = M D M^T."""

    identity: bool
    M: torch.Tensor
    Q: Interval
    C: Interval
    c_min: float  # lower bound of lam_min(C)
    c_max: float  # upper bound of lam_max(C)


def make_preconditioner(P: torch.Tensor) -> Preconditioner:
    P = P.to(torch.float64)
    n = P.shape[0]
    eye = torch.eye(n, dtype=torch.float64)
    if torch.equal(P, eye):
        return Preconditioner(True, eye, point(eye), point(eye), 1.0, 1.0)
    L = torch.linalg.cholesky(P)
    M = torch.linalg.solve_triangular(L, eye, upper=False)
    Q = imatmul(point(M), point(P))
    C = imatmul(Q, point(M.T))
    dev = Interval(C.lo - eye, C.hi - eye)
    e = float(rho_upper(torch.maximum(dev.lo.abs(), dev.hi.abs())))
    return Preconditioner(False, M, Q, C, float(down(torch.tensor(1.0 - e))),
                          float(up(torch.tensor(1.0 + e))))


def _congruence(pc: Preconditioner, Jm: Interval) -> Interval:
    """He{Q J M^T} for interval J [B, n, n] (or [B, d, n, n] stacked)."""
    if pc.identity:
        return isym(Jm)
    QJ = imatmul(Interval(pc.Q.lo.expand_as(Jm.lo), pc.Q.hi.expand_as(Jm.hi)), Jm)
    MT = pc.M.T.expand_as(Jm.lo)
    return isym(imatmul(QJ, point(MT)))


def to_lam_max_D(upper_A: torch.Tensor, P: torch.Tensor, pc: Preconditioner) -> torch.Tensor:
    """Convert a bound on lam_max(M D M^T) to one on lam_max(D) (same sign; D = L A L^T)."""
    if pc.identity:
        return upper_A
    ev = torch.linalg.eigvalsh(P.to(torch.float64))
    smax = float(ev[-1]) * (1 + 1e-10)
    smin = float(ev[0]) * (1 - 1e-10)
    # ||L||^2 = lam_max(P), sigma_min(L)^2 = lam_min(P); M = L^-1 up to rounding (relative
    # 1e-10 slack covers it for any well-conditioned P)
    return torch.where(upper_A >= 0, up(upper_A * smax), up(upper_A * smin))

