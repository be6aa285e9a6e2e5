"""Paper preset vs certified LMI baseline vs certified learned gain on vdp (issue 5, item 5).

For each lam: (a) the paper preset (P = I, the source method), (b) the LMI observer
k0 = K (y - h(xhat)) (`training.baseline`), (c) the certified preset (`training.certified`).
Each checkpoint is verified with `certify.verify.verify`; the table shows the verdict, the
proved lam_cert, the sound L and eps_bar, the ISS ultimate bound at vbar = 0.15,
sqrt(kappa(P)) (eps_bar + L vbar) / (2 lam_cert), and the mean squared error of the source's
simulation protocol (x(0) = (-1, 2.5), xhat(0) = 0, Gaussian noise std 0.15, RK4 dt 1e-3 over
10 s; outside the bound's conditions, as METHOD §3.7 says). Checkpoints are cached in --out
and reused (delete them to retrain).

Run: python bench/compare.py [--out out/compare] [--quick] [--lams 2.5,4,5]
Prints a Markdown table, then one JSON line per row.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from certify.checks.bounds import metric_constants, ultimate_bound_per_unit_noise  # noqa: E402
from certify.errors import CertifyError  # noqa: E402
from certify.model import checkpoint  # noqa: E402
from certify.settings import VerifySettings  # noqa: E402
from certify.simulate.integrate import gaussian_noise, simulate  # noqa: E402
from certify.spec.system import load_system  # noqa: E402
from certify.verify import verify  # noqa: E402

VBAR = 0.15
SIM_DT, SIM_T, SIM_SEED = 1e-3, 10.0, 0


def _tag(lam: float) -> str:
    return f"{lam:g}".replace(".", "p")


def make_paper(path: Path, system: Any, lam: float) -> dict[str, Any]:
    from training.presets import make_config
    from training.train import train

    res = train(system, make_config(system, "paper", lam=lam))
    checkpoint.save(path, system=system, network=res.network, lam=lam,
                    P=np.eye(system.n), training=res.record())
    return {"train_seconds": res.timings["total"]}


def make_lmi(path: Path, system: Any, lam: float) -> dict[str, Any]:
    from training.baseline import save_lmi_baseline

    t0 = time.perf_counter()
    info, how = None, ""
    for gain_max in (1e3, 1e4, None):  # the default bound ||PK|| <= 1e3 is too tight at
        try:                            # high rates; an unbounded gain is needlessly large
            info = save_lmi_baseline(path, system, lam, gain_max=gain_max)
            how = f"gain_max {gain_max:g}" if gain_max else "no gain bound"
            break
        except CertifyError as exc:
            last = exc
    if info is None:
        raise last
    return {"train_seconds": time.perf_counter() - t0, "lmi": how,
            "gain_norm": info["gain_norm"]}


def make_certified(path: Path, system: Any, lam: float, quick: bool) -> dict[str, Any]:
    from training.certified import DEFAULT_CEGIS, cegis_settings, save_certified, train_certified
    from training.presets import make_config

    config = make_config(system, "certified", lam=lam)
    cs = cegis_settings(config, DEFAULT_CEGIS,
                        budget_seconds=90.0 if quick else DEFAULT_CEGIS.budget_seconds)
    res = train_certified(system, config, settings=cs,
                          log=lambda m: print(f"  [certified lam {lam:g}] {m}",
                                              file=sys.stderr, flush=True))
    save_certified(path, system, res)
    return {"train_seconds": res.seconds, "loop": res.status.value,
            "rounds": len(res.cegis.rounds)}


def source_mse(problem: Any) -> float:
    """Mean over [0, 10] of ||x - xhat||^2 under the source protocol (inf if it blows up)."""
    system = problem.system
    sim = system.simulation or {}
    x0 = torch.tensor([sim.get("x0", [-1.0, 2.5])], dtype=torch.float64)
    xh0 = torch.tensor([sim.get("xhat0", [0.0] * system.n)], dtype=torch.float64)
    steps = int(round(SIM_T / SIM_DT))
    noise = gaussian_noise(steps, 1, system.p, VBAR, seed=SIM_SEED)
    tr = simulate(system, problem.network, x0, xh0, dt=SIM_DT, steps=steps, noise=noise)
    e2 = ((tr.x - tr.xhat) ** 2).sum(-1)
    v = float(e2.mean())
    return v if math.isfinite(v) else math.inf


def evaluate(path: Path, settings: VerifySettings) -> dict[str, Any]:
    ck = checkpoint.load(path)
    cert = verify(ck, settings)
    c = cert.checks
    rate = c.get("rate")
    lam_cert = rate.proved_lower if rate is not None else None
    eps = c["residual"].upper if "residual" in c else None
    L = c["lipschitz"].value if "lipschitz" in c else None
    kappa = metric_constants(ck.problem.P)[2]
    ub = ultimate_bound_per_unit_noise(lam_cert=lam_cert, eps_bar=eps, L=L, vbar=VBAR,
                                       kappa_P=kappa)
    return {"verdict": cert.verdict, "mpdi": c["mpdi"].status.value,
            "lam_cert": lam_cert, "lam_cert_sampled": rate.sampled_upper if rate else None,
            "L": L, "L_which": c["lipschitz"].which if "lipschitz" in c else None,
            "eps_bar": eps, "kappa_P": kappa, "ultimate_bound": ub,
            "mse_source": source_mse(ck.problem), "verify_seconds": cert.timings["total"]}


def _f(v: Any, fmt: str = ".4g") -> str:
    if v is None:
        return "—"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return format(v, fmt) if isinstance(v, float) else str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/compare", help="checkpoint cache folder")
    ap.add_argument("--lams", default=None, help="comma-separated rates (default 2.5,4,5)")
    ap.add_argument("--quick", action="store_true",
                    help="lam 2.5 only, smaller verification and training budgets")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # one thread: on a shared 2-core machine two are slower
    lams = [float(v) for v in (args.lams or ("2.5" if args.quick else "2.5,4,5")).split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    system = load_system("vdp")
    settings = VerifySettings(grid_points=50_000 if args.quick else 200_000,
                              proof_seconds=20.0 if args.quick else 60.0,
                              lipschitz_seconds=5.0 if args.quick else 10.0,
                              residual_seconds=5.0 if args.quick else 10.0,
                              adversarial_starts=32, noise=VBAR, skip=("simulation",))
    rows: list[dict[str, Any]] = []
    for lam in lams:
        for design in ("paper", "lmi", "certified"):
            path = out / f"vdp_{design}_lam{_tag(lam)}.ckpt"
            row: dict[str, Any] = {"lam": lam, "design": design, "checkpoint": str(path)}
            try:
                if not path.exists():
                    print(f"training {design} at lam {lam:g} -> {path}", file=sys.stderr,
                          flush=True)
                    if design == "paper":
                        row.update(make_paper(path, system, lam))
                    elif design == "lmi":
                        row.update(make_lmi(path, system, lam))
                    else:
                        row.update(make_certified(path, system, lam, args.quick))
                else:
                    row["cached"] = True
                print(f"verifying {path}", file=sys.stderr, flush=True)
                row.update(evaluate(path, settings))
            except CertifyError as exc:
                row.update({"verdict": "ERROR", "error": str(exc)})
            rows.append(row)
    print("| lam | design | verdict | lam_cert (proved) | L (sound) | eps_bar (sound) | "
          "kappa(P) | ultimate bound at vbar=0.15 | MSE, source protocol |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['lam']:g} | {r['design']} | {r.get('verdict')} | {_f(r.get('lam_cert'))} "
              f"| {_f(r.get('L'))} | {_f(r.get('eps_bar'))} | {_f(r.get('kappa_P'))} | "
              f"{_f(r.get('ultimate_bound'))} | {_f(r.get('mse_source'))} |")
    print()
    for lam in lams:
        by = {r["design"]: r for r in rows if r["lam"] == lam}
        a, b = by.get("certified", {}).get("ultimate_bound"), by.get("lmi", {}).get(
            "ultimate_bound")
        if a is not None and b is not None:
            word = "beats" if a < b else "does NOT beat"
            print(f"lam {lam:g}: the certified learned gain {word} the LMI baseline on the "
                  f"certified ultimate bound ({a:.4g} vs {b:.4g}, ratio {a / b:.3f}); "
                  f"L {by['certified']['L']:.4g} vs {by['lmi']['L']:.4g}, kappa(P) "
                  f"{by['certified']['kappa_P']:.4g} vs {by['lmi']['kappa_P']:.4g}")
        else:
            print(f"lam {lam:g}: no comparison of certified bounds (certified: {_f(a)}, "
                  f"LMI: {_f(b)})")
    print()
    for r in rows:
        print(json.dumps({k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                          for k, v in r.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
