"""Training benchmark: the paper preset, two source trees side by side, one JSON line each.

Each tree (default: /work/before as "before", this tree as "after") trains the paper preset
(`training.train.train`, 4000 points, 5 x 30 tanh, Adam 500 + L-BFGS 500) in a subprocess with
PYTHONPATH set to it; runs of the two trees alternate, so load from other processes hits both
alike. Lines:

- `side` (before or after): one training run: wall seconds per phase (setup, adam, lbfgs,
  total), the child's CPU seconds, evaluations, the final loss terms (float64, on the
  training points) and the 1-minute load average before it (a load above the core count
  inflates the wall seconds);
- `compare`: per system, the medians over `--repeat` runs side by side (after / before, wall
  and CPU), and the two loss histories compared entry by entry (relative difference of the
  total at the first evaluation, the largest over the first 10 and the first 100 Adam
  evaluations, at the end of Adam, at L-BFGS evaluation 10 and at the end), with the final
  loss terms of both;
- with `--certify`: `certify run --skip simulation` on each tree's vdp checkpoint (the verdict
  and the MPDI check's sampled and proved numbers), in that tree;
- with `--spread 2000,1500`: the before tree again with those chunk sizes (the same
  mathematics, the float32 gradient summed in another order), its final losses beside the
  default's: how far a rounding-level change alone moves the end of the L-BFGS phase, the
  scale against which the two trees' final numbers are read.

The paper preset is trained directly, not through `certify train`, which stops before
training vdp and duffing at the design's P and lam (the pre-flight proves that no gain can
pass there); the benchmark measures the training itself.

Run: python bench/train.py [--before /work/before] [--after .] [--systems vdp,duffing]
         [--repeat 3] [--certify] [--spread 2000,1500,3000]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from record import emit  # noqa: E402  (bench/record.py)

ROOT = Path(__file__).resolve().parents[1]

#: what a child runs (in the tree on its PYTHONPATH): train, save the checkpoint, print JSON;
#: a fifth argument other than 0 sets the objective's chunk size (points per chunk)
CHILD = """
import json, sys, time, numpy as np, torch
import training.objective as objective
from certify.model import checkpoint
from certify.spec.system import load_system
from training.objective import WORKERS
from training.presets import make_config
from training.train import train
if int(sys.argv[4]):
    init = objective.Objective.__init__
    def sized(self, *a, **k):
        k.setdefault("chunk_points", int(sys.argv[4]))
        init(self, *a, **k)
    objective.Objective.__init__ = sized
system = load_system(sys.argv[1])
config = make_config(system, "paper", seed=int(sys.argv[2]))
result = train(system, config)
checkpoint.save(sys.argv[3], system=system, network=result.network, lam=config.lam,
                P=np.asarray(config.P), training=result.record())
print(json.dumps({"timings": result.timings, "counts": result.counts, "final": result.final,
                  "history": {ph: cols["total"] for ph, cols in result.history.items()},
                  "workers": WORKERS, "torch": torch.__version__}))
