"""The sound prover: upper sides of the MPDI, rate, residual, dk/dy and pre-flight checks.

Every function here runs `certify.bnb.branch_and_bound` with bounds from
`certify.enclosures` (interval + second-order Taylor forms, outward rounding as in
`certify.intervals.ROUNDING`). Only a bound that covers every box of the domain is called
proved; NaN/Inf anywhere leaves the box UNKNOWN; a violation is a concrete float64 point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.bnb import Box, BoxEval, branch_and_bound
from certify.bounds.mpdi import (
    CROWN_GAIN,
    choose_preconditioner,
    direct_mixed,
    estimate_crown_gain,
)
from certify.enclosures import (
    Preconditioner,
    dk_dy_box_upper,
    dk_dy_box_upper_crown,
    make_preconditioner,
    manifold_enclosure,
    mpdi_box_bounds,
    residual_box_upper,
    residual_box_upper_crown,
    to_lam_max_D,
)
from certify.intervals import ROUNDING, up
from certify.kernels import mpdi_lam_max, pointwise_rate
from certify.problem import Problem
from certify.progress import NullProgress, Progress
from certify.results import Counterexample, ProofStats, Status
from certify.system import System
from certify.system_enclosures import h_enclosure
from certify.witness import is_witness, mpdi_lower

__all__ = [
    "ProofOutcome", "RateOutcome", "prove_mpdi", "prove_rate", "bound_residual",
    "bound_dk_dy", "bound_manifold_quantity", "ROUNDING",
]


@dataclass
class ProofOutcome:
    """Decision on max lam_max(D) <= 0 over X x Y."""

    status: Status
    upper: float  # proved upper bound on max lam_max(D) (<= 0 when PROVED; inf if none)
    lower: float  # best value found at evaluated points
    counterexample: Counterexample | None
    stats: ProofStats
    boxes: dict[str, list] = field(default_factory=dict)
    message: str = ""


@dataclass
class RateOutcome:
    """lam_cert in [lower, upper_sampled]: lower proved, upper from evaluated points."""

    lower: float | None
    upper_sampled: float
    stats: ProofStats
    worst: Counterexample | None


def _root(problem: Problem) -> tuple[torch.Tensor, torch.Tensor]:
    s = problem.system
    box = np.concatenate([s.X, s.Y], 0)
    t = torch.as_tensor(box, dtype=torch.float64)
    return t[:, 0].clone(), t[:, 1].clone()


def _seed_box(seeds: object | None, d: int) -> Box | None:
    if seeds is None:
        return None
    pts = torch.as_tensor(np.asarray(seeds, dtype=np.float64), dtype=torch.float64)
    if pts.ndim != 2 or pts.shape[1] != d or pts.shape[0] == 0:
        return None
    return Box(pts, pts.clone(), torch.zeros(pts.shape[0], dtype=torch.long))


def _mpdi_evaluator(problem: Problem, lam: float, pc: Preconditioner, taylor: bool | str = True,
                    crown: bool = True):
    n = problem.n
    P = problem.P_t
    gain = CROWN_GAIN
    rlo, rhi = _root(problem)
    if crown and taylor is True and not direct_mixed(problem, pc):
        gain = estimate_crown_gain(problem.network, rlo, rhi)

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        # boxes the plain interval bound already proves skip the Taylor / relaxation work
        bb = mpdi_box_bounds(problem, lo, hi, lam, pc=pc, taylor=taylor, crown=crown,
                             screen=0.0, crown_gain=gain, root_width=rhi - rlo)
        ub = to_lam_max_D(bb.upper, P, pc)
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        c = 0.5 * (lo + hi)
        val = mpdi_lam_max(problem.system, problem.network, P, lam, c[:, :n], c[:, n:])
        return BoxEval(upper=ub, centre_value=val, score=bb.score)

    return evaluate


def _mpdi_preconditioner(problem: Problem, lam: float, taylor: bool | str) -> Preconditioner:
    """The congruence for the MPDI proof: probed (`choose_preconditioner`) for the default
    prover, M ~ L^-1 for the plain-interval and "interval" comparison provers."""
    if taylor is True:
        return choose_preconditioner(problem, lam)
    return make_preconditioner(problem.P_t)


def mpdi_box_chunk(payload: dict, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """Executor task (module level, picklable): the MPDI box evaluation of one chunk; the
    evaluator is rebuilt from plain data once per worker process (`certify.remote`)."""
    from certify.executor import worker_cache
    from certify.parallel import torch_threads
    from certify.remote import problem_from_payload

    def build():
        base = {k: payload[k] for k in ("spec", "name", "architecture", "state", "lam", "P")}
        problem = problem_from_payload(base)
        return _mpdi_evaluator(problem, payload["prove_lam"],
                               _mpdi_preconditioner(problem, payload["prove_lam"],
                                                    payload["taylor"]), payload["taylor"],
                               payload["crown"])

    evaluate = worker_cache("mpdi-boxes:" + payload["key"], build)
    with torch_threads(1):
        return evaluate(lo, hi)


def _mpdi_remote(problem: Problem, lam: float, taylor: bool | str, crown: bool,
                 executor: object) -> tuple | None:
    """(chunk_fn, payload) for an executor whose work runs in other processes (a Dask cluster,
    even of one worker), else None (evaluate in process)."""
    if not (getattr(executor, "remote", False) or getattr(executor, "workers", 1) > 1):
        return None
    from certify.executor import payload_key
    from certify.remote import problem_payload

    payload = problem_payload(problem)
    payload.update(prove_lam=float(lam), taylor=taylor, crown=bool(crown))
    payload["key"] = payload_key(payload)
    return mpdi_box_chunk, payload


def prove_mpdi(problem: Problem, *, lam: float | None = None, seconds: float = 60.0,
               max_boxes: int = 2_000_000, progress: Progress | None = None,
               seeds: object | None = None, batch: int = 1024, taylor: bool | str = True,
               keep_leaves: int = 5000, crown: bool = True,
               executor: object | None = None) -> ProofOutcome:
    """Decide D(xhat, y) <= 0 over X x Y for rate `lam` (default problem.lam) and P.

    PROVED: every sub-box has a sound bound lam_max(D) <= 0. VIOLATED: a point (a box
    centre or one of `seeds` [m, n+p]) with float64 lam_max(D) > 0. UNKNOWN: budget spent
    (`seconds`, `max_boxes`) or NaN/Inf in some bound; `upper` is then the best bound.
    `taylor=False` uses plain interval arithmetic only (for comparison); `crown=False` keeps
    the forward Taylor models without backward linear bound propagation (the pre-issue-9 prover).
    `executor`: where the rounds' boxes are evaluated (default `current_executor()`; the
    verdict and bounds do not depend on it).
    """
    from certify.executor import current_executor

    progress = progress or NullProgress()
    lam = float(problem.lam if lam is None else lam)
    pc = _mpdi_preconditioner(problem, lam, taylor)
    lo, hi = _root(problem)
    n = problem.n
    executor = current_executor() if executor is None else executor
    out = branch_and_bound(
        lo, hi, _mpdi_evaluator(problem, lam, pc, taylor, crown), threshold=0.0, seconds=seconds,
        max_boxes=max_boxes, batch=batch, progress=progress, task="mpdi proof",
        seeds=_seed_box(seeds, lo.shape[0]), keep_leaves=keep_leaves, executor=executor,
        remote=_mpdi_remote(problem, lam, taylor, crown, executor))
    cex = None
    if out.best_point is not None:
        pt = out.best_point[None]
        v = float(mpdi_lam_max(problem.system, problem.network, problem.P_t, lam,
                               pt[:, :n], pt[:, n:])[0])
        cex = Counterexample(xhat=pt[0, :n].tolist(), y=pt[0, n:].tolist(), value=v,
                             sound_bound=float(mpdi_lower(problem, pt, lam)[0]))
    if out.violated and cex is not None and is_witness(cex.sound_bound):
        status = Status.VIOLATED
        msg = f"lam_max(D) = {cex.value:.6g} > 0 at xhat={cex.xhat}, y={cex.y}"
    elif out.complete and out.upper <= 0 and math.isfinite(out.upper):
        status = Status.PROVED
        msg = f"proved max lam_max(D) <= {out.upper:.6g} over {out.stats.boxes_processed} boxes"
        cex = None if cex is None or cex.value <= 0 else cex
    else:
        status = Status.UNKNOWN
        why = (f"{out.stuck} boxes gave NaN/Inf or hit the depth limit" if out.stuck
               else "proof budget spent")
        msg = (f"{why} (seconds={seconds}, max_boxes={max_boxes}); best upper bound "
               f"{out.upper:.6g}, proved volume {out.stats.proved_volume_fraction:.4f}; "
               "raise proof_seconds or max_boxes")
    upper = out.upper if math.isfinite(out.upper) else float("inf")
    return ProofOutcome(status=status, upper=upper, lower=out.lower, counterexample=cex,
                        stats=out.stats, boxes=out.leaves, message=msg)


def prove_rate(problem: Problem, *, seconds: float = 60.0, max_boxes: int = 2_000_000,
               progress: Progress | None = None, tol: float = 1e-9, rel_tol: float = 1e-3,
               batch: int = 1024) -> RateOutcome:
    """Proved lower bound on lam_cert = -max lam_max(He{P J_cl}, P) / 2 over X x Y.

    Direct branch and bound on phi(z) = lam_max(He{P J_cl(z)}, P) (no bisection): boxes are
    refined worst-first until the gap between the proved max and the best point is within
    max(tol, rel_tol |phi|) or the budget ends; lower = -(proved max of phi) / 2.
    The generalised eigenvalue uses the congruence with M ~ L^-1: with A0 = M He{PJ} M^T
    and C = M P M^T in [c_min, c_max] (bounded), lam_max(A0, C) <= mu / c_min (mu >= 0) or
    mu / c_max (mu < 0), mu >= lam_max(A0).
    """
    progress = progress or NullProgress()
    pc = make_preconditioner(problem.P_t)
    lo, hi = _root(problem)
    n = problem.n
    P = problem.P_t

    level = _Level(rel_tol, tol)
    gain = estimate_crown_gain(problem.network, lo, hi)

    def evaluate(blo: torch.Tensor, bhi: torch.Tensor) -> BoxEval:
        c = 0.5 * (blo + bhi)
        val = -2.0 * pointwise_rate(problem.system, problem.network, P, c[:, :n], c[:, n:])
        cv = torch.nan_to_num(val, nan=-math.inf)
        level.best = max(level.best, float(cv.max())) if len(cv) else level.best
        lv = level.value()  # phi-level -> mu-level (mu / c_min or mu / c_max <= lv)
        screen = None if not math.isfinite(lv) else (lv * pc.c_min if lv >= 0
                                                      else lv * pc.c_max)
        bb = mpdi_box_bounds(problem, blo, bhi, 0.0, pc=pc, screen=screen, crown_gain=gain,
                             root_width=hi - lo)
        mu = bb.upper
        ub = torch.where(mu >= 0, up(mu / pc.c_min), up(mu / pc.c_max))
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=val, score=bb.score)

    out = branch_and_bound(lo, hi, evaluate, threshold=None, tol=tol, rel_tol=rel_tol,
                           seconds=seconds, max_boxes=max_boxes, batch=batch,
                           progress=progress, task="rate proof")
    lower = -out.upper / 2.0 if math.isfinite(out.upper) else None
    worst = None
    upper_sampled = -out.lower / 2.0 if math.isfinite(out.lower) else float("inf")
    if out.best_point is not None:
        pt = out.best_point
        worst = Counterexample(xhat=pt[:n].tolist(), y=pt[n:].tolist(), value=upper_sampled)
    if lower is not None:
        lower = float(torch.nextafter(torch.tensor(lower), torch.tensor(-math.inf)))
    return RateOutcome(lower=lower, upper_sampled=upper_sampled, stats=out.stats, worst=worst)


class _Level:
    """The closing level of a maximisation branch and bound, tracked from the centre values
    the evaluator sees (the same points `branch_and_bound` ranks): boxes whose cheap bound is
    already at or below it skip the expensive bound. Only the choice of bound depends on it,
    never soundness."""

    def __init__(self, rel_tol: float, tol: float) -> None:
        self.best = -math.inf
        self.rel_tol, self.tol = rel_tol, tol

    def value(self) -> float:
        if not math.isfinite(self.best):
            return math.inf
        return self.best + max(self.tol, self.rel_tol * abs(self.best))

    def tighten(self, cheap: torch.Tensor, centre: torch.Tensor, tight) -> torch.Tensor:
        """min(cheap, tight(mask)) on the boxes whose cheap bound is above the level."""
        cv = torch.nan_to_num(centre, nan=-math.inf)
        if len(cv):
            self.best = max(self.best, float(cv.max()))
        work = ~(cheap <= self.value())
        if not bool(work.any()):
            return cheap
        out = cheap.clone()
        t = tight(work)
        out[work] = torch.where(torch.isnan(t) | torch.isnan(cheap[work]), cheap[work],
                                torch.minimum(cheap[work], t))
        return out


def bound_residual(problem: Problem, *, seconds: float = 30.0, max_boxes: int = 1_000_000,
                   progress: Progress | None = None, rel_tol: float = 1e-3,
                   batch: int = 1024) -> tuple[float | None, list[float] | None, ProofStats]:
    """Sound upper bound on sup_{x in X} ||k(x, h(x))||_2 (B&B over X; exactly 0 if structural).

    Returns (upper, worst point x found, stats); upper is None when some box stayed NaN/Inf.
    """
    if problem.structural:
        return 0.0, None, ProofStats(rounding="structural network: k(x, h(x)) = 0 exactly")
    s = problem.system
    X = torch.as_tensor(s.X, dtype=torch.float64)

    level = _Level(rel_tol, 1e-12)

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        ub, cen = residual_box_upper(s, problem.network, lo, hi)
        ub = level.tighten(ub, cen, lambda m: residual_box_upper_crown(
            s, problem.network, lo[m], hi[m])[0])
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=cen, score=None)

    out = branch_and_bound(X[:, 0].clone(), X[:, 1].clone(), evaluate, threshold=None,
                           rel_tol=rel_tol, tol=1e-12, seconds=seconds, max_boxes=max_boxes,
                           batch=batch, progress=progress, task="residual bound", project=None)
    upper = out.upper if math.isfinite(out.upper) else None
    worst = out.best_point.tolist() if out.best_point is not None else None
    return upper, worst, out.stats


def bound_dk_dy(problem: Problem, *, seconds: float = 30.0, max_boxes: int = 1_000_000,
                progress: Progress | None = None, rel_tol: float = 1e-3,
                batch: int = 1024) -> float | None:
    """Sound upper bound on sup over X x Y of ||dk/dy||_2 (by the Frobenius norm of the
    entry magnitudes; exact for p = 1). None when a box stayed NaN/Inf."""
    lo, hi = _root(problem)

    level = _Level(rel_tol, 1e-12)

    def evaluate(blo: torch.Tensor, bhi: torch.Tensor) -> BoxEval:
        ub, cen = dk_dy_box_upper(problem.system, problem.network, blo, bhi)
        if not problem.structural:  # the linear bounds cover direct networks only
            ub = level.tighten(ub, cen, lambda m: dk_dy_box_upper_crown(
                problem.system, problem.network, blo[m], bhi[m])[0])
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, float("nan")))
        return BoxEval(upper=ub, centre_value=cen, score=None)

    out = branch_and_bound(lo, hi, evaluate, threshold=None, rel_tol=rel_tol, tol=1e-12,
                           seconds=seconds, max_boxes=max_boxes, batch=batch,
                           progress=progress, task="dk/dy bound", project=None)
    return out.upper if math.isfinite(out.upper) else None


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
                            seconds: float = 10.0, max_boxes: int = 500_000,
                            rel_tol: float = 1e-4
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
        from certify.intervals import Interval
        from certify.system_enclosures import jacobian_f_enclosure

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

    out = branch_and_bound(X[:, 0].clone(), X[:, 1].clone(), evaluate, threshold=None,
                           rel_tol=rel_tol, tol=1e-12, seconds=seconds, max_boxes=max_boxes,
                           batch=256, task="manifold bound", project=None)
    upper = out.upper if not math.isnan(out.upper) else None
    if upper is not None and upper == math.inf:
        upper = None
    witness = out.best_point.tolist() if out.best_point is not None else None
    return upper, witness
