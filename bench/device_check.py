"""The MPDI proof's box bounds on a GPU (`--device cuda`): sound, as on the CPU, and how fast.

For each instance of `bench/instances.py` (tuned rates from --cache): random sub-boxes at a few
relative radii, bounded by the prover's own evaluator (`certify.prove.mpdi._mpdi_evaluator`, the
congruence chosen on each device) on the CPU and on --device, and lam_max(D) at sampled points
of every box (float64, CPU). One JSON line per instance and radius:
  violations        device bounds below a sampled value (must be 0: soundness)
  max_rel_diff      largest |cpu - device| / (1 + |cpu|) over finite bounds (rounding only)
  decisions_differ  boxes closed (bound <= 0) on one side only
  cpu_us_per_box, device_us_per_box   wall time of one evaluation of all the boxes
Then `bench/prove_suite.py --device` times whole proofs.

Example (on a machine with a GPU):
    python bench/device_check.py --device cuda --family 2x10 --n 2 4 6 --boxes 4096
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from bench.instances import InstanceSpec  # noqa: E402
from bench.prove_suite import FAMILIES, _cached_instance  # noqa: E402
from certify.arith.device import describe, resolve_device  # noqa: E402
from certify.enclose.options import Technique  # noqa: E402
from certify.model.kernels import mpdi_lam_max  # noqa: E402
from certify.prove.mpdi import (  # noqa: E402
    _mpdi_evaluator,
    _mpdi_preconditioner,
    mpdi_options,
    root_box,
)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed_bounds(problem, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, float]:
    """The evaluator's upper bounds of lam_max(D) on the boxes (on the CPU) and the seconds
    of the second of two evaluations (the first warms caches and kernels)."""
    device = torch.device(problem.device)
    pc = _mpdi_preconditioner(problem, problem.lam, Technique.TAYLOR)
    evaluate = _mpdi_evaluator(problem, mpdi_options(problem, problem.lam, pc))
    lo, hi = lo.to(device), hi.to(device)
    evaluate(lo[:64], hi[:64])
    _sync(device)
    t = time.perf_counter()
    ev = evaluate(lo, hi)
    _sync(device)
    return ev.upper.cpu(), time.perf_counter() - t


def check(problem, boxes: int, radius: float, samples: int, device: torch.device,
          seed: int) -> dict:
    rlo, rhi = root_box(problem)
    w = rhi - rlo
    d = len(w)
    gen = torch.Generator().manual_seed(seed)
    c = rlo + w * (radius + (1 - 2 * radius) * torch.rand(boxes, d, generator=gen,
                                                          dtype=torch.float64))
    lo, hi = c - w * radius, c + w * radius
    up_cpu, t_cpu = _timed_bounds(problem, lo, hi)
    up_dev, t_dev = _timed_bounds(problem.on(device), lo, hi)
    u = torch.rand(boxes, samples, d, generator=gen, dtype=torch.float64)
    u[:, 0] = 0.5
    z = (lo[:, None] + (hi - lo)[:, None] * u).reshape(-1, d)
    n = problem.n
    vals = mpdi_lam_max(problem.system, problem.network, problem.P_t, problem.lam,
                        z[:, :n], z[:, n:]).reshape(boxes, samples).amax(-1)
    tol = 1e-12 * (1 + vals.abs())
    finite = torch.isfinite(up_dev)
    both = finite & torch.isfinite(up_cpu)
    rel = ((up_cpu - up_dev).abs() / (1 + up_cpu.abs()))[both]
    return {"radius": radius, "boxes": boxes, "samples_per_box": samples,
            "violations": int((finite & (up_dev < vals - tol)).sum()),
            "nonfinite_device": int((~finite).sum()), "nonfinite_cpu":
            int((~torch.isfinite(up_cpu)).sum()),
            "max_rel_diff": float(rel.max()) if len(rel) else None,
            "closed_cpu": int((up_cpu <= 0).sum()), "closed_device": int((up_dev <= 0).sum()),
            "decisions_differ": int(((up_cpu <= 0) != (up_dev <= 0)).sum()),
            "cpu_us_per_box": round(1e6 * t_cpu / boxes, 2),
            "device_us_per_box": round(1e6 * t_dev / boxes, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--family", nargs="+", default=["2x10"], choices=sorted(FAMILIES))
    ap.add_argument("--g", type=float, default=2.0)
    ap.add_argument("--n", nargs="+", type=int, default=[2, 4])
    ap.add_argument("--margin", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--boxes", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--radii", nargs="+", type=float, default=[1 / 16, 1 / 64, 1 / 256])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default="/tmp/certify-bench/instances.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    for fam in args.family:
        depth, width = FAMILIES[fam]
        for n in args.n:
            spec = InstanceSpec(depth, width, args.g, n, args.margin, args.seed)
            problem, _ = _cached_instance(spec, Path(args.cache))
            for k, radius in enumerate(args.radii):
                rec = {"instance": spec.name, "device": describe(device),
                       "threads": args.threads}
                rec.update(check(problem, args.boxes, radius, args.samples, device, 100 + k))
                record_line(rec)


if __name__ == "__main__":
    main()
