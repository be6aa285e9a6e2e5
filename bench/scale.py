"""Scale benchmark: prints JSON lines (medians over --repeats).

Parts (`--part`, default all but `six`):

- `n`: the MPDI proof against the state dimension n = 2, 3, 4, 6 on the certified designs:
  vdp's shipped `--preset certified` checkpoint, and the certified joint-LMI observer (P, K)
  of lorenz (n=3), vdp2 (n=4) and vdp3 (n=6) in checkpoint form (what the certified preset
  starts from); proof seconds, sub-boxes, boxes per second, verdict.
- `workers`: one proof with a fixed box budget, serial vs Dask LocalCluster with 1 and 2
  workers (same verdict, bound and boxes asserted), the measured per-task overhead of Dask
  (round trip of one task; scheduler cost per task from a burst of no-op tasks), and the
  paper arithmetic for 16-64 workers:
      t_round(W) = t_client + t_eval / W + o_rt + W k o_s        (k chunks per worker)
      efficiency(W) = (t_client + t_eval) / (W t_round(W))
  with t_eval, t_client the measured per-round evaluation and driver times of the serial run;
      E(W) >= 1/2  <=>  t_eval >= (W - 2) t_client + W (o_rt + W k o_s)
  (the batch factor printed is how much larger a round's batch must be for that, if the
  driver's time per round did not grow with the batch).
- `six`: `certify train vdp3 --preset certified` then `certify run` (10 minute cap, memory
  capped at --mem-gb), timed, with the exit codes.

Run: python bench/scale.py [--part n,workers,six] [--repeats 3] [--boxes 60000]
[--checkpoint PATH]. Wall-clock on this shared machine; compare lines of one run only.
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

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from certify import checkpoint  # noqa: E402
from certify.parallel import torch_threads  # noqa: E402


def emit(record: dict) -> None:
    print(json.dumps(record), flush=True)


def lmi_checkpoint(name: str, folder: Path) -> str:
    """The certified joint-LMI observer of a built-in as a checkpoint (margin 0.5; one
    sub-box of X for n = 6, where the default subdivision makes the SDP too large)."""
    from certify.system import load_system
    from training.baseline import save_lmi_baseline

    system = load_system(name)
    path = folder / f"{name}_lmi.ckpt"
    if not path.exists():
        save_lmi_baseline(path, system, system.lam, margin=0.5, gain_max=1e4,
                          subdivisions=1 if system.n >= 6 else None)
    return str(path)


def part_n(args: argparse.Namespace, folder: Path) -> None:
    from certify.prover import prove_mpdi

    cases = [("vdp", str(ROOT / "examples" / "vdp_certified.ckpt"), "certified preset")]
    cases += [(name, lmi_checkpoint(name, folder), "joint-LMI observer")
              for name in ("lorenz", "vdp2", "vdp3")]
    for name, path, design in cases:
        problem = checkpoint.load(path).problem
        runs = []
        with torch_threads(1):
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = prove_mpdi(problem, seconds=args.proof_seconds, max_boxes=args.max_boxes)
                runs.append((time.perf_counter() - t0, out))
        secs = statistics.median(r[0] for r in runs)
        out = runs[0][1]
        emit({"bench": "scale_n", "system": name, "n": problem.n, "box_dims": problem.n
              + problem.p, "design": design, "status": out.status.value, "upper": out.upper,
              "boxes": out.stats.boxes_processed, "seconds_median": round(secs, 3),
              "boxes_per_second": round(out.stats.boxes_processed / secs, 1),
              "repeats": args.repeats})


def _noop(x: int) -> int:
    return x


def dask_overheads(executor, tasks: int = 400) -> dict:
    """Round trip of one task (median of 20) and scheduler cost per task (burst of `tasks`)."""
    executor.map(_noop, list(range(8)))  # warm
    rt = []
    for i in range(20):
        t0 = time.perf_counter()
        executor.map(_noop, [i])
        rt.append(time.perf_counter() - t0)
    bursts = []
    for _ in range(3):
        t0 = time.perf_counter()
        executor.map(_noop, list(range(tasks)))
        bursts.append((time.perf_counter() - t0) / tasks)
    return {"round_trip_s": statistics.median(rt), "per_task_s": statistics.median(bursts)}


def timed_serial(problem, max_boxes: int) -> dict:
    """The serial proof with its evaluation time split from the driver's (per round)."""
    import certify.prover as prover

    calls = {"n": 0, "t": 0.0}
    original = prover._mpdi_evaluator

    def counting(*a, **k):
        inner = original(*a, **k)

        def evaluate(lo, hi):
            t0 = time.perf_counter()
            out = inner(lo, hi)
            calls["t"] += time.perf_counter() - t0
            calls["n"] += 1
            return out

        return evaluate

    prover._mpdi_evaluator = counting
    try:
        t0 = time.perf_counter()
        out = prover.prove_mpdi(problem, seconds=1e9, max_boxes=max_boxes)
        total = time.perf_counter() - t0
    finally:
        prover._mpdi_evaluator = original
    return {"outcome": out, "seconds": total, "rounds": calls["n"], "eval_seconds": calls["t"]}


