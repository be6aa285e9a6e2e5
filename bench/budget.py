"""The wall-clock cap on networks whose boxes are slow: one JSON line per measurement.

Two observers with gelu gains (n = 4 states, p = 2 outputs, a linear chain as f, P = I):
"gelu-3-16-8-64" (hidden widths 3, 16, 8, 64, weights scaled by 2, lam 0.2 just below the
sampled limit: a long proof) and "deep" (six hidden layers of 128, lam 0.25: tens of
milliseconds a box, several seconds of set-up).

- prove: wall seconds of `prove_mpdi(seconds=S)` (`--seconds`, default 3), with the proof's
  own seconds, boxes and status;
- run: wall seconds of `certify run CKPT --max-seconds S` (`--run-seconds`, default 12: the
  cap of the whole run; `--proof-seconds S`, the MPDI proof's own time budget, in a
  checkout from before the box budgets) as a subprocess, with the MPDI check's seconds from
  the JSON certificate (`--grid-points`, default 1e5, keeps the grid sweep of the deep
  network short; `--skip`, default lipschitz: LipSDP on the deep network asks the SDP
  solver for more memory than a 24 GB machine has, and the run aborts).

`--code DIR` imports `certify` from another checkout (before/after comparisons: run once
per tree, on the same machine, one after the other). The machine is shared: the `load`
field is the 1-minute load average at the start of each measurement.

Run: python bench/budget.py [--code /work/main] [--only prove|run] [--nets deep]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from record import emit as record_line  # bench/record.py

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
if "--code" in sys.argv:  # import `certify` from another checkout (side-by-side comparisons)
    sys.path.insert(0, str(Path(sys.argv[sys.argv.index("--code") + 1]).resolve()))

import numpy as np  # noqa: E402
import torch  # noqa: E402

NETS = {"gelu-3-16-8-64": ((3, 16, 8, 64), 2.0, 0.2), "deep": ((128,) * 6, 1.0, 0.25)}


def make_problem(name: str):
    from certify.model.network import GainNetwork
    from certify.model.problem import Problem
    from tests.planted import linear_system

    hidden, scale, lam = NETS[name]
    n = 4
    A = -np.eye(n) + 0.3 * np.diag(np.ones(n - 1), 1) - 0.3 * np.diag(np.ones(n - 1), -1)
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    system = linear_system(A, C, lam=lam)
    torch.manual_seed(0)
    net = GainNetwork(n, 2, hidden, activation="gelu").double()
    with torch.no_grad():
        for prm in net.parameters():
            prm.mul_(scale)
    return Problem(system, net.requires_grad_(False), lam, np.eye(n))


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def bench_prove(name: str, seconds: float) -> dict:
    from certify.prove.mpdi import prove_mpdi

    problem = make_problem(name)
    load = _load()
    t = time.perf_counter()
    out = prove_mpdi(problem, seconds=seconds)
    return {"bench": "prove", "net": name, "budget_s": seconds,
            "wall_s": round(time.perf_counter() - t, 2),
            "proof_s": round(out.stats.seconds, 2), "boxes": out.stats.boxes_processed,
            "status": out.status.value, "estimated_boxes": out.stats.estimated_boxes,
            "load": load}


def bench_run(name: str, seconds: float, grid_points: int, code: Path, skip: str) -> dict:
    from certify.model import checkpoint

    problem = make_problem(name)
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(tmp) / f"{name}.ckpt"
        checkpoint.save(ckpt, system=problem.system, network=problem.network,
                        lam=problem.lam, P=problem.P)
        cert = Path(tmp) / "cert.json"
        env = {**os.environ, "PYTHONPATH": str(code)}
        load = _load()
        t = time.perf_counter()
        settings = (Path(code) / "certify" / "settings.py").read_text()
        cap = "--max-seconds" if "max_seconds" in settings else "--proof-seconds"
        proc = subprocess.run([sys.executable, "-m", "certify", "run", str(ckpt), "--no-config",
                               "--quiet", cap, str(seconds), "--grid-points",
                               str(grid_points), "--json", str(cert)]
                              + (["--skip", skip] if skip else []), env=env, cwd=tmp,
                              capture_output=True, text=True)
        wall = time.perf_counter() - t
        data = json.loads(cert.read_text()) if cert.exists() else {}
    checks = data.get("checks", {})
    mpdi = checks.get("mpdi", {})
    return {"bench": "run", "net": name, "proof_budget_s": seconds, "skip": skip,
            "wall_s": round(wall, 1),
            "exit": proc.returncode, "mpdi_status": mpdi.get("status"),
            "mpdi_s": round(mpdi.get("seconds") or 0.0, 1),
            "checks_s": {k: round(v.get("seconds") or 0.0, 1) for k, v in checks.items()},
            "load": load}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--code", type=Path, default=ROOT, help="the checkout to measure")
    ap.add_argument("--only", choices=("prove", "run"), default=None)
    ap.add_argument("--nets", nargs="*", default=list(NETS), choices=list(NETS))
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--run-seconds", type=float, default=12.0)
    ap.add_argument("--grid-points", type=int, default=100_000)
    ap.add_argument("--skip", default="lipschitz", help="checks the run skips ('' for none)")
    args = ap.parse_args()
    code = args.code.resolve()
    for name in args.nets:
        if args.only in (None, "prove"):
            record_line({"code": str(code), **bench_prove(name, args.seconds)})
        if args.only in (None, "run"):
            record_line({"code": str(code), **bench_run(name, args.run_seconds,
                                                             args.grid_points, code,
                                                             args.skip)})


if __name__ == "__main__":
    main()
