"""Verifier benchmark: prints one JSON line per measurement.

- grid: points/s of lam_max(D) on the 5x30 paper-preset network (examples/vdp.ckpt) over a dense
  grid of X x Y: the general row-major kernel, the feature-major grid kernel in float64 and in
  float32, and the falsifier's full grid pass (float32 screen + float64 re-check) on a
  contracting 5x30 instance (where few points need the re-check) and on the paper network
  (where every point violates, so every point is re-checked in float64);
- planted: seconds for `check_mpdi` to find a planted violation (corner, edge, blob);
- lipsdp: `check_lipschitz` on the 5x30 network (LipSDP + re-check, naive, sampled);
- run: `verify()` end to end with default settings on the shipped examples.

Run: python bench/verify.py [--points 2000000] [--skip run]. Wall-clock on this machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from certify.checks.mpdi import check_mpdi, joint_box, mpdi_score  # noqa: E402
from certify.model import checkpoint  # noqa: E402
from certify.search.falsify import grid_chunk, grid_shape, maximize_over_box  # noqa: E402
from certify.search.grid import GridKernel  # noqa: E402
from certify.settings import VerifySettings  # noqa: E402


def emit(**record: object) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


def grid_rate(fn, problem, points: int, chunk: int = 8192) -> float:
    lo, hi = joint_box(problem)
    shape = grid_shape(lo, hi, points)
    total = int(np.prod(shape))
    lo_t, hi_t = torch.as_tensor(lo), torch.as_tensor(hi)
    with torch.no_grad():
        fn(grid_chunk(lo_t, hi_t, shape, 0, chunk))  # warm-up
        t0 = time.perf_counter()
        for start in range(0, total, chunk):
            fn(grid_chunk(lo_t, hi_t, shape, start, min(total, start + chunk)))
        return total / (time.perf_counter() - t0)


def bench_grid(points: int) -> None:
    paper = checkpoint.load(ROOT / "examples" / "vdp.ckpt").problem
    emit(bench="grid", network="5x30 paper", kernel="general float64",
         points_per_s=round(grid_rate(mpdi_score(paper), paper, points // 4)))
    for dtype in (torch.float64, torch.float32):
        emit(bench="grid", network="5x30 paper", kernel=f"grid kernel {str(dtype)[6:]}",
             points_per_s=round(grid_rate(GridKernel(paper, dtype=dtype), paper, points)))
    sys.path.insert(0, str(ROOT / "bench"))
    from prove import true_instance  # a contracting 5x30 instance (margin 0.02)

    true = true_instance()
    for label, problem in (("5x30 contracting", true), ("5x30 paper", paper)):
        lo, hi = joint_box(problem)
        for screen in (True, False):
            t0 = time.perf_counter()
            out = maximize_over_box(GridKernel(problem), lo, hi, grid_points=points, starts=0,
                                    steps=0, screen=GridKernel(problem, dtype=torch.float32)
                                    if screen else None)
            dt = time.perf_counter() - t0
            emit(bench="grid", network=label, kernel="falsifier grid pass",
                 float32_screen=screen, points=out.grid_points,
                 points_per_s=round(out.grid_points / dt), seconds=round(dt, 3),
                 max_lam_max_D=out.best_value, violating_fraction=out.above_fraction)


def bench_planted() -> None:
    sys.path.insert(0, str(ROOT))
    from tests.planted import planted_problem

    settings = VerifySettings(grid_points=200_000)
    for kind in ("corner", "edge", "blob"):
        t0 = time.perf_counter()
        res = check_mpdi(planted_problem(kind), settings)
        emit(bench="planted", kind=kind, status=res.status.value, value=res.lower,
             found_by="grid/ascent" if res.proof is None else "prover",
             seconds=round(time.perf_counter() - t0, 3))


def bench_lipsdp() -> None:
    from certify.checks.lipschitz import check_lipschitz

    paper = checkpoint.load(ROOT / "examples" / "vdp.ckpt").problem
    t0 = time.perf_counter()
    res = check_lipschitz(paper, VerifySettings())
    emit(bench="lipsdp", network="5x30 paper", seconds=round(time.perf_counter() - t0, 3),
         lipsdp=res.lipsdp, lipsdp_verified=res.lipsdp_verified,
         lmi_max_eig=res.lipsdp_lmi_max_eig, naive=res.naive, sampled=res.sampled,
         solver=res.solver)


def bench_run() -> None:
    from certify.verify import verify

    for name in ("vdp_certified.ckpt", "vdp_lmi.ckpt", "vdp.ckpt"):
        path = ROOT / "examples" / name
        if not path.exists():
            continue
        t0 = time.perf_counter()
        cert = verify(checkpoint.load(path), VerifySettings())
        mpdi = cert.checks["mpdi"]
        emit(bench="run", checkpoint=name, verdict=cert.verdict,
             seconds=round(time.perf_counter() - t0, 2),
             timings={k: round(v, 2) for k, v in cert.timings.items()},
             mpdi=[mpdi.lower, mpdi.upper], proof=None if mpdi.proof is None else {
                 "boxes": mpdi.proof.boxes_processed,
                 "boxes_per_s": round(mpdi.proof.boxes_per_second),
                 "volume_history": mpdi.proof.volume_history[-5:]})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--skip", default="", help="comma-separated: grid,planted,lipsdp,run")
    args = ap.parse_args()
    skip = set(args.skip.split(","))
    emit(bench="env", torch=torch.__version__, threads=torch.get_num_threads())
    for name, fn in (("grid", lambda: bench_grid(args.points)), ("planted", bench_planted),
                     ("lipsdp", bench_lipsdp), ("run", bench_run)):
        if name not in skip:
            fn()


if __name__ == "__main__":
    main()
