"""Training benchmark: the paper preset on vdp and duffing, one JSON line per system.

Each line: wall seconds of each phase (setup, adam, lbfgs, total), L-BFGS iterations and
function evaluations, the final loss terms (float64, on the training points), the process
CPU seconds and the 1-minute load average before the run (the machine is shared: a load
above the core count means the wall-clock numbers are inflated).

Run: python bench/train.py [--systems vdp,duffing] [--seed 0] [--save-vdp examples/vdp.ckpt]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from certify.model import checkpoint  # noqa: E402
from certify.spec.system import load_system  # noqa: E402
from training.objective import WORKERS  # noqa: E402
from training.presets import make_config  # noqa: E402
from training.train import train  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", default="vdp,duffing")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save-vdp", default=None, help="also write the vdp checkpoint here")
    args = parser.parse_args()
    for name in [s.strip() for s in args.systems.split(",") if s.strip()]:
        system = load_system(name)
        config = make_config(system, "paper", seed=args.seed)
        load = os.getloadavg()[0]
        cpu0 = time.process_time()
        result = train(system, config)
        cpu = time.process_time() - cpu0
        t = result.timings
        line = {
            "system": name, "preset": "paper", "seed": args.seed,
            "wall_s": {k: round(t[k], 3) for k in ("setup", "adam", "lbfgs", "total")},
            "cpu_s": round(cpu, 2),
            "lbfgs_iterations": result.counts["lbfgs_iterations"],
            "lbfgs_evaluations": result.counts["lbfgs_evaluations"],
            "evaluations": result.counts["evaluations"],
            "final": {k: float(f"{v:.6g}") for k, v in result.final.items()},
            "points": config.points, "workers": WORKERS, "cores": os.cpu_count(),
            "load_avg_1min_before": round(load, 2), "torch": torch.__version__,
        }
        record_line(line)
        if name == "vdp" and args.save_vdp:
            checkpoint.save(args.save_vdp, system=system, network=result.network,
                            lam=config.lam, P=np.asarray(config.P), training=result.record())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
