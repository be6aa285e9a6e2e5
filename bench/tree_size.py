"""How many boxes would a complete MPDI proof take? A random-descent estimate (issue 9;
the estimator is `certify.tree_estimate`, which `certify run` also uses on an UNKNOWN proof).

The tree of a decision proof is fixed by its bound and split rule, so random descents
through it (the prover's own evaluation and rule: `certify.prover.mpdi_decision`) estimate
its size before any run finishes it; see `certify.tree_estimate` for the method and its
error. 1024 points on the 2x10 six-state chain take ~13 k box evaluations (seconds).

`--validate SECONDS` also runs the proof (`prove_mpdi`) with that budget and prints its box
count beside the estimate when it finishes.

One JSON line per instance. Example (the six-state chain that misses issue 9's 600 s):
    python bench/tree_size.py --n 6 --seeds 0 1 2 --points 2048
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.prove_suite import add_family_arguments, family_instances  # noqa: E402
from certify.prover import mpdi_decision, prove_mpdi  # noqa: E402
from certify.tree_estimate import estimate_tree  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_family_arguments(ap, n=(6,))
    ap.add_argument("--points", type=int, default=1024, help="random descents per instance")
    ap.add_argument("--point-seed", type=int, default=0)
    ap.add_argument("--max-depth", type=int, default=80)
    ap.add_argument("--validate", type=float, default=None, metavar="SECONDS",
                    help="also run the proof with this budget and report its boxes")
    args = ap.parse_args()
    torch.set_num_threads(1)
    for spec, problem in family_instances(args):
        t0 = time.perf_counter()
        setup = mpdi_decision(problem, float(problem.lam))
        est = estimate_tree(setup.evaluate, setup.lo, setup.hi, setup.first_round,
                            args.points, args.point_seed, max_depth=args.max_depth)
        rec = {"bench": "tree_size", "instance": spec.name, **asdict(est),
               "seconds": round(time.perf_counter() - t0, 2)}
        rec["leaves"], rec["boxes"] = round(est.leaves), round(est.boxes)
        rec["rel_stderr"] = round(est.rel_stderr, 3)
        if args.validate is not None:
            out = prove_mpdi(problem, seconds=args.validate, max_boxes=10**9)
            rec.update(proof_status=out.status.value,
                       proof_boxes=out.stats.boxes_processed,
                       proof_seconds=round(out.stats.seconds, 2))
        print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
