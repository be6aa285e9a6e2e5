"""Every design of the project on vdp, lorenz and vdp2, compared on the certified error bound.

Designs (each written once into --out and reused; delete a checkpoint to retrain):
- paper: the source method (P = I; vdp only),
- lmi: the LMI observer k0 = K (y - h(xhat)) at the rate lam (`training.baseline`),
- certified: the certified preset at lam (`training.certified`, CEGIS),
- bound: the linear observer designed for the error bound (`training.bound`, rate free),
- learned: the bound preset's learned attempt (the network it trained, whether or not the
  preset returned it),
- metric: the linear gain with a metric that follows the state M(x) (`training.bound_metric`,
  the designs the bound preset compares),
- metric_learned: the learned gain against the same certificate (the network it trained,
  whether or not the preset returned it).
Each checkpoint is verified with `certify.verify.verify` (simulation skipped); the table reads
the error-bound check's result generically: the best applicable bound (`best`), its ultimate
value, the headline ||e|| <= B after t >= T, the per-component bounds and whether the bound
is useful or vacuous (larger than the box's half-diagonal), at vbar = 0.15. For the bound
designs it also shows the bound the design aimed at (vertex SDP) and its sampled value
(`certify.design.bound.sampled_bound`). The last column is the mean squared error of the
source's simulation protocol (Gaussian noise std 0.15, outside the bounds' conditions).

Run: python bench/compare.py [--out out/compare] [--systems vdp,lorenz,vdp2]
       [--designs paper,lmi,certified,bound,learned,metric,metric_learned] [--lams 2.5]
       [--quick]
Prints a Markdown table, then one JSON line per row.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from record import emit as record_line  # noqa: E402  (bench/record.py)

from certify.errors import CertifyError  # noqa: E402
from certify.model import checkpoint  # noqa: E402
from certify.settings import VerifySettings  # noqa: E402
from certify.simulate.integrate import gaussian_noise, simulate  # noqa: E402
from certify.spec.system import load_system  # noqa: E402
from certify.verify import verify  # noqa: E402

VBAR = 0.15
SIM_DT, SIM_T, SIM_SEED = 1e-3, 10.0, 0
DESIGNS = ("paper", "lmi", "certified", "bound", "learned", "metric", "metric_learned")
SYSTEMS = ("vdp", "lorenz", "vdp2")
RATE_DESIGNS = ("paper", "lmi", "certified")  # designed at a given rate lam


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
    last: Exception | None = None
    for gain_max in (1e3, 1e4, None):  # the default bound ||PK|| <= 1e3 is too tight at
        try:                            # high rates; an unbounded gain is needlessly large
            info = save_lmi_baseline(path, system, lam, gain_max=gain_max)
            how = f"gain_max {gain_max:g}" if gain_max else "no gain bound"
            break
        except CertifyError as exc:
            last = exc
    if info is None:
        assert last is not None
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
                          log=lambda m: print(f"  [certified {system.name} lam {lam:g}] {m}",
                                              file=sys.stderr, flush=True))
    save_certified(path, system, res)
    return {"train_seconds": res.seconds, "loop": res.status.value,
            "rounds": len(res.cegis.rounds)}


def make_bound(paths: dict[str, Path], system: Any, quick: bool) -> dict[str, Any]:
    """The bound preset once: the linear design to paths["bound"], the learned attempt's
    network (returned or not) to paths["learned"]."""
    from training.bound import LearnSettings, save_bound, train_bound
    from training.presets import make_config

    config = make_config(system, "bound")
    learn = LearnSettings(rounds=2 if quick else LearnSettings.rounds,
                          steps=config.adam_iters, lr=config.adam_lr, seed=config.seed)
    res = train_bound(system, config, learn=learn,
                      log=lambda m: print(f"  [bound {system.name}] {m}", file=sys.stderr,
                                          flush=True))
    att = res.attempt
    linear = res if res.returned == "linear" else None
    if linear is None:  # the learned gain was returned: write the linear design beside it
        linear = train_bound(system, make_config(system, "bound", adam_iters=0), prove=False)
    save_bound(paths["bound"], system, linear)
    info = {"train_seconds": res.seconds, "returned": res.returned,
            "learned_outcome": None if att is None else att.message}
    if att is not None and att.final is not None:
        learned = res if res.returned == "learned" else None
        if learned is None:
            rec = res.record()
            rec["returned"] = "learned attempt (not returned by the preset)"
            checkpoint.save(paths["learned"], system=system, network=att.final, lam=res.lam,
                            P=res.P, training=rec)
        else:
            save_bound(paths["learned"], system, learned)
    return info


def make_metric(paths: dict[str, Path], system: Any, quick: bool) -> dict[str, Any]:
    """The designs with M(x) once: the linear gain to paths["metric"], the learned gain's
    network (returned by the preset or not) to paths["metric_learned"]."""
    from training.bound import REPORT_VBAR
    from training.bound_metric import (
        MetricSettings,
        design_linear_metric,
        learn_metric_gain,
        save_candidate,
    )
    from training.presets import make_config

    say = lambda m: print(f"  [metric {system.name}] {m}", file=sys.stderr,  # noqa: E731
                          flush=True)
    config = make_config(system, "bound")
    t0 = time.perf_counter()
    base = checkpoint.load(paths["bound"]) if paths["bound"].exists() else None
    K0 = (np.asarray(base.problem.network.K) if base is not None
          else np.asarray(_bound_K(system)))
    ms = MetricSettings(rounds=2, degrees=(2,)) if quick else MetricSettings()
    cand = design_linear_metric(system, K0, vbar=REPORT_VBAR, hidden=config.hidden,
                                settings=ms, seed=config.seed, log=say)
    if cand is None:
        raise CertifyError("no design with M(x) was proved")
    save_candidate(paths["metric"], system, cand)
    info: dict[str, Any] = {"train_seconds": time.perf_counter() - t0}
    att = learn_metric_gain(system, cand, vbar=REPORT_VBAR, settings=ms, log=say)
    info["learned_outcome"] = att.message
    if att.final is not None:
        save_candidate(paths["metric_learned"], system, att.final, returned=att.beat)
    info["train_seconds"] = time.perf_counter() - t0
    return info


def _bound_K(system: Any) -> np.ndarray:
    from certify.design.bound import design_bound_observer

    d = design_bound_observer(system)
    if d.K is None:
        raise CertifyError(f"no linear observer for {system.name}: {d.message}")
    return d.K


def source_mse(problem: Any) -> float:
    """Mean over [0, T] of ||x - xhat||^2 under the source protocol (inf if it blows up)."""
    system = problem.system
    sim = system.simulation or {}
    x0 = torch.tensor([sim.get("x0", [0.0] * system.n)], dtype=torch.float64)
    xh0 = torch.tensor([sim.get("xhat0", [0.0] * system.n)], dtype=torch.float64)
    steps = int(round(float(sim.get("t_final", SIM_T)) / SIM_DT))
    noise = gaussian_noise(steps, 1, system.p, VBAR, seed=SIM_SEED)
    tr = simulate(system, problem.network, x0, xh0, dt=SIM_DT, steps=steps, noise=noise)
    e2 = ((tr.x - tr.xhat) ** 2).sum(-1)
    v = float(e2.mean())
    return v if math.isfinite(v) else math.inf


def bound_fields(bounds: Any) -> dict[str, Any]:
    """The error-bound check's headline fields, read generically (None where absent)."""
    if bounds is None:
        return {"bounds_status": None}
    out: dict[str, Any] = {"bounds_status": getattr(bounds.status, "value", str(bounds.status))}
    for key in ("best", "ultimate", "headline", "settle_time", "per_component", "vacuous",
                "box_half_diagonal", "vbar"):
        out[key] = getattr(bounds, key, None)
    each = {}
    listing = bounds.bounds() if hasattr(bounds, "bounds") else []
    for b in listing:
        each[b.name] = b.bias if b.applicable else None
    out["bounds"] = each
    return out


