"""The branch-and-bound driver's batch choice (`certify.search.frontier.Frontier.take`) against the
frontier's size: candidate pools vs a full scan, side by side. Prints JSON lines.

Each size N starts a frontier of N open boxes (d dimensions, uniform random upper bounds),
then runs `--rounds` rounds of a decision proof's shape: take a batch of k (half the worst,
half the nearest to closing), add two children per box with fresh bounds. Reported: the
median and mean seconds of a take, and of a whole round's frontier work (take + add), for
the pooled frontier and for one that always scans (POOL_MIN raised past N). The two take
boxes of the same bounds (`tests/search/test_pipeline.py`); only the cost differs.

Run: python bench/frontier.py [--sizes 100000 1000000 4000000] [--batch 2048] [--rounds 100]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from record import emit as record_line  # bench/record.py

from certify.search.frontier import Frontier


def measure(n_open: int, d: int, k: int, rounds: int, pooled: bool, seed: int) -> dict:
    """Seconds per take and per round (take + add of 2k children) on a frontier of
    `n_open` boxes."""
    gen = torch.Generator().manual_seed(seed)
    fr = Frontier(d)
    if not pooled:
        fr.POOL_MIN = 1 << 62
    lo = torch.rand(n_open, d, generator=gen, dtype=torch.float64)
    fr.add(lo, lo + 0.1, torch.zeros(n_open, dtype=torch.long),
           torch.rand(n_open, generator=gen, dtype=torch.float64) - 0.5,
           torch.rand(n_open, d, generator=gen, dtype=torch.float64))
    takes, whole = [], []
    for _ in range(rounds):
        t0 = time.perf_counter()
        got = fr.take(k, True)
        t1 = time.perf_counter()
        kids = torch.cat([got[0], got[0]])
        ub = torch.rand(len(kids), generator=gen, dtype=torch.float64) - 0.5
        sc = torch.rand(len(kids), d, generator=gen, dtype=torch.float64)
        t2 = time.perf_counter()
        fr.add(kids, kids + 0.05, torch.zeros(len(kids), dtype=torch.long), ub, sc)
        t3 = time.perf_counter()
        takes.append(t1 - t0)
        whole.append((t1 - t0) + (t3 - t2))
    return {"take_median_ms": round(1e3 * statistics.median(takes), 3),
            "take_mean_ms": round(1e3 * statistics.mean(takes), 3),
            "round_mean_ms": round(1e3 * statistics.mean(whole), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000, 4_000_000])
    ap.add_argument("--dim", type=int, default=7)
    ap.add_argument("--batch", type=int, default=2048)
    ap.add_argument("--rounds", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    for n_open in args.sizes:
        pooled = measure(n_open, args.dim, args.batch, args.rounds, True, 0)
        scan = measure(n_open, args.dim, args.batch, args.rounds, False, 0)
        record_line({"bench": "frontier_take", "open_boxes": n_open, "dim": args.dim,
                          "batch": args.batch, "rounds": args.rounds, "pooled": pooled,
                          "full_scan": scan,
                          "speedup_mean": round(scan["take_mean_ms"]
                                                / max(pooled["take_mean_ms"], 1e-9), 1)})


if __name__ == "__main__":
    main()
