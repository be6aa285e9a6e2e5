"""Speed of the compiled spec evaluators (`certify.spec.expr`): one JSON line per measurement.

Times `System.f_and_h` (the simulation's right-hand side, small batches called tens of
thousands of times), `System.jac_f` and `System.jac_h` (grid sweeps, large batches) on the
built-in systems, for two source trees side by side (default: `/work/main` as "before" and
this tree as "after"), each in a subprocess with PYTHONPATH set to its tree. Trees alternate
round by round so load from other processes hits both alike; each number is the median over
`--repeat` rounds of a per-call time (itself the median of 7 timed blocks). A `compare` line
gives after / before per measurement.

Run: python bench/expr.py [--before /work/main] [--after .] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SYSTEMS = ("vdp", "duffing", "lorenz", "vdp3")
#: (System method, batch rows, calls per timed block)
CASES = (("f_and_h", 32, 2000), ("f_and_h", 2, 2000), ("jac_f", 4096, 200),
         ("jac_h", 4096, 400))

CHILD = r"""
import json, statistics, sys, time
import torch
torch.set_num_threads(1)
from certify.spec.system import load_system
cases = json.loads(sys.argv[1])
out = {}
for name in cases["systems"]:
    s = load_system(name)
    g = torch.Generator().manual_seed(0)
    X = torch.as_tensor(s.X, dtype=torch.float64)
    for method, batch, calls in cases["cases"]:
        x = X[:, 0] + (X[:, 1] - X[:, 0]) * torch.rand(batch, s.n, generator=g,
                                                        dtype=torch.float64)
        fn = getattr(s, method)
        for _ in range(20):
            fn(x)
        blocks = []
        for _ in range(7):
            t0 = time.perf_counter()
            for _ in range(calls):
                fn(x)
            blocks.append((time.perf_counter() - t0) / calls)
        out[f"{name} {method} B={batch}"] = statistics.median(blocks) * 1e6
print(json.dumps(out))
"""


def emit(**record: object) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


def measure(tree: Path) -> dict[str, float]:
    """Per-call microseconds of every case, in a fresh interpreter importing `tree`."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    arg = json.dumps({"systems": SYSTEMS, "cases": CASES})
    proc = subprocess.run([sys.executable, "-c", CHILD, arg], env=env, capture_output=True,
                          text=True, timeout=1800, cwd="/")
    if proc.returncode != 0:
        raise RuntimeError(f"{tree}: {proc.stderr[-500:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, default=Path("/work/main"))
    ap.add_argument("--after", type=Path, default=ROOT)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in trees}
    for r in range(args.repeat):
        for label in (("before", "after") if r % 2 == 0 else ("after", "before")):
            runs[label].append(measure(trees[label]))
    for key in runs["before"][0]:
        med = {label: statistics.median(run[key] for run in runs[label]) for label in trees}
        for label in trees:
            emit(kind="expr", tree=label, case=key, us_per_call=round(med[label], 2),
                 repeat=args.repeat)
        emit(kind="compare", case=key, before_us=round(med["before"], 2),
             after_us=round(med["after"], 2), ratio=round(med["after"] / med["before"], 3))


if __name__ == "__main__":
    main()
