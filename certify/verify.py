"""`verify()`: the one library entry point. Runs every check, gathers the Certificate.

It never prints or exits: progress goes to the injected `progress`, the outcome is data.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import time
from typing import Any

import numpy as np
import torch

from certify.certificate import Certificate, decide_verdict
from certify.checkpoint import Checkpoint, versions
from certify.parallel import torch_threads
from certify.problem import Problem
from certify.progress import NullProgress, Progress
from certify.results import Status
from certify.settings import VerifySettings

MAP_RESOLUTION = 61  # per axis, for the report's maps
MAP_Y_SAMPLES = 41  # total samples over Y (and the other states) per map pixel


def verify(checkpoint: Checkpoint, settings: VerifySettings | None = None, *,
           progress: Progress | None = None) -> Certificate:
    """Check a loaded checkpoint and return its Certificate (see METHOD.md §3)."""
    settings = settings or VerifySettings()
    with torch_threads(1):  # see certify.parallel: chunk workers beat intra-op threads here
        return _verify(checkpoint, settings, progress or NullProgress())


def _verify(checkpoint: Checkpoint, settings: VerifySettings, progress: Progress) -> Certificate:
    from certify.checks.bounds import check_bounds
    from certify.checks.lipschitz import check_lipschitz
    from certify.checks.mpdi import check_mpdi
    from certify.checks.necessary import check_necessary
    from certify.checks.rate import check_rate
    from certify.checks.residual import check_residual
    from certify.checks.simulation import check_simulation
    from certify.prover import bound_dk_dy

    problem = checkpoint.problem
    torch.manual_seed(settings.seed)
    checks: dict[str, Any] = {}
    timings: dict[str, float] = {}
    figures: dict[str, Any] = {}
    t_all = time.perf_counter()

    def wanted(name: str) -> bool:
        return name not in settings.skip

    def timed(name: str, fn, *args, **kwargs):
        t0 = time.perf_counter()
        progress.start(name)
        out = fn(*args, **kwargs)
        timings[name] = time.perf_counter() - t0
        progress.finish(name, getattr(out, "status", Status.SKIPPED).value
                        if hasattr(out, "status") else "")
        return out

    system = problem.system
    if wanted("necessary"):
        checks["necessary"] = timed("necessary", check_necessary, system, problem.P, problem.lam,
                                    settings, progress=progress)
    if wanted("mpdi"):
        checks["mpdi"] = timed("mpdi", check_mpdi, problem, settings, progress=progress,
                               figures=figures)
    if wanted("rate"):
        checks["rate"] = timed("rate", check_rate, problem, settings, progress=progress,
                               mpdi=checks.get("mpdi"))
    if wanted("residual"):
        checks["residual"] = timed("residual", check_residual, problem, settings,
                                   progress=progress)
    if wanted("lipschitz"):
        t0 = time.perf_counter()
        local = bound_dk_dy(problem, seconds=settings.lipschitz_seconds,
                            max_boxes=settings.max_boxes)
        timings["lipschitz_local"] = time.perf_counter() - t0
        checks["lipschitz"] = timed("lipschitz", check_lipschitz, problem, settings,
                                    progress=progress, local_upper=local)
    rate, res, lip = checks.get("rate"), checks.get("residual"), checks.get("lipschitz")
    lam_cert = None
    if rate is not None:  # a sampled rate <= 0 already rules any bound out; else the proved one
        lam_cert = rate.sampled_upper if rate.sampled_upper <= 0 else rate.proved_lower
    eps_bar = res.upper if res is not None else None
    L = lip.value if lip is not None else None
    if wanted("bounds"):
        # sup ||P^(1/2) k(x, h(x))|| is known exactly only when k vanishes there by construction
        eps_bar_P = 0.0 if res is not None and res.structural else None
        checks["bounds"] = timed(
            "bounds", check_bounds, problem, lam_cert=lam_cert, eps_bar=eps_bar, L=L,
            vbar=settings.noise, eps_bar_P=eps_bar_P,
            L_P=lip.lipsdp_P if lip is not None else None,
            L_is_local=bool(lip is not None and lip.which == "local"))
    required = list(settings.required)
    if wanted("simulation") and "bounds" in checks:
        pre_verdict, _ = decide_verdict(checks, required, settings.allow_unknown)
        certified = pre_verdict == "CERTIFIED" and checks["bounds"].status == Status.PROVED
        checks["simulation"] = timed("simulation", check_simulation, problem, checks["bounds"],
                                     settings, progress=progress, certified=certified)
        if checks["simulation"].status == Status.ERROR and "simulation" not in required:
            required.append("simulation")  # a breached proof is a bug: never certify
    t0 = time.perf_counter()
    figures.update(report_maps(problem, checks))
    timings["figures"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    verdict, summary = decide_verdict(checks, required, settings.allow_unknown)
    network = problem.network.architecture()
    network["has_linear_gain"] = bool(torch.any(problem.network.K != 0))
    training = checkpoint.training or {}
    return Certificate(
        verdict=verdict, summary=summary, checks=checks, required=required,
        settings=dataclasses.asdict(settings), system=system.summary(), lam=problem.lam,
        P=np.asarray(problem.P).tolist(), network=network,
        checkpoint={"path": checkpoint.path, "sha256": checkpoint.sha256,
                    "created": checkpoint.created,
                    "preset": (training.get("config") or {}).get("preset", training.get("preset")),
                    "versions": checkpoint.versions},
        versions=versions(), timings=timings, figures=figures,
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )


def _state_grid(problem: Problem) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    X = problem.system.X
    xs = np.linspace(X[0, 0], X[0, 1], MAP_RESOLUTION)
    ys = np.linspace(X[1, 0], X[1, 1], MAP_RESOLUTION) if problem.n > 1 else np.zeros(1)
    gx, gy = np.meshgrid(xs, ys)  # [ny, nx]
    centre = X.mean(axis=1)
    pts = np.tile(centre, (gx.size, 1))
    pts[:, 0] = gx.ravel()
    if problem.n > 1:
        pts[:, 1] = gy.ravel()
    return xs, ys, torch.as_tensor(pts, dtype=torch.float64)


def report_maps(problem: Problem, checks: dict[str, Any]) -> dict[str, Any]:
    """Arrays for the report's maps over the first two state coordinates."""
    from certify.checks.mpdi import mpdi_score
    from certify.checks.residual import residual_norm

    system = problem.system
    xs, ys, pts = _state_grid(problem)
    axes = system.states[:2]
    out: dict[str, Any] = {}
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        if "mpdi" in checks:
            # samples over Y (and over the remaining states) for each pixel; max taken
            m = MAP_Y_SAMPLES
            lo = torch.as_tensor(np.vstack([system.X[2:], system.Y])[:, 0])
            hi = torch.as_tensor(np.vstack([system.X[2:], system.Y])[:, 1])
            u = torch.linspace(0, 1, m, dtype=torch.float64)[:, None]
            rest = lo + (hi - lo) * (u if lo.numel() == 1 else
                                     torch.rand(m, lo.numel(), generator=gen, dtype=torch.float64))
            z = torch.cat([pts[:, :2].repeat_interleave(m, 0), rest.repeat(len(pts), 1)], dim=1)
            vals = mpdi_score(problem)(z).reshape(len(pts), m).max(dim=1).values
            out["mpdi_map"] = _grid_dict(axes, xs, ys, vals)
        if "residual" in checks:
            out["residual_map"] = _grid_dict(axes, xs, ys, residual_norm(problem, pts))
        if "necessary" in checks:
            try:
                from certify.checks.necessary import manifold_quantity
            except ImportError:
                manifold_quantity = None
            if manifold_quantity is not None:
                q = manifold_quantity(system, problem.P, problem.lam, pts)
                yv = system.h(pts)
                inside = ((yv >= torch.as_tensor(system.Y[:, 0])) &
                          (yv <= torch.as_tensor(system.Y[:, 1]))).all(dim=1)
                q = torch.where(inside, q, torch.full_like(q, float("nan")))
                out["necessary_map"] = _grid_dict(axes, xs, ys, q)
    return out


def _grid_dict(axes: list[str], xs: np.ndarray, ys: np.ndarray, vals: torch.Tensor) -> dict:
    values = vals.reshape(len(ys), len(xs)).numpy()
    return {"axes": list(axes), "x": xs.tolist(), "y": ys.tolist(),
            "values": [[float(v) for v in row] for row in values]}
