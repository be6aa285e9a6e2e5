"""The proved validity region, measured: one JSON line per system and per checkpoint.

- check (per system: vdp, vdp_wide, the pendulum example): the invariance check alone
  (`certify.checks.invariance.check_invariance`, default budget): its status, the region
  (kind, vertices), the proved ranges of R, the simulated attractor's box, whether it leaves
  X and the box suggested, the outward-speed bound, the pieces proved, and the wall and CPU
  seconds (medians over --repeat);
- certificate (per checkpoint, default examples/vdp_wide_bound.ckpt and
  examples/vdp_bound.ckpt): `verify` with the simulation skipped; the verdict, the headline
  B after T, its ultimate value, the box's half-diagonal and B / half-diagonal (the bound is
  called useful below 1; the shipped vdp_wide checkpoint aims at 0.5), the validity region:
  r0 (||e(0)||_2), r0 in the P-norm, the settle time from those starts, the conditions
  proved, or why there is none; and the whole run's wall seconds.

Run: python bench/invariance.py [--repeat 3] [--only-checks]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.record import emit  # noqa: E402

SYSTEMS = ("vdp", "vdp_wide", str(ROOT / "examples" / "pendulum.toml"))
CHECKPOINTS = ("examples/vdp_wide_bound.ckpt", "examples/vdp_bound.ckpt")


def rounded(box, digits: int = 4):
    return None if box is None else [[round(float(v), digits) for v in row] for row in box]


def check_line(name: str, repeat: int) -> dict:
    from certify.checks.invariance import check_invariance
    from certify.spec.system import load_system

    system = load_system(name)
    walls, cpus, r = [], [], None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        r = check_invariance(system)
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    region = r.region or {}
    return {"kind": "check", "system": system.name, "status": r.status.value,
            "region": region.get("kind"), "origin": region.get("origin"),
            "vertices": len(region.get("vertices") or []) or None,
            "region_ranges": rounded(r.hull), "X": rounded(system.X),
            "attractor": r.attractor, "attractor_box": rounded(r.attractor_box),
            "attractor_leaves_box": r.attractor_leaves_box,
            "suggested_box": rounded(r.suggested_box), "outward_speed_bound": r.margin,
            "pieces": r.proof.boxes_processed if r.proof else None,
            "wall_s": round(statistics.median(walls), 3),
            "cpu_s": round(statistics.median(cpus), 3), "repeat": repeat}


def certificate_line(path: str) -> dict:
    from certify.model.checkpoint import load
    from certify.settings import VerifySettings
    from certify.verify import verify

    w = time.perf_counter()
    cert = verify(load(str(ROOT / path)),
                  dataclasses.replace(VerifySettings(), skip=("simulation",)), figures=False)
    wall = time.perf_counter() - w
    b = cert.checks["bounds"]
    inv = cert.checks.get("invariance")
    half = b.box_half_diagonal
    return {"kind": "certificate", "checkpoint": Path(path).name, "verdict": cert.verdict,
            "invariance": getattr(inv, "status", None) and inv.status.value,
            "headline": b.headline, "after_s": b.settle_time, "ultimate": b.ultimate,
            "best": b.best, "per_component": b.per_component, "noise": b.vbar,
            "box_half_diagonal": half,
            "headline_over_half_diagonal": (None if b.headline is None or not half
                                            else round(b.headline / half, 4)),
            "region": b.region or None, "r0": b.r0, "r0_P": b.r0_W,
            "after_from_r0_s": b.region_settle_time,
            "proved_conditions": b.proved_conditions, "no_region": b.region_reason or None,
            "wall_s": round(wall, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only-checks", action="store_true")
    args = ap.parse_args()
    for name in SYSTEMS:
        emit(check_line(name, args.repeat))
    if not args.only_checks:
        for path in CHECKPOINTS:
            emit(certificate_line(path))


if __name__ == "__main__":
    main()
