"""How fast `certify run` says NOT CERTIFIED: one JSON line per measurement.

A violated network (bench/instances.py's family "vdp-n2-5x30", the rate set so that the
sampled maximum of lam_max(D) is +`--margin`, i.e. the MPDI fails near its worst point) is
written to a checkpoint in a temporary folder, and `certify run CKPT` (no report: the run
may stop once the verdict is decided) is timed as a subprocess for each tree:

- run: wall and CPU seconds (of the child) and the exit code (1 expected), medians over
  `--repeat` runs; the two trees alternate, so load from other processes hits both alike;
- compare: after / before, wall and CPU.

The machine is shared: `load` is the 1-minute load average at the start (bench/record.py).

Run: python bench/fail_fast.py [--before /work/before] [--after .] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from run import certify, emit, median  # noqa: E402  (bench/run.py)


def violated_checkpoint(folder: Path, depth: int, width: int, margin: float, seed: int) -> Path:
    """A checkpoint of the instance with sampled max lam_max(D) = +margin."""
    from bench.instances import InstanceSpec, make_instance
    from certify.model.checkpoint import save

    spec = InstanceSpec(depth, width, 2.0, 2, -margin, seed)
    problem, info = make_instance(spec)
    path = folder / f"{spec.name}.ckpt"
    save(path, system=problem.system, network=problem.network, lam=problem.lam, P=problem.P,
         training={"bench": info})
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="/work/before", help="'' to measure --after alone")
    ap.add_argument("--after", default=str(ROOT))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--depth", type=int, default=5)
    ap.add_argument("--width", type=int, default=30)
    ap.add_argument("--margin", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    trees = {"after": Path(args.after).resolve()}
    if args.before:
        trees = {"before": Path(args.before).resolve(), **trees}
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        ckpt = violated_checkpoint(cwd, args.depth, args.width, args.margin, args.seed)
        runs: dict[str, dict[str, list[float]]] = {k: {"wall": [], "cpu": []} for k in trees}
        codes: dict[str, set[int]] = {k: set() for k in trees}
        for _ in range(args.repeat):
            for name, tree in trees.items():
                wall, code, err, cpu = certify(tree, ["run", str(ckpt), "--no-config"], cwd)
                runs[name]["wall"].append(wall)
                runs[name]["cpu"].append(cpu)
                codes[name].add(code)
                if code not in (1,):
                    print(err, file=sys.stderr)
        med = {}
        for name in trees:
            med[name] = {k: median(v) for k, v in runs[name].items()}
            emit(kind="run", tree=name, instance=ckpt.stem, wall_s=med[name]["wall"],
                 cpu_s=med[name]["cpu"], exit=sorted(codes[name]), repeat=args.repeat)
        if "before" in med:
            emit(kind="compare", instance=ckpt.stem,
                 wall=round(med["after"]["wall"] / med["before"]["wall"], 3),
                 cpu=round(med["after"]["cpu"] / med["before"]["cpu"], 3))


if __name__ == "__main__":
    main()
