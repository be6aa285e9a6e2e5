"""Side proofs beside the MPDI: sound upper bounds of the BC residual sup ||k(x, h(x))||,
of sup ||dk/dy||_2, and of the manifold quantity lam_max(Z^T (He{P Jf} + 2 lam P) Z) on
{h(xhat) in Y}, with the float kernel basis Z and its error bound.

Each is a maximisation `certify.search.bnb.branch_and_bound` over boxes with bounds from
`certify.enclose` / `certify.enclose.side` (outward rounding as in
`certify.arith.intervals.ROUNDING`); the cheap interval bound runs first and the linear bounds only
on boxes above the closing level (`certify.prove.mpdi.Level`). NaN/Inf leave the bound None.
Each is budgeted in boxes (`max_boxes`), with an optional wall-clock cap (`seconds` from the
call and/or a `deadline`, a `time.perf_counter()` value; None: none), as `prove_mpdi`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from certify.arith.intervals import up
from certify.enclose.side import (
    dk_dy_box_upper_crown,
    dk_dy_interval,
    manifold_enclosure,
    residual_box_upper,
    residual_box_upper_crown,
)
from certify.model.problem import Problem
from certify.progress import Progress
from certify.prove.mpdi import Level, root_box, seed_box
from certify.results import ProofStats
from certify.search.bnb import Budget, ClosingRule, Output, Schedule, branch_and_bound
from certify.search.evaluation import BoxEval
from certify.settings import DEFAULTS
from certify.spec.enclosures import h_enclosure
from certify.spec.system import System

__all__ = ["bound_residual", "bound_dk_dy", "bound_manifold_quantity",
           "kernel_basis_with_error"]

#: the box budget of the manifold bound of the pre-flight (`certify.checks.necessary`)
MANIFOLD_BOXES = 100_000


def bound_residual(problem: Problem, *, max_boxes: int = DEFAULTS.residual_boxes,
                   seconds: float | None = None, deadline: float | None = None,
                   progress: Progress | None = None, rel_tol: float = 1e-3,
                   batch: int = 1024, seeds: object | None = None
                   ) -> tuple[float | None, list[float] | None, ProofStats]:
    """Sound upper bound on sup_{x in X} ||k(x, h(x))||_2 (B&B over X; exactly 0 if structural).

    `seeds` [S, n]: points evaluated first (the residual grid's worst): their values set the
    closing level from the first round (they choose what is refined, never the bound).

    Returns (upper, worst point x found, stats); upper is None when some box stayed NaN/Inf.
    """
    if problem.structural:
        return 0.0, None, ProofStats(rounding="structural network: k(x, h(x)) = 0 exactly")
    s = problem.system
    X = torch.as_tensor(s.X, dtype=torch.float64, device=problem.device)

    level = Level(rel_tol, 1e-12)

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        ub, cen = residual_box_upper(s, problem.network, lo, hi)
        ub = level.tighten(ub, cen, lambda m: residual_box_upper_crown(
            s, problem.network, lo[m], hi[m], interval=(ub[m], cen[m]))[0])
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=cen, score=None)

    out = branch_and_bound(X[:, 0].clone(), X[:, 1].clone(), evaluate,
                           ClosingRule(rel_tol=rel_tol, tol=1e-12),
                           Budget.capped(max_boxes, seconds=seconds, deadline=deadline),
                           Schedule(batch=batch),
                           Output(progress=progress, task="residual bound", project=None),
                           seeds=seed_box(seeds, X.shape[0], problem.device))
    upper = out.upper if math.isfinite(out.upper) else None
    worst = out.best_point.tolist() if out.best_point is not None else None
    return upper, worst, out.stats


def bound_dk_dy(problem: Problem, *, max_boxes: int = DEFAULTS.lipschitz_boxes,
                seconds: float | None = None, deadline: float | None = None,
                progress: Progress | None = None, rel_tol: float = 1e-3,
                batch: int = 1024) -> tuple[float | None, ProofStats]:
    """Sound upper bound on sup over X x Y of ||dk/dy||_2 (by the Frobenius norm of the
    entry magnitudes; exact for p = 1), None when a box stayed NaN/Inf; and the proof's
    stats."""
    lo, hi = root_box(problem)

    level = Level(rel_tol, 1e-12)

    def evaluate(blo: torch.Tensor, bhi: torch.Tensor) -> BoxEval:
        iv = dk_dy_interval(problem.system, problem.network, blo, bhi)
        # where the interval bound is above the closing level: linear bounds (direct
        # networks) or Taylor models (structural ones), reusing the interval enclosure
        ub = level.tighten(iv.upper, iv.centre, lambda m: dk_dy_box_upper_crown(
            problem.system, problem.network, blo[m], bhi[m], interval=iv[m])[0])
        cen = iv.centre
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=cen, score=None)

    out = branch_and_bound(lo, hi, evaluate, ClosingRule(rel_tol=rel_tol, tol=1e-12),
                           Budget.capped(max_boxes, seconds=seconds, deadline=deadline),
                           Schedule(batch=batch),
                           Output(progress=progress, task="dk/dy bound", project=None))
    return (out.upper if math.isfinite(out.upper) else None), out.stats


def kernel_basis_with_error(C: np.ndarray) -> tuple[np.ndarray, float]:
    """Orthonormal basis Z of ker C (float) and a bound eps on its distance to an exact one."""
    p, n = C.shape
    U_, sv, Vt = np.linalg.svd(C)
    rank = int((sv > 1e-12 * max(1.0, sv.max(initial=0.0))).sum())
    Z = Vt[rank:].T  # [n, n - rank]
    if Z.shape[1] == 0:
        return Z, 0.0
    smin = sv[rank - 1] if rank > 0 else 1.0
    dist_kernel = np.linalg.norm(C @ Z, 2) / smin
    orth = np.linalg.norm(Z.T @ Z - np.eye(Z.shape[1]), 2)
    eps = 10.0 * (dist_kernel + orth) + 1e-14
    return Z, float(eps)


def bound_manifold_quantity(system: System, P: np.ndarray | torch.Tensor, lam: float, *,
                            max_boxes: int = MANIFOLD_BOXES, seconds: float | None = None,
                            deadline: float | None = None, rel_tol: float = 1e-4
                            ) -> tuple[float | None, list[float] | None]:
    """Sound upper bound of q(xhat) = lam_max(Z^T (He{P Jf} + 2 lam P) Z) over
    {xhat in X : h(xhat) in Y}, Z an orthonormal basis of ker dh/dxhat.

    Linear h only (Z constant): B&B over X with interval Jf; boxes whose h-enclosure misses
    Y are dropped. Z comes from an SVD; its distance eps to an exact orthonormal kernel basis
    is bounded from residuals (x10) and costs 3 eps ||S||_2 in the bound. Returns
    (upper, witness xhat) or (None, None) for nonlinear h; (-inf, None) if ker dh = {0}.
    """
    # h is affine iff every entry of dh/dx is a constant (checked here directly)
    if any(e.free_symbols for e in system.jh_expr):
        return None, None
    Pt = torch.as_tensor(np.asarray(P, dtype=np.float64), dtype=torch.float64)
    n = system.n
    x0 = torch.zeros(1, n, dtype=torch.float64)
    C = system.jac_h(x0)[0].numpy()
    Z, eps = kernel_basis_with_error(C)
    if Z.shape[1] == 0:
        return float("-inf"), None
    Zt = torch.as_tensor(Z, dtype=torch.float64)
    X = torch.as_tensor(system.X, dtype=torch.float64)
    Y = torch.as_tensor(system.Y, dtype=torch.float64)
    Pn = float(torch.linalg.matrix_norm(Pt, ord=2)) * (1 + 1e-12)

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        from certify.arith.intervals import Interval
        from certify.spec.enclosures import jacobian_f_enclosure

        ub = manifold_enclosure(system, lo, hi, Pt, lam, Zt)
        jf = Interval(*jacobian_f_enclosure(system, lo, hi))
        jmag = torch.maximum(jf.lo.abs(), jf.hi.abs())
        snorm = Pn * torch.linalg.matrix_norm(jmag) + 2.0 * abs(lam) * Pn  # >= ||S||_2
        ub = up(ub + 3.0 * eps * snorm * (1 + 1e-9))
        hl, hh = h_enclosure(system, lo, hi)
        miss = ((hh < Y[:, 0]) | (hl > Y[:, 1])).any(-1)
        ub = torch.where(miss, torch.full_like(ub, -math.inf), ub)
        ub = torch.where(torch.isnan(ub), ub, ub)
        c = 0.5 * (lo + hi)
        Jc = system.jac_f(c)
        S = 0.5 * (Pt @ Jc + (Pt @ Jc).transpose(-1, -2)) + 2.0 * lam * Pt
        q = torch.linalg.eigvalsh(Zt.T @ S @ Zt)[..., -1]
        hc = system.h(c)
        inside = ((hc >= Y[:, 0]) & (hc <= Y[:, 1])).all(-1)
        q = torch.where(inside, q, torch.full_like(q, -math.inf))
        return BoxEval(upper=ub, centre_value=q, score=None)

    out = branch_and_bound(X[:, 0].clone(), X[:, 1].clone(), evaluate,
                           ClosingRule(rel_tol=rel_tol, tol=1e-12),
                           Budget.capped(max_boxes, seconds=seconds, deadline=deadline),
                           Schedule(batch=256), Output(task="manifold bound", project=None))
    upper = out.upper if not math.isnan(out.upper) else None
    if upper is not None and upper == math.inf:
        upper = None
    witness = out.best_point.tolist() if out.best_point is not None else None
    return upper, witness
