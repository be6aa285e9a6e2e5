"""The simulation check, before and after, side by side: one JSON line per measurement.

- check: per shipped example (examples/*.ckpt), the simulation check alone
  (`certify.checks.simulation.check_simulation` with the default settings) in a child
  process: the result's `seconds` (wall), the check's CPU seconds (less moved by load), and
  the whole child's CPU seconds (imports included). Both trees get the same
  proved bounds: computed once by the first tree (`verify` with the simulation skipped),
  cached as JSON under --cache;
- zero_gain: the whole `certify run` (wall and CPU seconds, exit code, the simulation's
  seconds from the JSON certificate) of an observer that does nothing: x' = -x (two
  states, the first measured), the zero gain. Its proved bound is a rounding residue
  reached after hundreds of seconds, which used to stretch the simulated horizon.

Trees alternate, so load from other processes hits both alike; medians over --repeat (the
zero-gain run of a slow tree: --zero-repeat); each line records the 1-minute load average
at its start, and `bench/record.py` the run's tag. Wall seconds on a shared machine are
noisy: read the ratios, and the load.

Run: python bench/simulation.py [--before /work/before] [--after .] [--repeat 3]
         [--zero-repeat 1] [--only vdp_lmi] [--cache DIR]
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

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = tuple(sorted(p.stem for p in (ROOT / "examples").glob("*.ckpt")))

BOUNDS = """
import dataclasses, json, sys
from certify.model.checkpoint import load
from certify.results import to_jsonable
from certify.settings import VerifySettings
from certify.verify import verify
cert = verify(load(sys.argv[1]), dataclasses.replace(VerifySettings(), skip=("simulation",)),
              figures=False)
json.dump(to_jsonable(cert.checks["bounds"]), open(sys.argv[2], "w"))
"""

CHECK = """
import json, sys, time
from certify.checks.simulation import check_simulation
from certify.model.checkpoint import load
from certify.results import BoundsResult, Status, from_jsonable
from certify.settings import VerifySettings
bounds = from_jsonable(BoundsResult, json.load(open(sys.argv[2])))
problem = load(sys.argv[1]).problem
cpu = time.process_time()
r = check_simulation(problem, bounds, VerifySettings(), certified=bounds.status == Status.PROVED)
print(json.dumps({"seconds": r.seconds, "cpu": time.process_time() - cpu,
                  "status": r.status.value, "horizon": r.horizon, "runs": len(r.runs)}))
"""

ZERO_GAIN = """
import sys, torch
from certify.model.checkpoint import save
from certify.model.network import GainNetwork
from certify.spec.system import System
TEXT = '''name = "contracting"
states = ["x1", "x2"]
outputs = ["y"]
f = ["-x1", "-x2"]
h = ["x1"]
[box]
X = [[-1.0, 1.0], [-1.0, 1.0]]
Y = [[-1.0, 1.0]]
[design]
lam = 0.25
'''
net = GainNetwork(2, 1, (4,)).double()
with torch.no_grad():
    for p in net.parameters():
        p.zero_()
