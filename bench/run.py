"""The whole `certify run`, as a user meets it: one JSON line per measurement.

Compares two source trees side by side in one session (default: `/work/main` as "before"
and this tree as "after"), each run as a subprocess with PYTHONPATH set to its tree:

- run: wall and CPU seconds (user + system, of the child process) of `certify run CKPT` on
  examples/vdp_certified.ckpt, vdp.ckpt and vdp_lmi.ckpt, without reports and with all four
  (HTML, PDF, JUnit, JSON); exit code;
- verify: seconds inside verify() per check, read from the JSON certificate's timings
  (`checks_s`: the checks alone, without the report figures, as in a run without reports);
- startup: wall seconds of `certify --version` and `certify systems`;
- compare: the medians side by side (after / before), wall and CPU.

Runs of the two trees alternate, so load from other processes hits both alike; medians over
`--repeat` runs (startup: `--startup-repeat`). Wall-clock seconds on a shared machine are
noisy: read the ratios, and re-run when other work was going on.

Run: python bench/run.py [--before /work/main | --before ''] [--after .] [--repeat 3]
         [--only vdp_lmi]
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
CHECKPOINTS = ("vdp_certified", "vdp", "vdp_lmi")
#: every shipped example (`--only`); the default runs CHECKPOINTS
EXAMPLES = CHECKPOINTS + ("vdp2_lmi", "lorenz_lmi")
REPORTS = ("--html", "r.html", "--pdf", "r.pdf", "--junit", "r.xml", "--json", "r.json")


def emit(**record: object) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def certify(tree: Path, args: list[str], cwd: Path) -> tuple[float, int, str, float]:
    """(wall seconds, exit code, stderr tail, CPU seconds) of `python -m certify.cli.main ARGS`
    from `tree` (CPU: user + system of the child; on a loaded machine it moves less than
    the wall time).

    `cwd` must lie outside both trees: `python -m` puts it first on sys.path."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    c0 = _children_cpu()
    t0 = time.perf_counter()
    # the command line's module: certify.cli.main since the stage packages, certify.cli before
    module = "certify.cli.main" if (Path(tree) / "certify" / "cli" / "main.py").exists() \
        else "certify.cli"
    proc = subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=1800)
    return (time.perf_counter() - t0, proc.returncode, proc.stderr[-300:],
            _children_cpu() - c0)


def median(xs: list[float]) -> float:
    return round(statistics.median(xs), 3)


def bench_runs(trees: dict[str, Path], names: list[str], repeat: int) -> dict:
    medians: dict[tuple[str, str, bool, str], float] = {}
    for name in names:
        ckpt = str(ROOT / "examples" / f"{name}.ckpt")
        for with_reports in (False, True):
            runs: dict[tuple[str, str], list[float]] = {
                (t, m): [] for t in trees for m in ("wall", "cpu", "checks")}
            for _ in range(repeat):
                for tag, tree in trees.items():  # alternate the trees
                    with tempfile.TemporaryDirectory() as tmp:
                        args = ["run", ckpt, "--quiet", "--no-config"]
                        args += list(REPORTS) if with_reports else []
                        wall, code, err, cpu = certify(tree, args, Path(tmp))
                        runs[(tag, "wall")].append(wall)
                        runs[(tag, "cpu")].append(cpu)
                        record = {"bench": "run", "tree": tag, "checkpoint": name,
                                  "reports": with_reports, "wall_s": round(wall, 3),
                                  "cpu_s": round(cpu, 3), "exit": code}
                        if code not in (0, 1, 3):
                            record["stderr"] = err
                        emit(**record)
                        if with_reports and (Path(tmp) / "r.json").exists():
                            cert = json.loads((Path(tmp) / "r.json").read_text())
                            checks = sum(v for k, v in cert["timings"].items()
                                         if k not in ("figures", "total"))
                            runs[(tag, "checks")].append(checks)
                            emit(bench="verify", tree=tag, checkpoint=name,
                                 verdict=cert["verdict"], checks_s=round(checks, 3),
                                 timings={k: round(v, 3) for k, v in cert["timings"].items()})
            for (tag, measure), values in runs.items():
                if values:
                    medians[(tag, name, with_reports, measure)] = median(values)
    return medians


def bench_startup(trees: dict[str, Path], repeat: int) -> dict:
    medians = {}
    for command in (["--version"], ["systems"]):
        walls: dict[str, list[float]] = {t: [] for t in trees}
        for _ in range(repeat):
            for tag, tree in trees.items():
                with tempfile.TemporaryDirectory() as tmp:  # cwd outside both trees
                    wall, code, _, _ = certify(tree, command, Path(tmp))
                walls[tag].append(wall)
        for tag in trees:
            medians[(tag, " ".join(command))] = median(walls[tag])
            emit(bench="startup", tree=tag, command=f"certify {' '.join(command)}",
                 median_s=median(walls[tag]), runs_s=[round(w, 3) for w in walls[tag]])
    return medians


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="/work/main",
                    help="tree measured as 'before' ('' to measure only --after)")
    ap.add_argument("--after", default=str(ROOT), help="tree measured as 'after'")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration")
    ap.add_argument("--startup-repeat", type=int, default=7)
    ap.add_argument("--only", action="append", choices=EXAMPLES,
                    help="examples to run (default: vdp_certified, vdp, vdp_lmi)")
    ap.add_argument("--skip-runs", action="store_true", help="start-up times only")
    args = ap.parse_args()
    trees = {"after": Path(args.after).resolve()}
    if args.before:
        trees = {"before": Path(args.before).resolve(), **trees}
    startup = bench_startup(trees, args.startup_repeat)
    for (tag, command), value in startup.items():
        if tag == "after" and "before" in trees:
            before = startup[("before", command)]
            emit(bench="compare", what=f"certify {command} start-up s", before=before,
                 after=value, ratio=round(value / before, 3))
    if args.skip_runs:
        return
    runs = bench_runs(trees, list(args.only or CHECKPOINTS), args.repeat)
    units = {"wall": "wall s", "cpu": "CPU s", "checks": "s inside verify (checks)"}
    for (tag, name, with_reports, measure), value in runs.items():
        before = runs.get(("before", name, with_reports, measure))
        if tag == "after" and before:
            emit(bench="compare", what=f"certify run {name}"
                 + (" with 4 reports" if with_reports else " (no reports)")
                 + f" {units[measure]}", before=before, after=value,
                 ratio=round(value / before, 3))


if __name__ == "__main__":
    main()