"""


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_child(tree: Path, args: list[str], code: str | None = None,
              module: str | None = None) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall, CPU seconds, process) of a child interpreter with PYTHONPATH = tree."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", module,
                                                            *args]
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=3600,
                          cwd=tempfile.gettempdir())
    return time.perf_counter() - t0, _children_cpu() - c0, proc


def rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b), 1e-300)


def compare_histories(before: dict, after: dict) -> dict:
    """The loss histories of two runs, entry by entry (relative differences of the total)."""
    ab, aa = before["history"].get("adam", []), after["history"].get("adam", [])
    lb, la = before["history"].get("lbfgs", []), after["history"].get("lbfgs", [])
    out: dict[str, object] = {}
    if ab and aa:
        n = min(len(ab), len(aa))
        d = [rel(x, y) for x, y in zip(ab[:n], aa[:n])]
        out.update(first=d[0], max_first_10=max(d[:10]), max_first_100=max(d[:100]),
                   adam_end=d[n - 1])
    if lb and la:
        n = min(len(lb), len(la))
        out.update(lbfgs_10=rel(lb[min(10, n - 1)], la[min(10, n - 1)]),
                   lbfgs_end=rel(lb[-1], la[-1]), lbfgs_evaluations=[len(lb), len(la)])
    return {k: (float(f"{v:.2g}") if isinstance(v, float) else v) for k, v in out.items()}


def median(xs: list[float]) -> float:
    return round(statistics.median(xs), 3)


def certify_line(tree: Path, ckpt: str, label: str) -> None:
    """`certify run --skip simulation` on a checkpoint, in `tree`: verdict and MPDI numbers."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        module = "certify.cli.main" if (tree / "certify" / "cli" / "main.py").exists() \
            else "certify.cli"
        wall, cpu, proc = run_child(tree, ["run", ckpt, "--skip", "simulation", "--json",
                                           str(out), "--quiet", "--no-config"], module=module)
        if not out.exists():
            emit({"certify": label, "exit": proc.returncode, "stderr": proc.stderr[-300:]})
            return
        cert = json.loads(out.read_text())
    mpdi = cert["checks"].get("mpdi", {})
    emit({"certify": label, "exit": proc.returncode, "verdict": cert["verdict"],
          "mpdi": {k: mpdi.get(k) for k in ("status", "lower", "upper", "violating_fraction")},
          "wall_s": round(wall, 2)})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="/work/before" if Path("/work/before").is_dir()
                        else "", help="the tree to compare with ('' for this tree alone)")
    parser.add_argument("--after", default=str(ROOT))
    parser.add_argument("--systems", default="vdp,duffing")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--certify", action="store_true",
                        help="also run `certify run` on each tree's vdp checkpoint")
    parser.add_argument("--spread", default="", metavar="SIZES",
                        help="also train the before tree with these chunk sizes (comma-"
                             "separated): the final loss's spread under rounding")
    args = parser.parse_args()
    trees = {"after": Path(args.after).resolve()}
    if args.before:
        trees = {"before": Path(args.before).resolve(), **trees}
    keep = Path(tempfile.mkdtemp(prefix="bench-train-"))
    for name in [s.strip() for s in args.systems.split(",") if s.strip()]:
        runs: dict[str, list[dict]] = {label: [] for label in trees}
        for k in range(args.repeat):
            for label, tree in trees.items():
                ckpt = keep / f"{name}-{label}.ckpt"
                load = round(os.getloadavg()[0], 2)
                wall, cpu, proc = run_child(tree, [name, str(args.seed), str(ckpt), "0"],
                                            code=CHILD)
                if proc.returncode != 0:
                    emit({"side": label, "system": name, "exit": proc.returncode,
                          "stderr": proc.stderr[-500:]})
                    return 1
                rec = json.loads(proc.stdout.strip().splitlines()[-1])
                rec.update(wall=wall, cpu=cpu, load=load)
                runs[label].append(rec)
                t = rec["timings"]
                emit({"side": label, "system": name, "repeat": k, "tree": str(tree),
                      "wall_s": {p: round(t[p], 3) for p in ("setup", "adam", "lbfgs", "total")
                                 if p in t},
                      "process_wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
                      "evaluations": rec["counts"]["evaluations"],
                      "final": {key: float(f"{v:.6g}") for key, v in rec["final"].items()},
                      "workers": rec["workers"], "cores": os.cpu_count(),
                      "load_avg_1min_before": load, "torch": rec["torch"]})
        line: dict[str, object] = {"compare": name, "repeat": args.repeat}
        for label, recs in runs.items():
            line[label] = {"total_s": median([r["timings"]["total"] for r in recs]),
                           "cpu_s": median([r["cpu"] for r in recs]),
                           "load": [r["load"] for r in recs],
                           "final": {k: float(f"{v:.6g}") for k, v in recs[0]["final"].items()}}
        if "before" in runs:
            b, a = line["before"], line["after"]
            line["after_over_before"] = {"total": round(a["total_s"] / b["total_s"], 3),
                                         "cpu": round(a["cpu_s"] / b["cpu_s"], 3)}
            line["history"] = compare_histories(runs["before"][0], runs["after"][0])
        if args.spread and "before" in trees:
            finals = {"default": runs["before"][0]["final"]["total"]}
            for size in [int(v) for v in args.spread.split(",") if v.strip()]:
                _, _, proc = run_child(trees["before"], [name, str(args.seed),
                                                         str(keep / "spread.ckpt"), str(size)],
                                       code=CHILD)
                if proc.returncode != 0:
                    emit({"spread": name, "chunk": size, "exit": proc.returncode,
                          "stderr": proc.stderr[-300:]})
                    continue
                finals[f"chunk {size}"] = json.loads(
                    proc.stdout.strip().splitlines()[-1])["final"]["total"]
            emit({"spread": name, "tree": "before", "final_total": finals,
                  "range": [min(finals.values()), max(finals.values())],
                  "after_final_total": runs["after"][0]["final"]["total"]})
        emit(line)
    if args.certify:
        for label, tree in trees.items():
            ckpt = keep / f"vdp-{label}.ckpt"
            if ckpt.exists():
                certify_line(tree, str(ckpt), label)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
