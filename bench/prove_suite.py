"""Prover suite: the instance families of `bench/instances.py`, one JSON line per run.

Each run builds a seeded instance (tuned lam cached in --cache), proves it with the prover
(`certify.prove.mpdi.prove_mpdi`) and, in the same run on the same instance, with the plain
interval baseline (`prove_mpdi(..., taylor=False)`), then prints
{instance, prover, status, boxes, seconds, upper, proved_volume, volume_history, baseline: {...}}.
A final summary line per family gives the medians. The machine is shared: record the load
(`load` field: 1-minute load average at the start of each run; `cpu_seconds` is the process's
CPU time, steadier than the wall time under load). `--code DIR` imports `certify` from another
checkout, for before/after comparisons in one run.

Examples:
    python bench/prove_suite.py --family 2x10 --n 2 --margin 0.02 --seeds 0 1 2 --seconds 60
    python bench/prove_suite.py --family 5x30 --g 2 --margin 0.01 --seconds 600 --no-baseline
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
if "--code" in sys.argv:  # import `certify` from another checkout (side-by-side comparisons)
    sys.path.insert(0, str(Path(sys.argv[sys.argv.index("--code") + 1]).resolve()))

import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from bench.instances import InstanceSpec, make_instance  # noqa: E402
from certify.prove.mpdi import prove_mpdi  # noqa: E402

FAMILIES = {"2x10": (2, 10), "3x30": (3, 30), "5x30": (5, 30), "5x64": (5, 64)}


def _history(hist: list[list[float]], cap: int = 12) -> list[list[float]]:
    step = max(1, len(hist) // cap)
    out = hist[::step]
    if out[-1] != hist[-1]:
        out.append(hist[-1])
    return [[round(a, 2), round(b, 5)] for a, b in out]


def _run(prob, seconds: float, max_boxes: int, taylor: object, crown: bool = True,
         batch: int = 1024, executor: object | None = None) -> dict:
    """One proof; `cpu_seconds` is this process's CPU time (with a Dask executor the
    workers' CPU is not in it: compare wall `seconds` then, on a quiet machine). `stages`:
    per stage of the box bound, the boxes it bounded and closed in the proof's rounds
    (`ProofStats.stages`; None from a `--code` checkout older than them)."""
    t, cpu = time.perf_counter(), time.process_time()
    out = prove_mpdi(prob, seconds=seconds, max_boxes=max_boxes, taylor=taylor, crown=crown,
                     batch=batch, executor=executor)
    st = out.stats
    stages = getattr(st, "stages", None)
    return {"status": out.status.value, "boxes": st.boxes_processed, "stages": stages,
            "seconds": round(time.perf_counter() - t, 3),
            "cpu_seconds": round(time.process_time() - cpu, 3), "upper": out.upper,
            "lower": out.lower, "proved_volume": round(st.proved_volume_fraction, 6),
            "volume_history": _history(st.volume_history),
            # an unfinished proof: the boxes a complete one needs (certify.search.tree_estimate;
            # `seconds` then includes the estimate's few seconds, the proof's own is
            # `proof_seconds`; None from a `--code` checkout older than the estimate)
            "estimated_boxes": getattr(st, "estimated_boxes", None),
            "estimate_rel_stderr": getattr(st, "estimate_rel_stderr", None),
            "proof_seconds": round(st.seconds, 3)}


def _cached_instance(spec: InstanceSpec, cache: Path | None):
    import numpy as np

    from certify.model.problem import Problem

    store = {}
    if cache is not None and cache.exists():
        store = json.loads(cache.read_text())
    if spec.name in store:
        from bench.instances import make_network, make_system

        rec = store[spec.name]
        system = make_system(spec.system_name, spec.n)
        P, K = np.array(rec["P"]), np.array(rec["K"])
        net = make_network(spec, K)
        return Problem(system, net, rec["lam"], P), rec["info"]
    prob, info = make_instance(spec)
    if cache is not None:
        store = json.loads(cache.read_text()) if cache.exists() else {}
        store[spec.name] = {"lam": prob.lam, "P": prob.P.tolist(),
                            "K": prob.network.K.tolist(), "info": info}
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps(store))
    return prob, info


def add_family_arguments(ap: argparse.ArgumentParser, n: tuple[int, ...] = (2,)) -> None:
    """The instance-family options the one-g, one-margin benches share (bench/tree_size.py,
    bench/remainder_gap.py): --family, --g, --n, --margin, --seeds, --cache."""
    ap.add_argument("--family", nargs="+", default=["2x10"], choices=sorted(FAMILIES))
    ap.add_argument("--g", type=float, default=2.0)
    ap.add_argument("--n", nargs="+", type=int, default=list(n))
    ap.add_argument("--margin", type=float, default=0.02)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--cache", default="/tmp/certify-bench/instances.json")


def family_instances(args: argparse.Namespace):
    """(spec, problem) for every family, n and seed of `add_family_arguments`' options."""
    cache = Path(args.cache) if args.cache else None
    for fam in args.family:
        depth, width = FAMILIES[fam]
        for n in args.n:
            for seed in args.seeds:
                spec = InstanceSpec(depth, width, args.g, n, args.margin, seed)
                yield spec, _cached_instance(spec, cache)[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", nargs="+", default=["2x10"], choices=sorted(FAMILIES))
    ap.add_argument("--g", nargs="+", type=float, default=[2.0])
    ap.add_argument("--n", nargs="+", type=int, default=[2])
    ap.add_argument("--margin", nargs="+", type=float, default=[0.02])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--seconds", type=float, default=60.0, help="prover time limit per run")
    ap.add_argument("--baseline-seconds", type=float, default=None,
                    help="plain-interval baseline time limit (default: --seconds)")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--max-boxes", type=int, default=50_000_000)
    ap.add_argument("--prover", default="default", choices=["default", "taylor", "plain"],
                    help="taylor: the pre-issue-9 prover (interval + Taylor models)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batch", type=int, default=None,
                    help="boxes per B&B round (default: certify.arith.device.proof_batch, 1024 on "
                         "the CPU)")
    ap.add_argument("--device", default="cpu",
                    help="torch device of the proof's boxes and bounds (cpu, cuda)")
    ap.add_argument("--workers", type=int, default=1,
                    help="Dask LocalCluster worker processes for the prover (1: serial, in "
                         "process); the workers import the installed certify, not --code's")
    ap.add_argument("--cache", default="/tmp/certify-bench/instances.json")
    ap.add_argument("--code", default=None,
                    help="checkout whose `certify` is imported (default: this one); for "
                         "before/after runs side by side")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from certify.arith.device import describe, resolve_device

    device = resolve_device(args.device)
    try:
        from certify.arith.device import proof_batch
    except ImportError:  # --code: a checkout from before the proof ran on a GPU
        def proof_batch(_device):
            return 1024
    batch = args.batch or proof_batch(device)
    executor = None
    if args.workers > 1:
        from certify.search.distributed.executor import DaskExecutor

        executor = DaskExecutor(workers=args.workers)
        # each worker builds its evaluator once per instance; start the processes first
        executor.map(abs, list(range(args.workers)))
    cache = Path(args.cache) if args.cache else None
    taylor = {"default": True, "taylor": True, "plain": False}[args.prover]
    crown = args.prover == "default"
    rows: dict[str, list[dict]] = {}
    for fam in args.family:
        depth, width = FAMILIES[fam]
        for g in args.g:
            for n in args.n:
                for margin in args.margin:
                    for seed in args.seeds:
                        spec = InstanceSpec(depth, width, g, n, margin, seed)
                        t = time.perf_counter()
                        prob, info = _cached_instance(spec, cache)
                        prob = prob.on(device)
                        setup = time.perf_counter() - t
                        rec = {"instance": spec.name, "family": f"{fam}-g{g:g}-n{n}-m{margin:g}",
                               "prover": args.prover, "code": args.code or "this",
                               "workers": args.workers, "device": describe(device),
                               "batch": batch,
                               "load": round(os.getloadavg()[0], 2),
                               "lam": prob.lam, "sampled_max": info["sampled_max"],
                               "setup_seconds": round(setup, 2)}
                        rec.update(_run(prob, args.seconds, args.max_boxes, taylor, crown,
                                        batch, executor))
                        if not args.no_baseline:
                            bs = args.baseline_seconds or args.seconds
                            rec["baseline"] = _run(prob, bs, args.max_boxes, False,
                                                   batch=batch)
                        record_line(rec)
                        rows.setdefault(rec["family"], []).append(rec)
    for fam, rs in rows.items():
        summ = {"summary": fam, "runs": len(rs),
                "statuses": [r["status"] for r in rs],
                "median_seconds": statistics.median(r["seconds"] for r in rs),
                "median_cpu_seconds": statistics.median(r["cpu_seconds"] for r in rs),
                "median_boxes": statistics.median(r["boxes"] for r in rs)}
        if all("baseline" in r for r in rs):
            summ["baseline_statuses"] = [r["baseline"]["status"] for r in rs]
            summ["baseline_median_seconds"] = statistics.median(
                r["baseline"]["seconds"] for r in rs)
            summ["baseline_median_boxes"] = statistics.median(r["baseline"]["boxes"] for r in rs)
        record_line(summ)
    if executor is not None:
        executor.close()


if __name__ == "__main__":
    main()
