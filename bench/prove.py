"""Prover benchmark: prints JSON lines.

(a) a TRUE 5x30 instance on a 3-D box (vdp, X x Y; LMI metric P and linear injection K plus
    a small random 5x30 tanh network; lam set so that the sampled max lam_max(D) = -margin),
    proved with the second-order prover and, for comparison, with plain interval arithmetic;
(b) planted violations (corner, edge, interior blob) found by the prover.

Run: python bench/prove.py [--seconds 60] [--plain-seconds 60]. Shares the CPU with whatever
else runs: the numbers are wall-clock on this machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from record import emit as record_line  # bench/record.py

from certify.checks.mpdi import joint_box
from certify.model.kernels import mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.search.falsify import maximize_over_box
from certify.search.grid import GridKernel
from certify.spec.system import load_system

# LMI design for vdp on X = [-2,2]x[-3,3] (vertices of the Jf enclosure, lam = 1, margin 0.5),
# solved once with cvxpy + Clarabel: He{P (Jf - K C)} + 2 P <= -0.5 I.
P_VDP = [[69.5852, -6.6789], [-6.6789, 1.6504]]
K_VDP = [[8.1278], [47.7998]]


def sampled_max(problem: Problem, lam: float, grid: int = 60, refine: int = 64
                ) -> tuple[float, np.ndarray]:
    """Max of lam_max(D) found by the falsifier (grid of grid^3 points + ascent from `refine`)."""
    lo, hi = joint_box(problem)
    out = maximize_over_box(GridKernel(problem, lam), lo, hi, grid_points=grid ** 3,
                            starts=refine, steps=150, top_k=1)
    return out.best_value, out.best_point


#: lam found by `true_instance(retune=True)` for margin 0.02, seed 0, scale 0.3 (2 minutes of
#: bisection on sampled maxima); `main` re-measures the sampled max at it and prints it.
LAM_TUNED = 1.0991818614444298


def true_instance(margin: float = 0.02, seed: int = 0, scale: float = 0.3,
                  retune: bool = False) -> Problem:
    """vdp with the LMI metric and gain plus a small random 5x30 network, lam tuned so that
    the sampled max of lam_max(D) is -margin (the stored LAM_TUNED unless `retune`)."""
    torch.manual_seed(seed)
    s = load_system("vdp")
    net = GainNetwork(2, 1, (30,) * 5, K=torch.tensor(K_VDP))
    with torch.no_grad():
        net.layers[-1].weight.mul_(scale)
        net.layers[-1].bias.zero_()
    P = np.array(P_VDP)
    if not retune and (margin, seed, scale) == (0.02, 0, 0.3):
        return Problem(s, net, LAM_TUNED, P)
    prob = Problem(s, net, 1.0, P)
    # lam_max(D) is increasing in lam: bisection on a fixed point set (grid + refined points)
    _, where = sampled_max(prob, 1.0, grid=40, refine=32)
    box = np.concatenate([s.X, s.Y], 0)
    axes = [torch.linspace(float(a), float(b), 40, dtype=torch.float64) for a, b in box]
    Z = torch.cat([torch.cartesian_prod(*axes), torch.as_tensor(where)[None]])
    lo, hi = 0.0, 3.0
    for _ in range(3):
        for _ in range(45):
            mid = 0.5 * (lo + hi)
            m = float(mpdi_lam_max(s, prob.network, prob.P_t, mid, Z[:, :2], Z[:, 2:]).max())
            lo, hi = (mid, hi) if m < -margin else (lo, mid)
        prob = Problem(s, net, lo, P)
        _, where = sampled_max(prob, lo, grid=40, refine=32)
        Z = torch.cat([Z, torch.as_tensor(where)[None]])
        hi = lo + 0.1
    lam = lo
    return Problem(s, net, lam, P)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--plain-seconds", type=float, default=60.0)
    ap.add_argument("--margin", type=float, default=0.02)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--retune", action="store_true", help="re-tune lam by bisection (2 min)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

    t = time.perf_counter()
    prob = true_instance(args.margin, retune=args.retune)
    m, where = sampled_max(prob, prob.lam, grid=80, refine=64)
    record_line({"instance": "vdp-5x30-true", "lam": prob.lam, "sampled_max": m,
                      "argmax": where.tolist(), "setup_seconds": time.perf_counter() - t})
    for name, taylor, secs in (("taylor+interval", True, args.seconds),
                               ("plain-interval", False, args.plain_seconds)):
        out = prove_mpdi(prob, seconds=secs, taylor=taylor)
        st = out.stats
        record_line({
            "case": f"true-5x30/{name}", "status": out.status.value, "upper": out.upper,
            "lower": out.lower, "seconds": round(st.seconds, 3),
            "boxes": st.boxes_processed, "boxes_per_second": round(st.boxes_per_second, 1),
            "proved_volume": st.proved_volume_fraction, "max_depth": st.max_depth,
            "volume_history": [[round(a, 2), round(b, 5)] for a, b in st.volume_history[::10]],
        })

    import planted  # tests/planted.py

    for kind in ("corner", "edge", "blob"):
        pb = planted.planted_problem(kind)
        out = prove_mpdi(pb, seconds=30.0)
        st = out.stats
        record_line({
            "case": f"planted-{kind}", "status": out.status.value,
            "seconds": round(st.seconds, 3), "boxes": st.boxes_processed,
            "counterexample": None if out.counterexample is None else
            [out.counterexample.xhat, out.counterexample.y, out.counterexample.value]})


if __name__ == "__main__":
    main()
