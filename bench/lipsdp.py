"""Benchmark the SDP layer; prints one JSON object.

LipSDP (verified) on a 5x30 gain network: time, value, the rebuilt LMI's largest eigenvalue,
the naive and sampled bounds; and the metric / LMI-observer SDP times for vdp.

    python bench/lipsdp.py [--checkpoint examples/vdp.ckpt] [--seed 0] [--clarabel]

Without --checkpoint it uses examples/vdp.ckpt when present, else a seeded random 5x30
network. --clarabel also times the chordal cvxpy + Clarabel form (about 30-60 s).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from record import emit as record_line  # bench/record.py

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from certify.checks.lipschitz import (  # noqa: E402
    lipsdp_for,
    mlp_in_y,
    naive_bound,
    sampled_lower,
)
from certify.design import lipsdp  # noqa: E402
from certify.design.metric import observer_lmi, synthesize_metric  # noqa: E402
from certify.model import checkpoint  # noqa: E402
from certify.model.network import GainNetwork  # noqa: E402
from certify.model.problem import Problem  # noqa: E402
from certify.spec.system import load_system  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clarabel", action="store_true")
    args = ap.parse_args()
    path = args.checkpoint or (ROOT / "examples" / "vdp.ckpt")
    if Path(path).is_file():
        pr = checkpoint.load(path).problem
        source = str(path)
    else:
        torch.manual_seed(args.seed)
        pr = Problem(load_system("vdp"), GainNetwork(2, 1, (30,) * 5), 2.5, np.eye(2))
        source = f"random 5x30, seed {args.seed}"
    out: dict = {"network": source, "hidden": pr.network.hidden,
                 "threads": torch.get_num_threads()}
    t = time.perf_counter()
    res = lipsdp_for(pr)
    out["lipsdp"] = {
        "seconds": time.perf_counter() - t, "value": res.value, "raw": res.raw_value,
        "status": res.status.value, "solver": res.solver, "iterations": res.iterations,
        "recheck_max_eig": res.check_max_eig, "recheck_tolerance": res.check_tolerance,
    } if res is not None else None
    if args.clarabel and res is not None:
        Ws, Wo = mlp_in_y(pr.network, pr.n)
        t = time.perf_counter()
        rc = lipsdp.lipsdp_neuron(Ws, Wo, pr.network.K.numpy(), method="clarabel")
        out["lipsdp_clarabel"] = {"seconds": time.perf_counter() - t, "value": rc.value,
                                  "iterations": rc.iterations,
                                  "solve_seconds": rc.solve_seconds}
    out["naive"] = naive_bound(pr.network, pr.n) if pr.network.structure == "direct" else None
    t = time.perf_counter()
    out["sampled"], _ = sampled_lower(pr, points=20_000)
    out["sampled_seconds"] = time.perf_counter() - t
    vdp = load_system("vdp")
    t = time.perf_counter()
    m = synthesize_metric(vdp, 2.5)
    out["metric_vdp"] = {"seconds": time.perf_counter() - t, "status": m.status.value,
                         "cond_P": m.condition_number,
                         "sdp_vertices": m.solver.get("sdp_vertices"),
                         "sub_boxes": m.solver.get("sub_boxes")}
    t = time.perf_counter()
    o = observer_lmi(vdp, 2.5)
    out["observer_lmi_vdp"] = {"seconds": time.perf_counter() - t, "status": o.status.value,
                               "cond_P": o.condition_number,
                               "gain_norm": o.solver.get("gain_norm"),
                               "sdp_vertices": o.solver.get("sdp_vertices")}
    record_line(out)


if __name__ == "__main__":
    main()
