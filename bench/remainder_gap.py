"""How far the prover's enclosures are from the best any affine enclosure could do.

The MPDI prover bounds A(z) = M D(z) M^T on a sub-box by an affine matrix function plus an
interval remainder E, and closes the box when max over the vertices of lam_max(affine) +
rho(E) <= 0. This bench measures, on sub-boxes of the issue-9 instance families:

- `sound_rho`: rho(E) of the prover's own Taylor model of A (`crown_contraction_tm` below,
  the linear-bound stage);
- `best_affine_rho`: rho of the entrywise half-range of A(z) minus its least-squares affine
  fit, over `--points` random points of the sub-box. A sampled ESTIMATE (not a bound) of the
  remainder of the best affine enclosure; no sound linear relaxation can do much better;
- `room`: minus the sampled max of lam_max(A) over the sub-box (what a remainder may use);
- `decided_if_zero` (networks with at most two hidden layers on the mixed rows): a what-if,
  NOT a bound: the fraction the rank-structured bound decides with each relaxation error
  set to zero in turn (`error_budget`), which says which relaxation to tighten next;
- `closed`: the fraction of sub-boxes the linear-bound stage alone closes (remainder
  entrywise); `closed_by_prover`: the fraction the prover's whole box bound decides
  (`mpdi_box_bounds` in decision mode); `closable_by_best_affine`:
  the fraction the prover's bound form (max over the vertices of lam_max of the affine part,
  plus rho of the remainder) closes with the fitted affine part and its sampled remainder in
  place of the prover's: an estimate of what a perfect affine enclosure could close.

If `closable_by_best_affine` is small at a radius, no tightening of linear relaxations
closes boxes of that size: the proof needs that many smaller boxes, or enclosures of higher
order. One JSON line per (instance, radius); radii are relative to the root's half-widths.

Example (why the 2x10 six-state chain does not close at radius 1/4):
    python bench/remainder_gap.py --family 2x10 --n 6 --seeds 0 --radii 0.25 0.125 0.0625
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from bench.prove_suite import add_family_arguments, family_instances  # noqa: E402
from certify.arith.eigen import rho_upper  # noqa: E402
from certify.arith.intervals import up  # noqa: E402
from certify.enclose.mixed import contraction_tm_mixed  # noqa: E402
from certify.enclose.mpdi import choose_preconditioner, mpdi_box_bounds  # noqa: E402
from certify.enclose.options import box_bound_options, mixed_rows_apply  # noqa: E402
from certify.enclose.preconditioner import constant_term  # noqa: E402
from certify.enclose.stages import linear_contraction_tm  # noqa: E402
from certify.enclose.taylor import tm_lam_upper  # noqa: E402
from certify.model.kernels import closed_loop_jacobian, contraction_matrix  # noqa: E402


def crown_contraction_tm(problem, pc, lo: torch.Tensor, hi: torch.Tensor, r: torch.Tensor,
                         lam: float):
    """The Taylor model of A = M D M^T over boxes (radii r) from the backward linear bounds
    of the prover's linear stage for this problem: the mixed rows where they apply
    (`mixed_rows_apply`), else the network's linear-bound Taylor models."""
    constant = constant_term(pc, lam)
    if mixed_rows_apply(problem, pc):
        return contraction_tm_mixed(problem, pc, lo, hi, r, lam, constant=constant)[0]
    return linear_contraction_tm(problem, pc, lo, hi, r, constant)


def contraction_at(problem, pc, z: torch.Tensor, lam: float) -> torch.Tensor:
    """A(z) = M D(z) M^T at points z [m, d] (float64)."""
    n = problem.n
    J = closed_loop_jacobian(problem.system, problem.network, z[:, :n], z[:, n:])
    D = contraction_matrix(J, torch.zeros_like(J), problem.P_t.to(torch.float64), lam)
    M = pc.M.to(torch.float64)
    return M @ D @ M.T


def lam_max_sym(A: torch.Tensor) -> torch.Tensor:
    return torch.linalg.eigvalsh(0.5 * (A + A.transpose(-1, -2)))[..., -1]