def evaluate(path: Path, settings: VerifySettings) -> dict[str, Any]:
    ck = checkpoint.load(path)
    cert = verify(ck, settings, figures=False)
    c = cert.checks
    rate = c.get("rate")
    row = {"verdict": cert.verdict, "mpdi": c["mpdi"].status.value,
           "lam": ck.problem.lam, "lam_cert": getattr(rate, "proved_lower", None),
           "L": getattr(c.get("lipschitz"), "value", None),
           "eps_bar": getattr(c.get("residual"), "upper", None),
           "kappa_P": float(np.linalg.cond(np.asarray(ck.problem.P))),
           **bound_fields(c.get("bounds")),
           "mse_source": source_mse(ck.problem), "verify_seconds": cert.timings["total"]}
    tr = ck.training or {}
    if ck.problem.metric is not None:
        row["metric_degree"] = ck.problem.metric.degree
        mb = c.get("metric_bound")
        row["metric_ultimate"] = getattr(mb, "ultimate", None)
        stages = getattr(mb, "stages", None) or []
        row["metric_tube"] = stages[-1]["tau"] if stages else None
        row["metric_seconds"] = getattr(mb, "seconds", None)
        design = (tr.get("metric") or {}).get("returned") or {}
        per = design.get("design_per_unit_noise")
        row["designed_bound"] = None if per is None else VBAR * per
        outcome = ((tr.get("metric") or {}).get("learned") or {}).get("message")
        if outcome is not None:  # else the design step's own (a checkpoint written alone)
            row["learned_outcome"] = outcome
    elif tr.get("preset") == "bound":
        per = tr.get("bound_per_unit_noise")
        row["designed_bound"] = None if per is None else VBAR * per
        row["alpha"], row["mu"], row["lam_min_P"] = (tr.get("alpha"), tr.get("mu"),
                                                     tr.get("lam_min_P"))
        row["sampled_bound"] = _sampled(ck, tr.get("alpha"))
        learned = tr.get("learned") or {}
        row["learned_outcome"] = learned.get("message")
    return row


