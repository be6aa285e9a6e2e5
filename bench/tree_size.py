"""How many boxes would a complete MPDI proof take? A random-descent estimate (the
estimator is `certify.search.tree_estimate`, which `certify run` also uses on an UNKNOWN proof).

The tree of a decision proof is fixed by its bound and split rule, so random descents
through it (the prover's own evaluation and rule: `certify.prove.mpdi.mpdi_decision`) estimate
its size before any run finishes it; see `certify.search.tree_estimate` for the method and its
error. 1024 points on the 2x10 six-state chain take ~13 k box evaluations (seconds).

`--validate SECONDS` also runs the proof (`prove_mpdi`) with that budget and prints its box
count beside the estimate when it finishes.

`--what-if-majorant F` / `--what-if-remainder F` (what-ifs, NOT bounds: the descents then
follow a tree no sound proof has) scale the two remainders of the mixed-row stage by F: the
Loewner majorant W of the top layers' product errors (the matrix-form upper models of
`certify.enclose.stages.MixedRows`: c + W becomes c + F W) and the entrywise remainder e.
Only proofs that use that stage (metric congruence M = I and a direct network, as on the
issue-9 families) change, and for n <= 3 the entrywise form the stage also tries stays as
built. Descents with the same
`--point-seed` follow the same points, so the line says what a F-times tighter enclosure of
that part would be worth in whole-tree boxes before anyone builds it. Measured on the six-state
chain, seed 0 (session 14): 8192 descents, 21.8 M boxes (+-14%) as built, 2.2 M (+-48%) with
W x 0.5, 0.99 M (+-53%) with both x 0.5; 2048 descents, e x 0.5 alone: 25.6 M against 31.9 M,
both x 0.25: 1.1 k boxes. The estimates of the smaller trees are rough (few deep descents
carry them), their order of magnitude is not.

One JSON line per instance. Example (the six-state chain, a long proof):
    python bench/tree_size.py --n 6 --seeds 0 1 2 --points 2048
    python bench/tree_size.py --n 6 --points 2048 --what-if-majorant 0.5
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from bench.prove_suite import add_family_arguments, family_instances  # noqa: E402
from certify.prove.mpdi import mpdi_decision, prove_mpdi  # noqa: E402
from certify.search.tree_estimate import estimate_tree  # noqa: E402


def scale_remainders(majorant: float, remainder: float) -> None:
    """The what-if of `--what-if-majorant` / `--what-if-remainder` (module docstring): the
    mixed-row stage's Loewner majorant W and entrywise remainder e scaled, in this process
    only (its matrix-form upper models, `certify.enclose.stages.MixedRows.models`, replaced
    by scaled ones; the entrywise model stays as built). Not sound."""
    from dataclasses import replace

    from certify.arith.taylor import TM
    from certify.enclose.stages import ENTRYWISE, MixedRows

    def scaled(exact):
        def model(A, top, level):
            T = exact(A, top, level)
            return TM(A.c + majorant * (T.c - A.c), T.g, remainder * T.e)

        return model

    MixedRows.models = tuple(m if m is ENTRYWISE else replace(m, model=scaled(m.model))
                             for m in MixedRows.models)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_family_arguments(ap, n=(6,))
    ap.add_argument("--points", type=int, default=1024, help="random descents per instance")
    ap.add_argument("--point-seed", type=int, default=0)
    ap.add_argument("--max-depth", type=int, default=80)
    ap.add_argument("--validate", type=float, default=None, metavar="SECONDS",
                    help="also run the proof with this budget and report its boxes")
    ap.add_argument("--what-if-majorant", type=float, default=None, metavar="F",
                    help="what-if, not a bound: scale the Loewner majorant W by F")
    ap.add_argument("--what-if-remainder", type=float, default=None, metavar="F",
                    help="what-if, not a bound: scale the entrywise remainder e by F")
    args = ap.parse_args()
    torch.set_num_threads(1)
    what_if = {k: v for k, v in (("majorant", args.what_if_majorant),
                                 ("remainder", args.what_if_remainder)) if v is not None}
    if what_if:
        if args.validate is not None:
            ap.error("--validate runs a proof: not with a what-if")
        scale_remainders(what_if.get("majorant", 1.0), what_if.get("remainder", 1.0))
    for spec, problem in family_instances(args):
        t0 = time.perf_counter()
        setup = mpdi_decision(problem, float(problem.lam))
        est = estimate_tree(setup.evaluate, setup.lo, setup.hi, setup.first_round,
                            args.points, args.point_seed, max_depth=args.max_depth)
        rec = {"bench": "tree_size", "instance": spec.name, **asdict(est),
               "seconds": round(time.perf_counter() - t0, 2)}
        rec["leaves"], rec["boxes"] = round(est.leaves), round(est.boxes)
        rec["rel_stderr"] = round(est.rel_stderr, 3)
        if what_if:
            rec["what_if"] = {**what_if, "note": "scaled remainders: not a bound"}
        if args.validate is not None:
            out = prove_mpdi(problem, seconds=args.validate, max_boxes=10**9)
            rec.update(proof_status=out.status.value,
                       proof_boxes=out.stats.boxes_processed,
                       proof_seconds=round(out.stats.seconds, 2))
        record_line(rec)


if __name__ == "__main__":
    main()
