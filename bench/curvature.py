"""The verification-aware training term (`training.curvature`): its cost and what it buys.

`cost` (default): one certified-preset Adam step (`CertObjective.evaluate(grad=True)`, 4000
collocation points, 16x16, vdp) with the term off and with 128/256/512 pairs, interleaved
in one process (side by side on a shared machine), one JSON line per setting with the
median milliseconds per step and the ratio to "off".

`proof SYSTEM SEEDS WEIGHTS [ROUNDS]`: the certified recipe with a fixed schedule (ROUNDS
CEGIS rounds, no proof-time stop rule, so every weight trains the same number of rounds),
then `certify run CKPT --json` on the result: one JSON line per (seed, weight) with the
verdict, the MPDI status, the proof's sub-boxes and seconds, the proved L and lam_cert, and
the Adam seconds; then one median line per weight.

Run: python bench/curvature.py cost
     python bench/curvature.py proof vdp 0,1,2 0,0.001 8
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from certify.spec.system import load_system  # noqa: E402


def cost(reps: int = 15, steps: int = 5) -> None:
    """Milliseconds per Adam step, term off vs on (interleaved)."""
    from training.cegis import warm_start_network
    from training.cegis_objective import CertObjective
    from training.certified import lmi_start
    from training.collocation import collocation_points
    from training.curvature import CurvaturePenalty, CurvatureSettings

    torch.set_num_threads(1)
    system = load_system("vdp")
    base, P, _ = lmi_start(system, system.lam)
    net = warm_start_network(system, (16, 16), K=base.K, seed=0).float()
    for prm in net.parameters():
        prm.requires_grad_(True)
    with torch.no_grad():
        net.layers[-1].weight.normal_(0, 0.1, generator=torch.Generator().manual_seed(0))
    xhat, y = collocation_points(system, 4000, 0)
    objs = {}
    for pairs in (0, 128, 256, 512):
        cur = None if pairs == 0 else CurvaturePenalty(
            system, CurvatureSettings(weight=1e-3, pairs=pairs), 0)
        objs[pairs] = CertObjective(system, net, xhat, y, lam=system.lam + 0.02,
                                    P=torch.as_tensor(P), margin=0.2, lip_weight=0.02,
                                    lip_power=8.0, mpdi_weight=10.0, curvature=cur)
    times: dict[int, list[float]] = {k: [] for k in objs}
    for _ in range(reps):
        for k, obj in objs.items():
            t0 = time.perf_counter()
            for _ in range(steps):
                obj.evaluate(grad=True)
            times[k].append((time.perf_counter() - t0) / steps)
    off = statistics.median(times[0])
    for k, ts in times.items():
        med = statistics.median(ts)
        record_line({"bench": "curvature_cost", "pairs": k, "ms_per_step": round(1e3 * med, 3),
                          "ratio_to_off": round(med / off, 3), "reps": reps})
    for obj in objs.values():
        obj.close()


def proof(system_name: str, seeds: list[int], weights: list[float], rounds: int) -> None:
    """Fixed-schedule certified training per (seed, weight), then `certify run --json`."""
    from training.certified import cegis_settings, save_certified, train_certified
    from training.presets import make_config

    system = load_system(system_name)
    rows: list[dict] = []
    tmp = Path(tempfile.mkdtemp(prefix="curvature-bench-"))
    for seed in seeds:
        for w in weights:
            cfg = make_config(system, "certified", seed=seed, curvature_weight=w)
            cs = cegis_settings(cfg, rounds=rounds, improve_rounds=10**6,
                                improve_proof_seconds=1e9, budget_seconds=1e9,
                                proof_seconds=120.0)
            t0 = time.perf_counter()
            res = train_certified(system, cfg, settings=cs)
            t_train = time.perf_counter() - t0
            ck = tmp / f"{system_name}_w{w:g}_s{seed}.ckpt"
            save_certified(ck, system, res)
            t0 = time.perf_counter()
            rc = subprocess.run([sys.executable, "-m", "certify", "run", str(ck), "--json",
                                 str(ck.with_suffix(".json")), "--quiet"],
                                capture_output=True, text=True).returncode
            rr = res.cegis.rounds
            row = {"bench": "curvature_proof", "system": system_name, "seed": seed,
                   "curvature_weight": w, "rounds": len(rr), "train_status": res.status.value,
                   "adam_s": round(sum(r.train_seconds for r in rr), 2),
                   "train_s": round(t_train, 1), "curv_last": round(rr[-1].curv, 4),
                   "exit": rc, "run_s": round(time.perf_counter() - t0, 1)}
            try:
                d = json.loads(ck.with_suffix(".json").read_text())
                m = d["checks"]["mpdi"]
                pr = m.get("proof") or {}
                row.update(verdict=d["verdict"], mpdi=m["status"], mpdi_upper=m.get("upper"),
                           boxes=pr.get("boxes_processed"), proof_s=pr.get("seconds"),
                           L=float(d["checks"]["bounds"].get("L", "nan")),
                           lam_cert=float(d["checks"]["rate"].get("proved_lower", "nan")))
            except (OSError, KeyError, ValueError) as exc:
                row["error"] = repr(exc)[:200]
            rows.append(row)
            record_line(row)
    for w in weights:
        mine = [r for r in rows if r["curvature_weight"] == w and "boxes" in r]
        if not mine:
            continue

        def med(key: str, rows_: list[dict] = mine) -> float:
            return statistics.median(float(r[key]) for r in rows_)
        record_line({"bench": "curvature_proof_median", "system": system_name,
                          "curvature_weight": w, "runs": len(mine),
                          "verdicts": [r["verdict"] for r in mine],
                          "boxes": med("boxes"), "proof_s": round(med("proof_s"), 3),
                          "L": round(med("L"), 3), "lam_cert": round(med("lam_cert"), 4),
                          "adam_s": round(med("adam_s"), 2)})


if __name__ == "__main__":
    args = sys.argv[1:] or ["cost"]
    if args[0] == "cost":
        cost()
    elif args[0] == "proof" and len(args) >= 4:
        proof(args[1], [int(s) for s in args[2].split(",")],
              [float(w) for w in args[3].split(",")], int(args[4]) if len(args) > 4 else 8)
    else:
        sys.exit("usage: bench/curvature.py cost | proof SYSTEM SEEDS WEIGHTS [ROUNDS]")
