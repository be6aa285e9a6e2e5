"""`verify()`: the one library entry point. Runs every check, gathers the Certificate.

It never prints or exits: progress goes to the injected `progress`, the outcome is data.
The checks run through `certify.checks.registry`, which isolates their faults: a check that
raises is that check's ERROR, and the others still run. What a run computes with is
resolved here, once: the device, the executor and the wall-clock cap's deadline, carried to
the checks on their `Context`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import shlex
import time
from typing import Any

import numpy as np
import torch

from certify.arith.text import lower_text
from certify.certificate import Certificate
from certify.checks.base import Context
from certify.checks.registry import run_checks
from certify.figuredata import MAP_POINTS, FigureData, GridMap
from certify.model.checkpoint import Checkpoint, versions
from certify.model.problem import Problem
from certify.progress import NullProgress, Progress, finish_step, start_step
from certify.results import CheckFailure, MpdiResult, RateResult, Status, decide_verdict
from certify.search.threads import torch_threads
from certify.settings import VerifySettings, required_checks

MAP_RESOLUTION = MAP_POINTS  # per axis, the report's maps
MAP_Y_SAMPLES = 41  # total samples over Y (and the other states) per map pixel


def verify(checkpoint: Checkpoint, settings: VerifySettings | None = None, *,
           progress: Progress | None = None, figures: bool = True,
           executor: Any = None, fail_fast: bool = False,
           overrides: dict[str, Any] | None = None) -> Certificate:
    """Check a loaded checkpoint and return its Certificate (see METHOD.md §3).

    `figures`: also compute the maps the reports draw (a step of its own, about as long as
    a fast check); leave it False when no report will be written. `executor`: where chunked
    work runs (`certify.search.distributed.executor`); None opens the one
    `settings.workers/scheduler` ask for and closes it at the end. `fail_fast`: once a
    required check is VIOLATED the verdict is decided and no further check runs (they are
    NOT RUN; `certify.checks.registry.run_checks`) and the MPDI looks for a counterexample
    by a coarse search first: for a caller that wants the verdict, not the numbers.
    `overrides`: {"lam": rate, "metric": P} verifies the checkpoint's network at that design
    rate and/or metric instead of its own (validated values; the certificate records both,
    `Certificate.overrides`). The wall-clock cap
    `settings.max_seconds` counts from this call.
    """
    from certify.arith.device import resolve_device
    from certify.search.distributed.executor import executor_from_settings, using

    started = time.perf_counter()
    settings = settings or VerifySettings()
    device = resolve_device(settings.device)  # an unusable device is bad input, before any work
    owned = executor is None
    executor = executor_from_settings(settings) if owned else executor
    deadline = None if settings.max_seconds is None else started + settings.max_seconds
    try:
        # see certify.search.threads: chunk workers beat intra-op threads here
        with torch_threads(1), using(executor):
            problem, applied = overridden(checkpoint.problem, overrides or {})
            context = Context(problem=problem, settings=settings,
                              progress=progress or NullProgress(), figures=FigureData(),
                              required=required_checks(settings), device=device,
                              executor=executor, deadline=deadline, fail_fast=fail_fast)
            return _verify(checkpoint, context, figures, applied)
    finally:
        if owned:
            executor.close()


def overridden(problem: Problem, overrides: dict[str, Any]) -> tuple[Problem, dict[str, Any]]:
    """The problem at the overridden design rate and metric, and the record of each
    override: {"lam": {"value": 0.45, "checkpoint": 0.5}, ...}."""
    unknown = set(overrides) - {"lam", "metric"}
    if unknown:
        raise ValueError(f"unknown override(s) {sorted(unknown)}: only lam and metric")
    if not overrides:
        return problem, {}
    lam = float(overrides.get("lam", problem.lam))
    P = np.asarray(overrides.get("metric", problem.P), dtype=np.float64)
    record = {}
    if "lam" in overrides:
        record["lam"] = {"value": lam, "checkpoint": float(problem.lam)}
    if "metric" in overrides:
        record["metric"] = {"value": P.tolist(), "checkpoint": np.asarray(problem.P).tolist()}
    return Problem(system=problem.system, network=problem.network, lam=lam, P=P,
                   device=problem.device, shift=problem.shift), record


def _verify(checkpoint: Checkpoint, context: Context, figures: bool,
            applied: dict[str, Any]) -> Certificate:
    """The run of `verify` on `context.problem` (the checkpoint's, with the overrides
    `applied`, as `overridden` records them)."""
    settings, progress, problem = context.settings, context.progress, context.problem
    torch.manual_seed(settings.seed)
    t_all = time.perf_counter()
    timings = run_checks(context, skip=settings.skip)
    checks = context.results
    if figures:
        start_step(progress, "figures")
        t0 = time.perf_counter()
        report_maps(problem, checks, context.figures)
        timings["figures"] = time.perf_counter() - t0
        finish_step(progress, "figures", "done", timings["figures"])
    timings["total"] = time.perf_counter() - t_all
    verdict, summary = decide_verdict(checks, context.required, settings.allow_unknown)
    sampled = None
    if isinstance(checks.get("rate"), CheckFailure) and checks["rate"].status == Status.NOT_RUN:
        sampled = sampled_rate_cap(problem, settings.seed)
    hint = smaller_rate_hint(checks, context.required, problem.lam, checkpoint.path, applied,
                             sampled_cap=sampled)
    network = problem.network.architecture()
    network["has_linear_gain"] = bool(torch.any(problem.network.K != 0))
    training = checkpoint.training or {}
    return Certificate(
        verdict=verdict, summary=f"{hint} ({summary})" if hint else summary, checks=checks,
        required=context.required,
        settings=dataclasses.asdict(settings), system=problem.system.summary(), lam=problem.lam,
        P=np.asarray(problem.P).tolist(), network=network,
        checkpoint={"path": checkpoint.path, "sha256": checkpoint.sha256,
                    "created": checkpoint.created,
                    "preset": (training.get("config") or {}).get("preset", training.get("preset")),
                    "versions": checkpoint.versions},
        versions=versions(), timings=timings, figures=context.figures,
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        overrides=applied,
    )


#: points of the quick sampled rate when the rate check was not run (a decided verdict)
RATE_SAMPLES = 20_000
#: the rate a hint proposes to try is this share of the sampled cap (below it: some margin)
TRY_SHARE = 0.9


def sampled_rate_cap(problem: Problem, seed: int, count: int = RATE_SAMPLES) -> float:
    """The smallest pointwise rate -lam_max(He{P J_cl}, P)/2 at `count` uniform points of
    X x Y: the MPDI fails at every rate above it (a sampled cap, not a proof)."""
    from certify.model.kernels import pointwise_rate

    s = problem.system
    box = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    z = box[:, 0] + torch.rand(count, len(box), generator=gen, dtype=torch.float64) * (
        box[:, 1] - box[:, 0])
    host = problem.on("cpu")
    with torch.no_grad():
        r = pointwise_rate(s, host.network, host.P_t, z[:, :s.n], z[:, s.n:])
    r = r[torch.isfinite(r)]
    return float(r.min()) if len(r) else float("nan")


def smaller_rate_hint(checks: dict[str, Any], required: list[str], lam: float,
                      path: str | None, overrides: dict[str, Any],
                      sampled_cap: float | None = None) -> str:
    """Where the MPDI is the one required check VIOLATED at the design rate `lam` and the
    rate check proved a smaller lam_cert > 0: that rate, rounded down (so that it is at most
    the proved bound: the MPDI holds there), and the command that certifies at it. Where the
    rate check was not run because the verdict was decided: with `sampled_cap` (the smallest
    pointwise rate at samples, `sampled_rate_cap`) a rate to try below it and the command that
    decides it, or that no positive rate holds at the samples; how to have the rate check run
    it in any case; "" else."""
    mpdi, rate = checks.get("mpdi"), checks.get("rate")
    failed = [n for n in required if n in checks and checks[n].status == Status.VIOLATED]
    if not (isinstance(mpdi, MpdiResult) and mpdi.status == Status.VIOLATED
            and failed == ["mpdi"]):
        return ""
    if isinstance(rate, CheckFailure) and rate.status == Status.NOT_RUN:
        run_it = ("a run with a report output (e.g. --json PATH) runs the rate check, which "
                  "proves the largest rate that does")
        if sampled_cap is not None and sampled_cap == sampled_cap and sampled_cap <= 0:
            return (f"the MPDI is violated at the design rate lam = {lam:g}, and no rate > 0 "
                    f"holds at sampled points (the smallest pointwise rate there is "
                    f"{sampled_cap:.4g}): this gain does not contract everywhere in X x Y")
        if sampled_cap is not None and 0 < sampled_cap < lam:
            text = lower_text(TRY_SHARE * sampled_cap, 3)
            command = ["certify", "run", path or "CHECKPOINT", "--lam", text]
            if "metric" in overrides:
                command += ["--metric", json.dumps(overrides["metric"]["value"])]
            return (f"the MPDI is violated at the design rate lam = {lam:g}; at sampled points "
                    f"it fails above lam = {sampled_cap:.4g}, so a smaller rate may certify: "
                    f"`{shlex.join(command)}` decides it ({run_it})")
        return (f"the MPDI is violated at the design rate lam = {lam:g}; a smaller rate may "
                f"certify: {run_it}")
    if not isinstance(rate, RateResult):
        return ""
    lower = rate.proved_lower
    if lower is None or not 0 < lower < lam:
        return ""
    text = lower_text(lower, 4)
    if not 0 < float(text) <= lower:  # never suggest more than was proved
        return ""
    command = ["certify", "run", path or "CHECKPOINT", "--lam", text]
    if "metric" in overrides:
        command += ["--metric", json.dumps(overrides["metric"]["value"])]
    return (f"the MPDI is violated at the design rate lam = {lam:g}, but a rate lam_cert >= "
            f"{text} is proved: `{shlex.join(command)}` certifies at that rate")


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


def report_maps(problem: Problem, checks: dict[str, Any], out: FigureData) -> FigureData:
    """Fill `out` with the report's maps over the first two state coordinates (for the
    checks that produced a result)."""
    from certify.checks.mpdi import mpdi_score
    from certify.checks.residual import residual_norm

    def ran(name: str) -> bool:
        return name in checks and not isinstance(checks[name], CheckFailure)

    system = problem.system
    xs, ys, pts = _state_grid(problem)
    axes = list(system.states[:2])

    def grid(vals: torch.Tensor) -> GridMap:
        values = vals.reshape(len(ys), len(xs)).numpy()
        return GridMap(x=xs.tolist(), y=ys.tolist(), values=values.tolist(), axes=axes)

    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        if ran("mpdi"):
            # samples over Y (and over the remaining states) for each pixel; max taken
            m = MAP_Y_SAMPLES
            lo = torch.as_tensor(np.vstack([system.X[2:], system.Y])[:, 0])
            hi = torch.as_tensor(np.vstack([system.X[2:], system.Y])[:, 1])
            u = torch.linspace(0, 1, m, dtype=torch.float64)[:, None]
            rest = lo + (hi - lo) * (u if lo.numel() == 1 else
                                     torch.rand(m, lo.numel(), generator=gen, dtype=torch.float64))
            z = torch.cat([pts[:, :2].repeat_interleave(m, 0), rest.repeat(len(pts), 1)], dim=1)
            vals = mpdi_score(problem)(z).reshape(len(pts), m).max(dim=1).values
            out.mpdi_map = grid(vals)
        if ran("residual"):
            out.residual_map = grid(residual_norm(problem, pts))
        if ran("necessary"):
            from certify.design.manifold import manifold_quantity

            q = manifold_quantity(system, problem.P, problem.lam, pts)
            yv = system.h(pts)
            inside = ((yv >= torch.as_tensor(system.Y[:, 0])) &
                      (yv <= torch.as_tensor(system.Y[:, 1]))).all(dim=1)
            q = torch.where(inside, q, torch.full_like(q, float("nan")))
            if bool(torch.isfinite(q).any()):  # none where all states are measured (no q)
                out.necessary_map = grid(q)
    return out
