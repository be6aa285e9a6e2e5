"""Scale benchmark: prints JSON lines (medians over --repeats).

Parts (`--part`, default all but `six`):

- `n`: the MPDI proof against the state dimension n = 2, 3, 4, 6 on the certified designs:
  vdp's shipped `--preset certified` checkpoint, and the certified joint-LMI observer (P, K)
  of lorenz (n=3), vdp2 (n=4) and vdp3 (n=6) in checkpoint form at the margin the certified
  preset's round 0 settles on (`DESIGN_MARGIN`); proof seconds, sub-boxes, boxes per
  second, verdict.
- `workers`: one MPDI proof with a fixed box budget (default: vdp3's LMI observer at margin
  2 and 600000 boxes, >= 60 s serially on a quiet 2-core machine), serial vs Dask LocalCluster
  with 1 and 2 workers, interleaved in each repeat with both clusters up (same verdict,
  bounds and boxes asserted: `identical_to_serial`); the speed-ups; Dask's measured cost per
  task (round trip; driver CPU per task). Then `scale_paper`: the efficiency at 16-64
  workers from those costs, the serial proof's evaluation and driver seconds per box, and
  the driver's seconds per round at the batch those workers get (`round_batch`), with
  L = PIPELINE_LAG rounds in flight:
      T(W) = max(t_chunk, t_driver(b_W) + W o_task, (t_chunk + t_driver + o_rt + W o_task)/L)
      E(W) = per_worker (c_eval + c_driver) / T(W)
  (the arithmetic is printed in each line; see `part_paper`).
- `six`: `certify train vdp3 --preset certified` then `certify run` (10 minute cap, memory
  capped at --mem-gb), timed, with the exit codes (`--systems lorenz,vdp2,vdp3` for more).

Run: python bench/scale.py [--part n,workers,six] [--repeats 3] [--boxes 600000]
[--checkpoint PATH]. Wall-clock on this shared machine; compare lines of one run only.
"""

from __future__ import annotations

import argparse
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

from certify.model import checkpoint  # noqa: E402
from certify.search.threads import torch_threads  # noqa: E402


def emit(record: dict) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


def lmi_checkpoint(name: str, folder: Path, margin: float = 0.5) -> str:
    """The certified joint-LMI observer of a built-in as a checkpoint (||P K|| <= 1e4; for
    n = 6 the memory-bounded LMI, `certify.design.metric.bounded_observer_lmi`)."""
    from certify.spec.system import load_system
    from training.baseline import save_lmi_baseline

    system = load_system(name)
    path = folder / f"{name}_lmi_m{margin:g}.ckpt"
    if not path.exists():
        save_lmi_baseline(path, system, system.lam, margin=margin, gain_max=1e4)
    return str(path)


#: LMI margin of each built-in's certified design: the first of the certified preset's
#: WARM_MARGINS whose warm start proves in round 0 (vdp2: 0.5 does not within 30 s)
DESIGN_MARGIN = {"lorenz": 0.5, "vdp2": 2.0, "vdp3": 0.5}

#: the workers part's proof: vdp3's LMI observer at margin 2, which does not close in
#: minutes (run on a box budget), so rounds are many and evaluation-heavy
WORKERS_PROOF = ("vdp3", 2.0)


