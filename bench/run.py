"""The whole `certify run`, as a user meets it: one JSON line per measurement.

Compares two source trees side by side in one session (default: `/work/main` as "before"
and this tree as "after"), each run as a subprocess with PYTHONPATH set to its tree:

- run: wall seconds of `certify run CKPT` on examples/vdp_certified.ckpt, vdp.ckpt and
  vdp_lmi.ckpt, without reports and with all four (HTML, PDF, JUnit, JSON); exit code;
- verify: seconds inside verify() per check, read from the JSON certificate's timings;
- startup: wall seconds of `certify --version` and `certify systems`;
- compare: the medians side by side (after / before).

Runs of the two trees alternate, so load from other processes hits both alike; medians over
`--repeat` runs (startup: `--startup-repeat`). Wall-clock seconds on a shared machine are
noisy: read the ratios, and re-run when other work was going on.

Run: python bench/run.py [--before /work/main] [--after .] [--repeat 3] [--only vdp_lmi]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = ("vdp_certified", "vdp", "vdp_lmi")
REPORTS = ("--html", "r.html", "--pdf", "r.pdf", "--junit", "r.xml", "--json", "r.json")


def emit(**record: object) -> None:
    print(json.dumps(record), flush=True)


def certify(tree: Path, args: list[str], cwd: Path) -> tuple[float, int, str]:
    """(wall seconds, exit code, stderr tail) of `python -m certify.cli ARGS` from `tree`.

    `cwd` must lie outside both trees: `python -m` puts it first on sys.path."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "certify.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=1800)
    return time.perf_counter() - t0, proc.returncode, proc.stderr[-300:]


def median(xs: list[float]) -> float:
    return round(statistics.median(xs), 3)


def bench_runs(trees: dict[str, Path], names: list[str], repeat: int) -> dict:
    medians: dict[tuple[str, str, bool], float] = {}
    for name in names:
        ckpt = str(ROOT / "examples" / f"{name}.ckpt")
        for with_reports in (False, True):
            walls: dict[str, list[float]] = {t: [] for t in trees}
            for _ in range(repeat):
                for tag, tree in trees.items():  # alternate the trees
                    with tempfile.TemporaryDirectory() as tmp:
                        args = ["run", ckpt, "--quiet", "--no-config"]
                        args += list(REPORTS) if with_reports else []
                        wall, code, err = certify(tree, args, Path(tmp))
                        walls[tag].append(wall)
                        record = {"bench": "run", "tree": tag, "checkpoint": name,
                                  "reports": with_reports, "wall_s": round(wall, 3),
                                  "exit": code}
                        if code not in (0, 1, 3):
                            record["stderr"] = err
                        emit(**record)
                        if with_reports and (Path(tmp) / "r.json").exists():
                            cert = json.loads((Path(tmp) / "r.json").read_text())
                            emit(bench="verify", tree=tag, checkpoint=name,
                                 verdict=cert["verdict"],
                                 timings={k: round(v, 3) for k, v in cert["timings"].items()})
            for tag in trees:
                medians[(tag, name, with_reports)] = median(walls[tag])
    return medians


def bench_startup(trees: dict[str, Path], repeat: int) -> dict:
    medians = {}
    for command in (["--version"], ["systems"]):
        walls: dict[str, list[float]] = {t: [] for t in trees}
        for _ in range(repeat):
            for tag, tree in trees.items():
                with tempfile.TemporaryDirectory() as tmp:  # cwd outside both trees
                    wall, code, _ = certify(tree, command, Path(tmp))
                walls[tag].append(wall)
        for tag in trees:
            medians[(tag, " ".join(command))] = median(walls[tag])
            emit(bench="startup", tree=tag, command=f"certify {' '.join(command)}",
                 median_s=median(walls[tag]), runs_s=[round(w, 3) for w in walls[tag]])
    return medians


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="/work/main", help="tree measured as 'before'")
    ap.add_argument("--after", default=str(ROOT), help="tree measured as 'after'")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration")
    ap.add_argument("--startup-repeat", type=int, default=7)
    ap.add_argument("--only", action="append", choices=CHECKPOINTS,
                    help="checkpoints to run (default: all three)")
    ap.add_argument("--skip-runs", action="store_true", help="start-up times only")
    args = ap.parse_args()
    trees = {"before": Path(args.before).resolve(), "after": Path(args.after).resolve()}
    startup = bench_startup(trees, args.startup_repeat)
    for (tag, command), value in startup.items():
        if tag == "after":
            before = startup[("before", command)]
            emit(bench="compare", what=f"certify {command} start-up s", before=before,
                 after=value, ratio=round(value / before, 3))
    if args.skip_runs:
        return
    runs = bench_runs(trees, list(args.only or CHECKPOINTS), args.repeat)
    for (tag, name, with_reports), value in runs.items():
        if tag == "after":
            before = runs[("before", name, with_reports)]
            emit(bench="compare", what=f"certify run {name}"
                 + (" with 4 reports" if with_reports else " (no reports)") + " wall s",
                 before=before, after=value, ratio=round(value / before, 3))


if __name__ == "__main__":
    main()
