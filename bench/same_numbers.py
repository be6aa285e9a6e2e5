"""Same numbers before and after a change: certificates and proofs, number for number.

Records, for one checkout (`--code DIR`, default this one), the JSON certificate of every
shipped example (`verify` with the box budgets as shipped; a checkout from before them: time
budgets so generous that only box budgets can bind) and the
prover-suite proofs of `bench/instances.py` (several families and seeds, a box budget and no
time budget), with everything that depends on the clock or the machine removed (seconds,
timings, versions, paths, dates). `--compare A B` then prints one JSON line per record that
differs (or {"same": true, ...}) and exits 1 when any differs.

    python bench/same_numbers.py --code /tmp/before --out /tmp/nums-before
    python bench/same_numbers.py --out /tmp/nums-after
    python bench/same_numbers.py --compare /tmp/nums-before /tmp/nums-after
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: keys whose values depend on the clock, the machine or the checkout, at any depth
VOLATILE = ("seconds", "time", "timing", "elapsed", "version", "versions", "date", "created",
            "path", "sha256", "load", "cpu", "rate_per_s", "boxes_per_second", "host",
            "python", "platform", "torch", "file", "history", "speed")

EXAMPLES = ("vdp", "vdp_lmi", "vdp_certified", "vdp2_lmi", "lorenz_lmi")

SUITE = (  # (family depth, width, g, n, margin, seeds, max_boxes)
    (2, 10, 2.0, 2, 0.02, (0, 1, 2), 200_000),
    (2, 10, 2.0, 3, 0.02, (0, 1), 200_000),
    (3, 30, 2.0, 2, 0.02, (0, 1), 100_000),
    (2, 10, 2.0, 4, 0.02, (0,), 400_000),
)


def volatile(key: str) -> bool:
    k = key.lower()
    return any(v in k for v in VOLATILE)


def scrub(obj):
    """The record without volatile keys; floats kept exactly (repr round-trips)."""
    if isinstance(obj, dict):
        return {k: scrub(v) for k, v in obj.items() if not volatile(str(k))}
    if isinstance(obj, list):
        return [scrub(v) for v in obj]
    return obj


def record(out: Path) -> None:
    import certify
    import certify.model.checkpoint  # noqa: F401  (certify.model as an attribute)

    out.mkdir(parents=True, exist_ok=True)
    import dataclasses

    names = {f.name for f in dataclasses.fields(certify.VerifySettings)}
    # box budgets as shipped; a checkout from before them: time budgets too long to bind
    settings = certify.VerifySettings(**({} if "rate_boxes" in names else dict(
        proof_seconds=1e5, rate_seconds=1e5, residual_seconds=1e5, lipschitz_seconds=1e5)))
    for name in EXAMPLES:
        ck = certify.model.checkpoint.load(str(ROOT / "examples" / f"{name}.ckpt"))
        cert = certify.verify(ck, settings)
        data = scrub(json.loads(cert.to_json()))
        (out / f"example-{name}.json").write_text(json.dumps(data, indent=1, sort_keys=True))
        print(json.dumps({"recorded": f"example-{name}", "verdict": data.get("verdict")}),
              flush=True)
    try:
        from certify.prove.mpdi import prove_mpdi
    except ImportError:  # a checkout from before the stage packages
        from certify.prove.mpdi import prove_mpdi
    from bench.instances import InstanceSpec, make_instance

    for depth, width, g, n, margin, seeds, max_boxes in SUITE:
        for seed in seeds:
            spec = InstanceSpec(depth, width, g, n, margin, seed)
            prob, _ = make_instance(spec)
            res = prove_mpdi(prob, seconds=1e5, max_boxes=max_boxes)
            st = res.stats
            data = {"instance": spec.name, "lam": prob.lam, "status": res.status.value,
                    "upper": res.upper, "boxes": st.boxes_processed,
                    "proved_volume": getattr(st, "proved_volume", None)}
            (out / f"suite-{spec.name}.json").write_text(json.dumps(data, indent=1,
                                                                    sort_keys=True))
            print(json.dumps(data), flush=True)


def diff(a, b, where: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}/{k}: only in {'after' if k in b else 'before'}")
            else:
                out += diff(a[k], b[k], f"{where}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items before, {len(b)} after"]
        return [d for x, y, i in zip(a, b, range(len(a))) for d in diff(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{where}: {a!r} -> {b!r}"]


def compare(before: Path, after: Path) -> int:
    bad = 0
    for fa in sorted(before.glob("*.json")):
        fb = after / fa.name
        if not fb.exists():
            print(json.dumps({"record": fa.stem, "missing_after": True}))
            bad += 1
            continue
        d = diff(json.loads(fa.read_text()), json.loads(fb.read_text()))
        print(json.dumps({"record": fa.stem, "same": not d, "differences": d[:20]}))
        bad += bool(d)
    return 1 if bad else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--code", default=None, help="checkout whose certify is measured")
    ap.add_argument("--out", default="/tmp/certify-same-numbers")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    args = ap.parse_args()
    if args.compare:
        sys.exit(compare(Path(args.compare[0]), Path(args.compare[1])))
    code = Path(args.code).resolve() if args.code else ROOT
    sys.path.insert(0, str(code))
    record(Path(args.out))


if __name__ == "__main__":
    main()