def part_workers(args: argparse.Namespace, folder: Path) -> None:
    from certify.executor import DaskExecutor, using
    from certify.prover import prove_mpdi

    path = args.checkpoint or lmi_checkpoint("vdp2", folder)
    problem = checkpoint.load(path).problem
    with torch_threads(1):
        serial = [timed_serial(problem, args.boxes) for _ in range(args.repeats)]
    t_serial = statistics.median(s["seconds"] for s in serial)
    ref = serial[0]
    rounds = ref["rounds"]
    t_eval = statistics.median(s["eval_seconds"] for s in serial) / rounds
    t_client = t_serial / rounds - t_eval
    emit({"bench": "scale_workers", "checkpoint": Path(path).name, "workers": 0,
          "executor": "serial", "seconds_median": round(t_serial, 3),
          "boxes": ref["outcome"].stats.boxes_processed, "rounds": rounds,
          "eval_s_per_round": t_eval, "driver_s_per_round": t_client,
          "status": ref["outcome"].status.value, "upper": ref["outcome"].upper})
    measured = {}
    for workers in (1, 2):
        with DaskExecutor(workers=workers) as ex, using(ex):
            prove_mpdi(problem, seconds=1e9, max_boxes=3000)  # workers import and build
            times, outs = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                outs.append(prove_mpdi(problem, seconds=1e9, max_boxes=args.boxes))
                times.append(time.perf_counter() - t0)
            over = dask_overheads(ex)
        same = all(o.upper == ref["outcome"].upper and o.status == ref["outcome"].status
                   and o.stats.boxes_processed == ref["outcome"].stats.boxes_processed
                   for o in outs)
        t = statistics.median(times)
        measured[workers] = (t, over)
        emit({"bench": "scale_workers", "workers": workers, "executor": "dask LocalCluster",
              "seconds_median": round(t, 3), "speedup_vs_serial": round(t_serial / t, 3),
              "identical_to_serial": same, **over})
    if 1 in measured and 2 in measured:
        emit({"bench": "scale_workers", "speedup_2_vs_1": round(measured[1][0] / measured[2][0],
                                                                 3)})
    over = measured[2][1] if 2 in measured else measured[1][1]
    from certify.bnb import CHUNKS_PER_WORKER

    k = CHUNKS_PER_WORKER  # chunks per worker per round
    for workers in (16, 32, 64):
        t_round = t_client + t_eval / workers + over["round_trip_s"] \
            + workers * k * over["per_task_s"]
        eff = (t_client + t_eval) / (workers * t_round)
        # E(W) = 1/2  <=>  t_eval = (W - 2) t_client + W (o_rt + W k o_s)
        need = (workers - 2) * t_client + workers * (over["round_trip_s"]
                                                     + workers * k * over["per_task_s"])
        emit({"bench": "scale_paper", "workers": workers, "t_eval_per_round": t_eval,
              "t_driver_per_round": t_client, "overhead_round_trip": over["round_trip_s"],
              "overhead_per_task": over["per_task_s"], "efficiency": round(eff, 3),
              "t_eval_per_round_for_50pct": round(max(need, 0.0), 4),
              "batch_factor_for_50pct": round(max(need, 0.0) / t_eval, 1) if t_eval else None})


def _limit_memory(gb: float):
    def apply() -> None:
        lim = int(gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
    return apply


def part_six(args: argparse.Namespace, folder: Path) -> None:
    ckpt = folder / "vdp3_certified.ckpt"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    steps = []
    for argv in (["train", "vdp3", "--preset", "certified", "-o", str(ckpt)],
                 ["run", str(ckpt), "--quiet", "--no-config"]):
        left = args.six_seconds - (time.perf_counter() - t0)
        if left <= 0 or (argv[0] == "run" and not ckpt.exists()):
            steps.append({"step": argv[0], "skipped": True})
            continue
        s0 = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, "-m", "certify", *argv], env=env,
                                  capture_output=True, text=True, timeout=left,
                                  preexec_fn=_limit_memory(args.mem_gb))
            code, tail = proc.returncode, (proc.stdout + proc.stderr).strip()[-400:]
        except subprocess.TimeoutExpired:
            code, tail = "timeout", ""
        steps.append({"step": argv[0], "exit": code, "seconds": round(time.perf_counter()
                                                                      - s0, 1), "tail": tail})
    emit({"bench": "scale_six", "system": "vdp3", "n": 6, "steps": steps,
          "total_seconds": round(time.perf_counter() - t0, 1),
          "certified": bool(steps and steps[-1].get("exit") == 0)})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="n,workers")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--proof-seconds", type=float, default=300.0)
    ap.add_argument("--max-boxes", type=int, default=2_000_000)
    ap.add_argument("--boxes", type=int, default=60_000, help="box budget of the workers part")
    ap.add_argument("--checkpoint", help="checkpoint of the workers part (default: vdp2 LMI)")
    ap.add_argument("--six-seconds", type=float, default=600.0)
    ap.add_argument("--mem-gb", type=float, default=6.0)
    ap.add_argument("--folder", default=None, help="where built checkpoints are kept")
    args = ap.parse_args()
    folder = Path(args.folder or tempfile.mkdtemp(prefix="certify-scale-"))
    folder.mkdir(parents=True, exist_ok=True)
    emit({"bench": "scale_env", "cpus": os.cpu_count(), "load_1min": os.getloadavg()[0],
          "torch": torch.__version__, "cuda": torch.cuda.is_available()})
    for part in args.part.split(","):
        {"n": part_n, "workers": part_workers, "six": part_six}[part.strip()](args, folder)


if __name__ == "__main__":
    main()
