"""How many boxes would a complete MPDI proof take? A random-descent estimate (issue 9).

A proof that does not finish in its budget says how much volume it closed, not how far it
is from done. In decision mode the branch-and-bound tree is fixed by the box bound and the
split rule alone: each box is closed or split on its own bound against the fixed threshold,
whatever order the rounds take (`certify.bnb`). So the tree can be sampled (Knuth's
estimator): follow uniform random points z of the root box down from their first-round box,
evaluating each box on the way with the prover's own evaluation and splitting it by the
prover's own rule (`certify.prover.mpdi_decision`, `certify.bnb.split_dimensions`), until
the box containing z closes. A leaf at depth L (halvings from the root) holds 2^-L of the
volume, so the tree has E_z[2^L(z)] leaves, and every split adds two boxes: about twice as
many boxes evaluated. The mean is unbiased but heavy-tailed (a few deep points near the
critical region carry much of it): read the standard error, and more points tighten it.

Each point costs one box evaluation per level (batched over the points): 1024 points on
the 2x10 six-state chain take ~13 k evaluations, seconds, where the proof is ~40 M boxes.
A point whose box still has NaN/Inf bounds at depth `--max-depth` is counted as stuck (the
proof would set it aside as UNKNOWN) and left out of the estimate.

`--validate SECONDS` also runs the proof (`prove_mpdi`) with that budget and prints its box
count beside the estimate when it finishes.

One JSON line per instance. Example (the six-state chain that misses issue 9's 600 s):
    python bench/tree_size.py --n 6 --seeds 0 1 2 --points 2048
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.instances import InstanceSpec  # noqa: E402
from bench.prove_suite import FAMILIES, _cached_instance  # noqa: E402
from certify.bnb import initial_grid, split_dimensions  # noqa: E402
from certify.prover import _root, mpdi_decision, prove_mpdi  # noqa: E402


def random_points(problem, points: int, seed: int) -> torch.Tensor:
    """`points` seeded uniform random points [points, d] of the root box X x Y."""
    lo, hi = _root(problem)
    gen = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(points, len(lo), generator=gen, dtype=torch.float64)


def leaf_depths(problem, z: torch.Tensor, max_depth: int = 60) -> tuple[torch.Tensor, int]:
    """(depth of the closed leaf containing each point z [P, d] of the root box, -1 where
    stuck; box evaluations spent) in the MPDI decision proof of `problem` at its rate."""
    setup = mpdi_decision(problem, float(problem.lam))
    lo_r, hi_r = setup.lo, setup.hi
    scale = (hi_r - lo_r).clamp_min(1e-300)
    points = z.shape[0]
    grid = initial_grid(lo_r, hi_r, setup.first_round)
    inside = ((z[:, None] >= grid.lo[None]) & (z[:, None] <= grid.hi[None])).all(-1)
    first = inside.to(torch.int8).argmax(1)  # the first box holding z (shared faces: any)
    lo, hi = grid.lo[first].clone(), grid.hi[first].clone()
    depth = grid.depth[first].clone()
    leaf = torch.full((points,), -1, dtype=torch.long)
    active = torch.arange(points)
    evaluations = 0
    while len(active):
        ev = setup.evaluate(lo[active], hi[active])
        evaluations += len(active)
        closed = (ev.upper <= 0.0) & torch.isfinite(ev.upper)
        leaf[active[closed]] = depth[active[closed]]
        deep = ~closed & (depth[active] >= max_depth)  # stuck: stays -1
        go = ~closed & ~deep
        active, score = active[go], None if ev.score is None else ev.score[go]
        if not len(active):
            break
        dims = split_dimensions(lo[active], hi[active], score, scale)
        ar = torch.arange(len(active))
        mid = 0.5 * (lo[active, dims] + hi[active, dims])
        left = z[active, dims] <= mid
        new_lo, new_hi = lo[active].clone(), hi[active].clone()
        new_hi[ar[left], dims[left]] = mid[left]
        new_lo[ar[~left], dims[~left]] = mid[~left]
        lo[active], hi[active] = new_lo, new_hi
        depth[active] += 1
    return leaf, evaluations


def estimate(leaf: torch.Tensor) -> dict:
    """Leaves and boxes of the whole tree from the leaf depths (module docstring), with the
    standard error of the leaf estimate and depth quantiles."""
    ok = leaf >= 0
    w = torch.pow(2.0, leaf[ok].to(torch.float64))
    if not len(w):
        return {"est_leaves": None, "est_boxes": None}
    mean = float(w.mean())
    se = float(w.std() / math.sqrt(len(w))) if len(w) > 1 else math.inf
    q = torch.quantile(leaf[ok].to(torch.float64),
                       torch.tensor([0.1, 0.5, 0.9, 0.99], dtype=torch.float64))
    return {"est_leaves": round(mean), "est_boxes": round(2 * mean),
            "rel_stderr": round(se / mean, 3),
            "depth_q10_50_90_99": [int(v) for v in q], "depth_max": int(leaf[ok].max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--family", nargs="+", default=["2x10"], choices=sorted(FAMILIES))
    ap.add_argument("--g", type=float, default=2.0)
    ap.add_argument("--n", nargs="+", type=int, default=[6])
    ap.add_argument("--margin", type=float, default=0.02)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--points", type=int, default=1024, help="random descents per instance")
    ap.add_argument("--point-seed", type=int, default=0)
    ap.add_argument("--max-depth", type=int, default=60)
    ap.add_argument("--validate", type=float, default=None, metavar="SECONDS",
                    help="also run the proof with this budget and report its boxes")
    ap.add_argument("--cache", default="/tmp/certify-bench/instances.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cache = Path(args.cache) if args.cache else None
    for fam in args.family:
        depth, width = FAMILIES[fam]
        for n in args.n:
            for seed in args.seeds:
                spec = InstanceSpec(depth, width, args.g, n, args.margin, seed)
                problem = _cached_instance(spec, cache)[0]
                t0 = time.perf_counter()
                z = random_points(problem, args.points, args.point_seed)
                leaf, evals = leaf_depths(problem, z, args.max_depth)
                rec = {"bench": "tree_size", "instance": spec.name, "points": args.points,
                       "stuck": int((leaf < 0).sum()), **estimate(leaf),
                       "evaluations": evals, "seconds": round(time.perf_counter() - t0, 2)}
                if args.validate is not None:
                    out = prove_mpdi(problem, seconds=args.validate, max_boxes=10**9)
                    rec.update(proof_status=out.status.value,
                               proof_boxes=out.stats.boxes_processed,
                               proof_seconds=round(out.stats.seconds, 2))
                print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