def part_n(args: argparse.Namespace, folder: Path) -> None:
    from certify.prove.mpdi import prove_mpdi

    cases = [("vdp", str(ROOT / "examples" / "vdp_certified.ckpt"), "certified preset")]
    cases += [(name, lmi_checkpoint(name, folder, DESIGN_MARGIN[name]),
               f"joint-LMI observer, margin {DESIGN_MARGIN[name]:g}")
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
    """Dask's cost per task on this cluster, measured with no-op tasks:

    - `round_trip_s`: wall time of one task, submitted and gathered alone (median of 20);
      a round pays it once (its tasks run in parallel);
    - `per_task_s`: wall time per task in a burst of `tasks` (throughput of the whole
      cluster on this machine: client, scheduler and workers share its cores);
    - `driver_cpu_per_task_s`: CPU seconds of this process (client and, for a
      LocalCluster, the scheduler) per task in the burst: the part of a task's cost that
      does not run on the workers, so is paid once per task per round whatever W is.
    """
    executor.map(_noop, list(range(8)))  # warm
    rt = []
    for i in range(20):
        t0 = time.perf_counter()
        executor.map(_noop, [i])
        rt.append(time.perf_counter() - t0)
    bursts, cpus = [], []
    for _ in range(3):
        c0, t0 = time.process_time(), time.perf_counter()
        executor.map(_noop, list(range(tasks)))
        bursts.append((time.perf_counter() - t0) / tasks)
        cpus.append((time.process_time() - c0) / tasks)
    return {"round_trip_s": round(statistics.median(rt), 5),
            "per_task_s": round(statistics.median(bursts), 5),
            "driver_cpu_per_task_s": round(statistics.median(cpus), 5)}


def _busy_cpu_seconds() -> float | None:
    """CPU seconds the whole machine has been busy (all cores, from /proc/stat), or None."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _tree_cpu_seconds() -> float:
    """CPU seconds of this process and its children (the Dask scheduler and workers of a
    LocalCluster)."""
    import psutil

    total = 0.0
    for proc in [psutil.Process(), *psutil.Process().children(recursive=True)]:
        try:
            t = proc.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def timed_proof(problem, max_boxes: int, batch: int = 1024, executor=None) -> dict:
    """One MPDI proof with a box budget: wall and driver CPU seconds, the load at its
    start, the CPU seconds of this process tree and of everything else on the machine
    meanwhile (`others_cores_busy`: how many cores other users took), and the time the
    driver spends collecting rounds (`RoundPipeline.collect`: serially the evaluation
    itself, on Dask the wait for the workers' results) split from the rest (the driver:
    selection, splitting, merging, submitting)."""
    from certify.prove.mpdi import prove_mpdi
    from certify.search.rounds import RoundPipeline

    calls = {"n": 0, "t": 0.0}
    original = RoundPipeline.collect

    def counting(self):
        t0 = time.perf_counter()
        out = original(self)
        calls["t"] += time.perf_counter() - t0
        calls["n"] += 1
        return out

    RoundPipeline.collect = counting
    load = os.getloadavg()[0]
    busy0, tree0 = _busy_cpu_seconds(), _tree_cpu_seconds()
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        out = prove_mpdi(problem, seconds=1e9, max_boxes=max_boxes, batch=batch,
                         executor=executor)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        RoundPipeline.collect = original
    busy1, tree1 = _busy_cpu_seconds(), _tree_cpu_seconds()
    others = None if busy0 is None or busy1 is None else (busy1 - busy0) - (tree1 - tree0)
    return {"outcome": out, "seconds": total, "rounds": calls["n"], "eval_seconds": calls["t"],
            "cpu_seconds": cpu, "load_1min": load, "tree_cpu_seconds": tree1 - tree0,
            "others_cpu_seconds": others}


def _same(a, b) -> bool:
    return (a.status == b.status and a.upper == b.upper and a.lower == b.lower
            and a.stats.boxes_processed == b.stats.boxes_processed)


def part_workers(args: argparse.Namespace, folder: Path) -> None:
    """Serial, 1 and 2 Dask workers side by side (interleaved per repeat, both clusters up
    the whole time, so load changes hit all three alike), then the paper arithmetic."""
    from certify.search.distributed.executor import BOXES_PER_WORKER, DaskExecutor, SerialExecutor

    path = args.checkpoint or lmi_checkpoint(WORKERS_PROOF[0], folder, WORKERS_PROOF[1])
    problem = checkpoint.load(path).problem
    runs: dict[str, list[dict]] = {"serial": [], "1": [], "2": []}
    with torch_threads(1), DaskExecutor(workers=1) as one, DaskExecutor(workers=2) as two:
        executors = {"serial": SerialExecutor(), "1": one, "2": two}
        for ex in (one, two):  # workers import certify and build the evaluator once
            timed_proof(problem, 3000, executor=ex)
        for _ in range(args.repeats):
            for name, ex in executors.items():
                runs[name].append(timed_proof(problem, args.boxes, executor=ex))
        over = dask_overheads(two)
    load = os.getloadavg()[0]
    ref = runs["serial"][0]["outcome"]
    med = {k: statistics.median(r["seconds"] for r in v) for k, v in runs.items()}
    for name, rs in runs.items():
        rounds = rs[0]["rounds"]
        t_eval = statistics.median(r["eval_seconds"] for r in rs) / rounds
        rec = {"bench": "scale_workers", "workers": 0 if name == "serial" else int(name),
               "executor": "serial" if name == "serial" else "dask LocalCluster",
               "seconds_median": round(med[name], 3),
               "seconds": [round(r["seconds"], 2) for r in rs],
               "boxes": rs[0]["outcome"].stats.boxes_processed, "rounds": rounds,
               "eval_s_per_round": round(t_eval, 4),
               "driver_s_per_round": round(med[name] / rounds - t_eval, 4),
               "driver_cpu_s_per_round": round(statistics.median(r["cpu_seconds"] for r in rs)
                                               / rounds, 4),
               "load_1min_at_start": [round(r["load_1min"], 2) for r in rs],
               "cpu_seconds_this_run": [round(r["tree_cpu_seconds"], 1) for r in rs],
               "others_cores_busy": [None if r["others_cpu_seconds"] is None else
                                     round(r["others_cpu_seconds"] / r["seconds"], 2)
                                     for r in rs],
               "status": rs[0]["outcome"].status.value, "upper": rs[0]["outcome"].upper,
               "identical_to_serial": all(_same(r["outcome"], ref) for r in rs)}
        if name != "serial":
            rec["speedup_vs_serial"] = round(med["serial"] / med[name], 3)
        emit(rec)
    emit({"bench": "scale_workers", "speedup_2_vs_1": round(med["1"] / med["2"], 3),
          "speedup_2_vs_serial": round(med["serial"] / med["2"], 3),
          "serial_seconds_median": round(med["serial"], 3), "load_1min_end": load,
          "checkpoint": Path(path).name, "box_budget": args.boxes, **over})
    serial = min(runs["serial"], key=lambda r: abs(r["seconds"] - med["serial"]))
    part_paper(args, problem, serial, over, BOXES_PER_WORKER)


def part_paper(args: argparse.Namespace, problem, serial: dict, over: dict,
               per_worker: int) -> None:
    """Efficiency at W = 16, 32, 64 workers on paper, from measured costs.

    A round on W > 2 workers splits b_W = W * per_worker / 2 boxes
    (`certify.search.distributed.executor.
    round_batch`): each worker evaluates one chunk of `per_worker` children, in
        t_chunk = per_worker * c_eval
    with c_eval, c_driver the evaluation and driver seconds per box of the serial proof
    (default batch: its rounds evaluate 2048 children, one worker's chunk). The driver's
    share of a round is t_drv + W o_task: t_drv(b_W) its seconds per round in the serial
    proof run at batch b_64 (--paper-boxes: the initial grid and a few rounds; per box for
    16 and 32), o_task its CPU seconds per task (client + scheduler, measured on the
    2-worker cluster); o_rt is the round trip of one task. With L = PIPELINE_LAG rounds in
    flight (`certify.search.rounds`) the driver merges round k while the workers compute round
    k+1, so a round takes the largest of: a chunk, the driver's share, and the cycle of L
    rounds through both (round k+L is dispatched after round k is back and merged):
        T(W) = max(t_chunk, t_drv + W o_task, (t_chunk + t_drv + o_rt + W o_task) / L)
    (synchronous rounds, L = 1: the sum). The same boxes take (c_eval + c_driver) per box
    serially, so
        E(W) = per_worker (c_eval + c_driver) / T(W)
    (above 1 by at most c_driver / c_eval when the driver's work is hidden behind the
    workers': the driver is a process besides the W workers). `workers_busy` = t_chunk / T;
    the driver's share reaches a chunk's time at W = t_chunk / (per_worker t_drv/child +
    o_task) workers (`driver_saturates_at_workers`): beyond, the driver is the bottleneck.
    (Per box, evaluation in one process is slower at batch b_64 than in 2048-box chunks:
    the chunk cost is taken from the default-batch run.)
    """
    from certify.search.bnb import PIPELINE_LAG

    big = 64 * per_worker // 2
    with torch_threads(1):
        r = timed_proof(problem, min(args.paper_boxes, args.boxes), batch=big)
    boxes = serial["outcome"].stats.boxes_processed
    c_eval = serial["eval_seconds"] / boxes
    c_drv = (serial["seconds"] - serial["eval_seconds"]) / boxes
    drv_per_child = (r["seconds"] - r["eval_seconds"]) / r["outcome"].stats.boxes_processed
    o_rt, o_task = over["round_trip_s"], over["driver_cpu_per_task_s"]
    lag = PIPELINE_LAG
    for workers in (16, 32, 64):
        t_drv = drv_per_child * workers * per_worker
        t_chunk = per_worker * c_eval
        share = t_drv + workers * o_task
        cycle = (t_chunk + t_drv + o_rt + workers * o_task) / lag
        t_round = max(t_chunk, share, cycle)
        t_sync = t_chunk + t_drv + o_rt + workers * o_task
        work = per_worker * (c_eval + c_drv)
        emit({"bench": "scale_paper", "workers": workers, "batch": workers * per_worker // 2,
              "children_per_worker": per_worker, "lag": lag, "c_eval_per_box": round(c_eval, 8),
              "c_driver_per_box_serial": round(c_drv, 8), "t_chunk": round(t_chunk, 4),
              "t_driver_per_round": round(t_drv, 4), "overhead_round_trip": o_rt,
              "overhead_driver_per_task": o_task,
              "arithmetic": f"T = max({t_chunk:.4f}, {t_drv:.4f} + {workers}*{o_task:.5f}, "
                            f"({t_chunk:.4f} + {t_drv:.4f} + {o_rt:.4f} + {workers}*"
                            f"{o_task:.5f}) / {lag}) = {t_round:.4f} s; E = {per_worker}*"
                            f"({c_eval:.3e} + {c_drv:.3e}) / {t_round:.4f}",
              "efficiency": round(work / t_round, 3),
              "efficiency_synchronous": round(work / t_sync, 3),
              "workers_busy": round(t_chunk / t_round, 3),
              "driver_saturates_at_workers": int(t_chunk / (per_worker * drv_per_child
                                                           + o_task)), "serial_at_b64": {
                  "rounds": r["rounds"], "seconds": round(r["seconds"], 2),
                  "boxes": r["outcome"].stats.boxes_processed,
                  "driver_s_per_round": round((r["seconds"] - r["eval_seconds"])
                                              / r["rounds"], 4)}})


def _limit_memory(gb: float):
    def apply() -> None:
        lim = int(gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
    return apply


def part_six(args: argparse.Namespace, folder: Path) -> None:
    for name in args.systems.split(","):
        train_and_run(args, folder, name.strip())


def train_and_run(args: argparse.Namespace, folder: Path, name: str) -> None:
    """`certify train NAME --preset certified` then `certify run`, timed, with exit codes."""
    from certify.spec.system import load_system

    ckpt = folder / f"{name}_certified.ckpt"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    steps = []
    for argv in (["train", name, "--preset", "certified", "-o", str(ckpt)],
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
    emit({"bench": "scale_six", "system": name, "n": load_system(name).n, "steps": steps,
          "total_seconds": round(time.perf_counter() - t0, 1),
          "certified": bool(steps and steps[-1].get("exit") == 0)})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="n,workers")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--proof-seconds", type=float, default=300.0)
    ap.add_argument("--max-boxes", type=int, default=2_000_000)
    ap.add_argument("--boxes", type=int, default=600_000, help="box budget of the workers part")
    ap.add_argument("--paper-boxes", type=int, default=200_000,
                    help="box budget of the serial run at the 64-worker batch (scale_paper)")
    ap.add_argument("--checkpoint", help="checkpoint of the workers part (default: vdp2 LMI)")
    ap.add_argument("--six-seconds", type=float, default=600.0)
    ap.add_argument("--systems", default="vdp3", help="built-ins of the six part")
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