save(sys.argv[1], system=System.from_text(TEXT, origin="bench"), network=net, lam=0.25)
"""


def emit(**record: object) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


def load() -> float:
    return round(os.getloadavg()[0], 2)


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def python(tree: Path, args: list[str], cwd: Path
           ) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall s, CPU s, the process) of `python ARGS` with `tree` first on the path; `cwd`
    outside both trees (`python -m` puts it first on sys.path)."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=3600)
    return time.perf_counter() - t0, _children_cpu() - c0, proc


def median(xs: list[float]) -> float | None:
    return round(statistics.median(xs), 3) if xs else None


def bench_checks(trees: dict[str, Path], names: list[str], repeat: int, cache: Path) -> None:
    first = next(iter(trees.values()))
    for name in names:
        ckpt = str(ROOT / "examples" / f"{name}.ckpt")
        bounds = cache / f"{name}.bounds.json"
        if not bounds.exists():
            _, _, proc = python(first, ["-c", BOUNDS, ckpt, str(bounds)], cache)
            if proc.returncode:
                emit(bench="check", checkpoint=name, error=proc.stderr[-300:])
                continue
        seconds: dict[str, list[float]] = {t: [] for t in trees}
        cpus: dict[str, list[float]] = {t: [] for t in trees}  # the check's own CPU seconds
        for _ in range(repeat):
            for tag, tree in trees.items():
                at = load()
                wall, cpu, proc = python(tree, ["-c", CHECK, ckpt, str(bounds)], cache)
                if proc.returncode:
                    emit(bench="check", tree=tag, checkpoint=name, error=proc.stderr[-300:])
                    continue
                out = json.loads(proc.stdout.strip().splitlines()[-1])
                seconds[tag].append(out["seconds"])
                cpus[tag].append(out["cpu"])
                emit(bench="check", tree=tag, checkpoint=name, check_s=round(out["seconds"], 3),
                     check_cpu_s=round(out["cpu"], 3), process_cpu_s=round(cpu, 3),
                     wall_s=round(wall, 3), status=out["status"], horizon_s=out["horizon"],
                     runs=out["runs"], load=at)
        emit(bench="check_median", checkpoint=name,
             **{f"{tag}_s": median(seconds[tag]) for tag in trees},
             **{f"{tag}_check_cpu_s": median(cpus[tag]) for tag in trees}, repeat=repeat,
             load=load())


def bench_zero_gain(trees: dict[str, Path], repeat: int, zero_repeat: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        ckpt = work / "zero.ckpt"
        _, _, proc = python(next(reversed(trees.values())), ["-c", ZERO_GAIN, str(ckpt)], work)
        if proc.returncode:
            emit(bench="zero_gain", error=proc.stderr[-300:])
            return
        walls: dict[str, list[float]] = {t: [] for t in trees}
        sims: dict[str, list[float]] = {t: [] for t in trees}
        for i in range(repeat):
            for tag, tree in trees.items():
                if tag != "after" and i >= zero_repeat:
                    continue
                at = load()
                out = work / f"{tag}.json"
                wall, cpu, proc = python(tree, ["-m", "certify.cli.main", "run", str(ckpt),
                                                "--quiet", "--no-config", "--json", str(out)],
                                         work)
                record = {"bench": "zero_gain", "tree": tag, "wall_s": round(wall, 3),
                          "cpu_s": round(cpu, 3), "exit": proc.returncode, "load": at}
                walls[tag].append(wall)
                if out.exists():
                    cert = json.loads(out.read_text())
                    sim = cert["checks"]["simulation"]
                    record.update(simulation_s=round(cert["timings"]["simulation"], 3),
                                  status=sim["status"], horizon_s=sim["horizon"],
                                  headline=cert["checks"]["bounds"]["headline"],
                                  settle_time=cert["checks"]["bounds"]["settle_time"])
                    sims[tag].append(cert["timings"]["simulation"])
                    out.unlink()
                else:
                    record["stderr"] = proc.stderr[-300:]
                emit(**record)
        emit(bench="zero_gain_median", **{f"{tag}_wall_s": median(walls[tag]) for tag in trees},
             **{f"{tag}_simulation_s": median(sims[tag]) for tag in trees},
             runs={tag: len(walls[tag]) for tag in trees}, load=load())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="/work/before",
                    help="tree measured as 'before' ('' to measure only --after)")
    ap.add_argument("--after", default=str(ROOT), help="tree measured as 'after'")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration")
    ap.add_argument("--zero-repeat", type=int, default=1,
                    help="whole zero-gain runs of the 'before' tree (minutes each)")
    ap.add_argument("--only", action="append", choices=EXAMPLES, help="examples to run")
    ap.add_argument("--skip-zero", action="store_true", help="the examples' checks only")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "certify-bench-sim"),
                    help="where the examples' proved bounds are kept between runs")
    args = ap.parse_args()
    trees = {"after": Path(args.after).resolve()}
    if args.before:
        trees = {"before": Path(args.before).resolve(), **trees}
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    bench_checks(trees, args.only or list(EXAMPLES), args.repeat, cache)
    if not args.skip_zero:
        bench_zero_gain(trees, args.repeat, args.zero_repeat)


if __name__ == "__main__":
    main()
