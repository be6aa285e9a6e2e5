"""The boxes each proof of `certify run` uses against its budget: one JSON line per example.

For every shipped example (or `--only NAME,...`), `verify` with the shipped settings (the
box budgets of `certify.settings`; `--grid-points` only shortens the grids, which no
budget depends on), and per check: the boxes its proofs evaluated, its budget, whether the
budget was spent (`exhausted`), and the check's status; with the verdict, the wall and CPU
seconds of the run and the load. A default budget is right when the proofs that finish do
so with room to spare and the ones that do not finish spend about the work the run should
cost (bench/run.py times the whole run).

Run: python bench/box_budgets.py [--only vdp2_lmi,vdp2_bound] [--grid-points 1000000]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from record import emit  # noqa: E402  (bench/record.py)

#: the setting that budgets each check's proofs
BUDGET = {"mpdi": "max_boxes", "rate": "rate_boxes", "residual": "residual_boxes",
          "lipschitz": "lipschitz_boxes", "dissipation": "dissipation_boxes"}


def main() -> None:
    from certify.model.checkpoint import load
    from certify.settings import VerifySettings
    from certify.verify import verify

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="comma-separated example names")
    ap.add_argument("--grid-points", type=int, default=VerifySettings().grid_points)
    args = ap.parse_args()
    names = [n for n in args.only.split(",") if n] or sorted(
        p.stem for p in (ROOT / "examples").glob("*.ckpt"))
    settings = VerifySettings(grid_points=args.grid_points)
    for name in names:
        ck = load(str(ROOT / "examples" / f"{name}.ckpt"))
        t, c = time.perf_counter(), time.process_time()
        cert = verify(ck, settings, figures=False)
        checks = {}
        for check, key in BUDGET.items():
            r = cert.checks.get(check)
            proof = getattr(r, "proof", None)
            if proof is not None:
                checks[check] = {"boxes": proof.boxes_processed,
                                 "budget": getattr(settings, key),
                                 "exhausted": proof.budget_exhausted,
                                 "status": r.status.value}
        emit(example=name, verdict=cert.verdict, checks=checks,
             wall_s=round(time.perf_counter() - t, 2), cpu_s=round(time.process_time() - c, 2))


if __name__ == "__main__":
    main()