def measure(problem, rel_radius: float, boxes: int, points: int, seed: int) -> dict:
    s = problem.system
    root = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=torch.float64)
    rlo, rhi = root[:, 0], root[:, 1]
    d = len(rlo)
    lam = float(problem.lam)
    pc = choose_preconditioner(problem, lam)
    g = torch.Generator().manual_seed(seed)
    rad = rel_radius * 0.5 * (rhi - rlo)
    c = rlo + rad + (rhi - rlo - 2 * rad) * torch.rand(boxes, d, generator=g, dtype=torch.float64)
    lo, hi = c - rad, c + rad
    r = up(torch.maximum(hi - c, c - lo))  # the prover's radii (`mpdi_box_bounds`)
    tm = crown_contraction_tm(problem, pc, lo, hi, r, lam)
    sound = rho_upper(tm.e)
    bound, _ = tm_lam_upper(tm, r)
    # sampled best affine fit per box (batched least squares over the points of each box)
    u = 2 * torch.rand(boxes, points, d, generator=g, dtype=torch.float64) - 1
    A = contraction_at(problem, pc, (c[:, None] + rad * u).reshape(-1, d), lam)
    m = A.shape[-1]
    A = A.reshape(boxes, points, m, m)
    Y = A.reshape(boxes, points, m * m)
    ones = torch.ones(boxes, points, 1, dtype=torch.float64)
    coef = torch.linalg.lstsq(torch.cat([ones, u], -1), Y).solution  # [boxes, d + 1, m m]
    dev = Y - torch.cat([ones, u], -1) @ coef
    mid = 0.5 * (dev.amax(1) + dev.amin(1))
    e = (0.5 * (dev.amax(1) - dev.amin(1))).reshape(boxes, m, m)
    best = rho_upper(e)
    smax = lam_max_sym(A).amax(1)
    # the prover's bound form with the fitted affine part: vertex max + rho(E)
    V = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=torch.float64)] * d).reshape(-1, d)
    Vx = torch.cat([torch.ones(len(V), 1, dtype=torch.float64), V], 1)
    Lv = (Vx @ coef + mid[:, None]).reshape(boxes, len(V), m, m)
    ideal_bound = lam_max_sym(Lv).amax(1) + best
    ratio = sound / best.clamp_min(1e-300)
    # what the prover's own box bound decides (every stage: rank-structured top layer, mixed
    # rows, congruence tests), at the level 0 of its decision mode
    decided = mpdi_box_bounds(box_bound_options(problem, lam, pc=pc, screen=0.0, decide=True,
                                                root_width=rhi - rlo), lo, hi).upper <= 0
    rec = {"rel_radius": rel_radius, "boxes": boxes, "points": points,
            "preconditioner": pc.kind,
            "sound_rho_median": round(float(sound.median()), 5),
            "best_affine_rho_median": round(float(best.median()), 5),
            "ratio_median": round(float(ratio.median()), 3),
            "room_median": round(float(-smax.median()), 5),
            "closed": round(float((bound <= 0).double().mean()), 4),
            "closed_by_prover": round(float(decided.double().mean()), 4),
            "closable_by_best_affine": round(float((ideal_bound <= 0).double().mean()), 4)}
    budget = error_budget(problem, pc, lo, hi, r, lam)
    if budget is not None:
        rec["decided_if_zero"] = budget
    return rec


#: the relaxation errors `error_budget` sets to zero one at a time (fields of
#: `certify.enclose.top_rank.TopRank`; "remainder": what the Taylor model's remainder keeps)
ERROR_SOURCES = ("top_kl", "top_o", "top_fprime", "first_fprime", "remainder")


def error_budget(problem, pc, lo, hi, r, lam: float) -> dict | None:
    """What-if (NOT sound): the fraction of the boxes the rank-structured Loewner bound
    (`certify.enclose.top_rank.rank_loewner_upper`, every neuron in the rank form) decides at
    level 0 with one error source set to zero, per `ERROR_SOURCES`, beside "none" (nothing
    zeroed) and "all": which relaxation is worth tightening next. Only where that bound
    applies (the mixed rows, a direct network with at most two hidden layers); else None.
    Measured on the 2x10 four-state chain, seed 5, the boxes its proof sends to this bound:
    none 0.29, top_kl 0.56, top_fprime 0.37, first_fprime 0.34, remainder 0.33, all 1.0."""
    from dataclasses import replace

    from certify.arith.taylor import TM
    from certify.enclose.mixed import contraction_tm_mixed
    from certify.enclose.top_rank import rank_loewner_upper

    if not mixed_rows_apply(problem, pc):
        return None
    A, top = contraction_tm_mixed(problem, pc, lo, hi, r, lam, top_apart=True)
    if top is None or top.rank is None:
        return None
    out = {}
    for source in ("none", *ERROR_SOURCES, "all"):
        rk, a = top.rank, A
        zero = source == "all"
        if zero or source == "top_kl":
            rk = replace(rk, beta=torch.zeros_like(rk.beta))
        if zero or source == "top_o":
            rk = replace(rk, o=torch.zeros_like(rk.o))
        if zero or source == "top_fprime":
            rk = replace(rk, ws=torch.zeros_like(rk.ws))
        if (zero or source == "first_fprime") and rk.lower is not None:
            rk = replace(rk, lower=replace(rk.lower, ws1=torch.zeros_like(rk.lower.ws1)))
        if zero or source == "remainder":
            a = TM(A.c, A.g, torch.zeros_like(A.e))
        bound, _ = tm_lam_upper(rank_loewner_upper(a, top.C, top.w, rk, 0.0, force="rank"), r)
        out[source] = round(float((bound <= 0).double().mean()), 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_family_arguments(ap)
    ap.add_argument("--radii", nargs="+", type=float, default=[0.25, 0.125, 0.0625])
    ap.add_argument("--boxes", type=int, default=32, help="random sub-boxes per radius")
    ap.add_argument("--points", type=int, default=3000, help="samples per sub-box")
    args = ap.parse_args()
    torch.set_num_threads(1)
    for spec, prob in family_instances(args):
        for r in args.radii:
            rec = {"bench": "remainder_gap", "instance": spec.name}
            rec.update(measure(prob, r, args.boxes, args.points, spec.seed))
            record_line(rec)

if __name__ == "__main__":
    main()