def _sampled(ck: Any, alpha: float | None) -> float | None:
    if alpha is None:
        return None
    from certify.design.bound import sampled_bound

    got = sampled_bound(ck.problem.system, ck.problem.network, np.asarray(ck.problem.P),
                        float(alpha))
    v = got["per_unit_noise"]
    return VBAR * v if math.isfinite(v) else math.inf


def _f(v: Any, fmt: str = ".4g") -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return format(v, fmt) if isinstance(v, float) else str(v)


def _headline(r: dict[str, Any]) -> str:
    if r.get("headline") is None:
        return "—"
    from certify.arith.text import upper_text  # as the certificate's headline prints it

    word = "vacuous" if r.get("vacuous") else "useful"
    after = "" if r.get("settle_time") is None else \
        f" after t >= {upper_text(r['settle_time'], 2)} s"
    return f"<= {upper_text(r['headline'])}{after} ({word})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/compare", help="checkpoint cache folder")
    ap.add_argument("--systems", default=",".join(SYSTEMS), help="comma-separated systems")
    ap.add_argument("--designs", default=",".join(DESIGNS),
                    help=f"comma-separated designs out of {','.join(DESIGNS)} (paper: vdp "
                         "only)")
    ap.add_argument("--lams", default=None,
                    help="comma-separated rates of the rate designs (default: each system's)")
    ap.add_argument("--quick", action="store_true",
                    help="smaller verification and training budgets")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # one thread: on a shared 2-core machine two are slower
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    designs = [d for d in args.designs.split(",") if d]
    unknown = sorted(set(designs) - set(DESIGNS))
    if unknown:
        ap.error(f"unknown design(s) {', '.join(unknown)}")
    settings = VerifySettings(grid_points=50_000 if args.quick else 200_000,
                              max_boxes=200_000 if args.quick else 2_000_000,
                              lipschitz_boxes=20_000 if args.quick else 100_000,
                              residual_boxes=20_000 if args.quick else 100_000,
                              adversarial_starts=32, noise=VBAR, skip=("simulation",))
    rows: list[dict[str, Any]] = []
    for name in [s for s in args.systems.split(",") if s]:
        system = load_system(name)
        lams = [float(v) for v in args.lams.split(",")] if args.lams else [float(system.lam)]
        jobs: list[tuple[str, float | None, Path]] = []
        for design in designs:
            if design == "paper" and name != "vdp":
                continue
            if design in RATE_DESIGNS:
                jobs += [(design, lam, out / f"{name}_{design}_lam{_tag(lam)}.ckpt")
                         for lam in lams]
            else:
                jobs.append((design, None, out / f"{name}_{design}.ckpt"))
        bound_paths = {"bound": out / f"{name}_bound.ckpt",
                       "learned": out / f"{name}_learned.ckpt"}
        metric_paths = {"bound": bound_paths["bound"],
                        "metric": out / f"{name}_metric.ckpt",
                        "metric_learned": out / f"{name}_metric_learned.ckpt"}
        for design, lam, path in jobs:
            row: dict[str, Any] = {"system": name, "design": design, "checkpoint": str(path)}
            try:
                if not path.exists():
                    print(f"training {name} {design} -> {path}", file=sys.stderr, flush=True)
                    if design == "paper":
                        row.update(make_paper(path, system, lam))
                    elif design == "lmi":
                        row.update(make_lmi(path, system, lam))
                    elif design == "certified":
                        row.update(make_certified(path, system, lam, args.quick))
                    elif design in ("metric", "metric_learned"):
                        row.update(make_metric(metric_paths, system, args.quick))
                    else:
                        row.update(make_bound(bound_paths, system, args.quick))
                else:
                    row["cached"] = True
                if not path.exists():
                    raise CertifyError(f"{design} wrote no checkpoint")
                print(f"verifying {path}", file=sys.stderr, flush=True)
                row.update(evaluate(path, settings))
            except CertifyError as exc:
                row.update({"verdict": "ERROR", "error": str(exc)})
            rows.append(row)
    print(f"| system | design | verdict | lam (proved) | best bound | ultimate | ||e|| at "
          f"vbar={VBAR:g} | per component | box half-diagonal | designed (SDP) | sampled | "
          "MSE, source protocol |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        comp = r.get("per_component")
        comp_s = "—" if not comp else ", ".join(f"{v:.3g}" for v in comp)
        print(f"| {r['system']} | {r['design']} | {r.get('verdict')} | "
              f"{_f(r.get('lam'))} ({_f(r.get('lam_cert'))}) | {r.get('best') or '—'} | "
              f"{_f(r.get('ultimate'))} | {_headline(r)} | {comp_s} | "
              f"{_f(r.get('box_half_diagonal'))} | {_f(r.get('designed_bound'))} | "
              f"{_f(r.get('sampled_bound'))} | {_f(r.get('mse_source'))} |")
    print()
    for r in rows:
        if r.get("learned_outcome") and r["design"] in ("bound", "metric"):
            print(f"{r['system']}: {r['learned_outcome']}")
    print()
    for r in rows:
        record_line({k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                     for k, v in r.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
