"""Simulation check (METHOD §3.8): the observed error against the proved bound.

Plant + observer are simulated (batched RK4, `certify.integrate`) from several initial
conditions in X with bounded noise ||v(t)||_2 <= vbar. For each run the first time a validity
condition of the bound fails is found (x or xhat leaves X, h(x) leaves Y, y + v leaves Y when
L is local, a non-finite state): the exit. Up to that time the error must stay under the
tightest applicable proved bound, up to the integrator's tolerance (estimated per run by a
second integration at twice the step). A breach of a PROVED certificate is a bug in this
tool, reported as ERROR, never as a pass. The source's protocol (Gaussian noise of std 0.15,
its initial conditions) is run beside, labelled as outside the theorem's conditions, for its
mean squared error. Simulation is evidence, never proof: PROVED here means "no breach seen".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from certify.checks.base import Check, Context, Presentation, Quantity
from certify.checks.bounds import BOUND_NAMES, bound_curve, initial_value
from certify.errors import SpecError
from certify.integrate import bounded_noise, gaussian_noise, simulate
from certify.problem import Problem
from certify.progress import NullProgress, Progress
from certify.results import BoundsResult, SimulationResult, SimulationRun, Status
from certify.settings import VerifySettings
from certify.system import System

#: The source's simulation protocol: white Gaussian measurement noise of this std.
SOURCE_NOISE_STD = 0.15
#: Samples kept per run for reports (the check itself uses every step).
MAX_SAMPLES = 500
#: Absolute part of the comparison tolerance (on top of the estimated integration error).
ATOL = 1e-9


@dataclass
class InitialConditions:
    """Labels and initial states x0, xhat0 [R, n] of the bounded-noise runs."""

    labels: list[str]
    x0: torch.Tensor
    xhat0: torch.Tensor


def source_initial_condition(system: System) -> tuple[list[float], list[float]] | None:
    """The source's x0 and xhat0 from the spec's [simulation] table (None if absent)."""
    sim = system.simulation or {}
    if "x0" not in sim:
        return None
    try:
        x0 = [float(v) for v in sim["x0"]]
        xhat0 = [float(v) for v in sim.get("xhat0", [0.0] * system.n)]
    except (TypeError, ValueError):
        raise SpecError(f"system {system.name}: [simulation] x0/xhat0 must be lists of "
                        "numbers") from None
    if len(x0) != system.n or len(xhat0) != system.n:
        raise SpecError(f"system {system.name}: [simulation] x0 and xhat0 need {system.n} "
                        "entries each")
    if not all(math.isfinite(v) for v in x0 + xhat0):
        raise SpecError(f"system {system.name}: [simulation] x0/xhat0 must be finite")
    return x0, xhat0


def initial_conditions(system: System, count: int, seed: int) -> InitialConditions:
    """The source's (x0, xhat0) when the spec has one, then seeded random pairs in X.

    Random x0 are drawn uniformly in X with h(x0) in Y (rejection, batched); xhat0 uniformly
    in X, or (every second pair) within 5% of the box of x0. All runs use bounded noise.
    """
    labels: list[str] = []
    x0s: list[torch.Tensor] = []
    xh0s: list[torch.Tensor] = []
    src = source_initial_condition(system)
    if src is not None:
        labels.append("source x0, bounded noise")
        x0s.append(torch.tensor([src[0]], dtype=torch.float64))
        xh0s.append(torch.tensor([src[1]], dtype=torch.float64))
    need = count - len(labels)
    if need > 0:
        gen = torch.Generator().manual_seed(int(seed) + 1)
        X = torch.as_tensor(system.X, dtype=torch.float64)
        Y = torch.as_tensor(system.Y, dtype=torch.float64)
        lo, width = X[:, 0], X[:, 1] - X[:, 0]
        cand = lo + width * torch.rand(64 * need, system.n, generator=gen, dtype=torch.float64)
        hy = system.h(cand)
        ok = ((hy >= Y[:, 0]) & (hy <= Y[:, 1])).all(dim=1)
        pick = cand[ok][:need]
        if pick.shape[0] < need:  # h(X) barely meets Y: fall back to unfiltered points
            pick = torch.cat([pick, cand[~ok][: need - pick.shape[0]]])
        xh = lo + width * torch.rand(need, system.n, generator=gen, dtype=torch.float64)
        # every second pair starts close (5% of the box): with a large initial error a
        # high-gain observer's transient leaves X at once and nothing can be compared
        near = torch.arange(need) % 2 == 1
        offset = 0.05 * width * (2 * torch.rand(need, system.n, generator=gen,
                                                dtype=torch.float64) - 1)
        close = torch.minimum(torch.maximum(pick + offset, X[:, 0]), X[:, 1])
        xh = torch.where(near[:, None], close, xh)
        x0s.append(pick)
        xh0s.append(xh)
        labels += [f"random {i + 1}, " + ("small initial error" if bool(near[i]) else
                                          "bounded noise") for i in range(need)]
    return InitialConditions(labels=labels, x0=torch.cat(x0s), xhat0=torch.cat(xh0s))


def _first_exit(problem: Problem, x: torch.Tensor, xhat: torch.Tensor, v: torch.Tensor,
                t: torch.Tensor, L_is_local: bool) -> tuple[np.ndarray, list[str]]:
    """First step index at which a validity condition fails, per run ([R]; T if never), and
    the reason in words. x, xhat [T, R, n], v [T, R, p]."""
    sysm = problem.system
    T, R, n = x.shape
    X = torch.as_tensor(sysm.X, dtype=torch.float64)
    Y = torch.as_tensor(sysm.Y, dtype=torch.float64)
    hx = sysm.h(x.reshape(T * R, n)).reshape(T, R, sysm.p)
    checks: list[tuple[str, torch.Tensor, torch.Tensor, list[str]]] = [
        ("the plant state x left X", x, X, sysm.states),
        ("the observer state xhat left X", xhat, X, sysm.states),
        ("the true output h(x) left Y", hx, Y, sysm.outputs),
    ]
    if L_is_local:
        checks.append(("the measured output h(x) + v left Y (L is a local bound)", hx + v, Y,
                       sysm.outputs))
    bad = torch.zeros(T, R, dtype=torch.bool)
    for _, val, box, _ in checks:
        inside = ((val >= box[:, 0]) & (val <= box[:, 1])).all(dim=-1)  # NaN -> outside
        bad |= ~inside
    any_bad = bad.any(dim=0)
    first = torch.where(any_bad, bad.to(torch.int8).argmax(dim=0), torch.full((R,), T))
    reasons: list[str] = []
    for r in range(R):
        k = int(first[r])
        if k >= T:
            reasons.append("")
            continue
        words = []
        for what, val, box, names in checks:
            row = val[k, r]
            for i, name in enumerate(names):
                a = float(row[i])
                if not math.isfinite(a):
                    words.append(f"{what}: {name} is not finite")
                elif a < box[i, 0]:
                    words.append(f"{what}: {name} = {a:.6g} < {float(box[i, 0]):g}")
                elif a > box[i, 1]:
                    words.append(f"{what}: {name} = {a:.6g} > {float(box[i, 1]):g}")
        reasons.append(f"t = {float(t[k]):.4g}: " + "; ".join(words))
    return first.numpy(), reasons


def _thin(T: int, limit: int = MAX_SAMPLES) -> np.ndarray:
    return np.unique(np.linspace(0, T - 1, min(T, limit)).round().astype(np.int64))


def _best_bound(bounds: BoundsResult | None, P: np.ndarray, e0: np.ndarray,
                t: np.ndarray) -> tuple[np.ndarray | None, list[str]]:
    """Pointwise minimum over every applicable proved bound -> [R, T] (None if none)."""
    if bounds is None:
        return None, []
    curves, names = [], []
    for which in BOUND_NAMES:
        b = getattr(bounds, which)
        if b is not None and b.applicable:
            start = initial_value(which, e0, P)
            curves.append(bound_curve(bounds, which, start, t))
            names.append(which)
    if not curves or "iss" not in names:
        return None, []
    return np.minimum.reduce(curves), names


def check_simulation(problem: Problem, bounds: BoundsResult | None,
                     settings: VerifySettings, *, progress: Progress | None = None,
                     certified: bool) -> SimulationResult:
    """Simulate plant + observer; compare the error with the proved bound inside the conditions.

    `certified`: whether the bound's inputs were all proved (the certificate passes). Then a
    breach is a bug in certify: status ERROR with a loud message.
    """
    start_time = time.perf_counter()
    progress = NullProgress() if progress is None else progress
    sysm = problem.system
    p = sysm.p
    P = np.asarray(problem.P, dtype=np.float64)
    dt = float(settings.sim_dt)
    steps = max(2, int(math.ceil(settings.sim_time / dt)))
    steps += steps % 2  # even, so the run at 2 dt ends at the same time
    vbar = float(bounds.vbar) if bounds is not None else float(settings.noise)
    L_is_local = bounds is not None and bounds.L_is_local
    progress.start("simulation", total=3)

    ics = initial_conditions(sysm, settings.sim_initial_conditions, settings.seed)
    R_b = len(ics.labels)
    src = source_initial_condition(sysm)
    labels = list(ics.labels)
    x0, xhat0 = ics.x0, ics.xhat0
    noise = bounded_noise(steps, R_b, p, vbar, dt, seed=settings.seed)
    kinds = ["bounded"] * R_b
    if src is not None:
        labels.append(f"source protocol (Gaussian noise, std {SOURCE_NOISE_STD:g}; outside "
                      "the theorem's conditions)")
        x0 = torch.cat([x0, torch.tensor([src[0]], dtype=torch.float64)])
        xhat0 = torch.cat([xhat0, torch.tensor([src[1]], dtype=torch.float64)])
        noise = torch.cat([noise, gaussian_noise(steps, 1, p, SOURCE_NOISE_STD,
                                                 seed=settings.seed + 2)], dim=1)
        kinds.append("gaussian")
    R = len(labels)

    fine = simulate(sysm, problem.network, x0, xhat0, dt=dt, steps=steps, noise=noise)
    progress.update("simulation")
    t = fine.t.numpy()
    T = t.shape[0]
    err = torch.linalg.vector_norm(fine.x - fine.xhat, dim=-1).numpy()  # [T, R]
    first, reasons = _first_exit(problem, fine.x, fine.xhat, fine.v, fine.t, L_is_local)
    e0 = (x0 - xhat0).numpy()
    curve, names = _best_bound(bounds, P, e0, t)  # [R, T] or None

    # Integration-error estimate by step doubling: the same signal at 2 dt (bounded noise
    # holds an even number of steps), over the bounded runs' valid windows only, and only
    # when there is a bound to compare with. |err_dt - err_2dt| is about 15x the error of
    # the dt solution (RK4), so it serves as the tolerance with a wide margin.
    diff = np.zeros((T // 2 + 1, R))
    last = max((int(first[r]) for r in range(R) if kinds[r] == "bounded"), default=0)
    if curve is not None and last > 0:
        c_steps = min(steps // 2, last // 2 + 1)
        b_idx = [r for r in range(R) if kinds[r] == "bounded"]
        coarse = simulate(sysm, problem.network, x0[b_idx], xhat0[b_idx], dt=2 * dt,
                          steps=c_steps, noise=noise[: 2 * c_steps: 2, b_idx])
        err_c = torch.linalg.vector_norm(coarse.x - coarse.xhat, dim=-1).numpy()
        with np.errstate(invalid="ignore"):
            diff[: c_steps + 1, b_idx] = np.abs(err[: 2 * c_steps + 1: 2, b_idx] - err_c)
    progress.update("simulation")

    keep = _thin(T)
    runs: list[SimulationRun] = []
    breaches: list[str] = []
    compared = 0
    late_ratio: float | None = None
    for r in range(R):
        k_exit = int(first[r])
        within = kinds[r] == "bounded"
        e_r = err[:, r]
        with np.errstate(invalid="ignore", over="ignore"):
            mse = float(np.mean(e_r ** 2))
        max_ratio, breach, tol = None, False, 0.0
        if curve is not None and within and k_exit > 0:
            w = slice(0, k_exit)
            b_r = curve[r, w]
            d_w = diff[: (k_exit + 1) // 2, r]
            est = float(np.max(d_w)) if d_w.size and np.all(np.isfinite(d_w)) else math.inf
            tol = ATOL * (1.0 + float(np.max(b_r))) + est
            ratio = e_r[w] / (b_r + tol)
            max_ratio = float(np.max(ratio))
            breach = bool(max_ratio > 1.0) or not math.isfinite(max_ratio)
            compared += 1 if k_exit > 1 else 0
            rate = bounds.iss.rate if bounds is not None and bounds.iss is not None else None
            if rate:
                lw = t[w] >= 1.0 / rate
                if lw.any():
                    m = float(np.max(ratio[lw]))
                    late_ratio = m if late_ratio is None else max(late_ratio, m)
            if breach:
                j = int(np.argmax(ratio))
                breaches.append(f"run '{labels[r]}' at t = {t[j]:.4g}: ||e|| = {e_r[j]:.6g} > "
                                f"bound {b_r[j]:.6g} + tolerance {tol:.2g}")
        exit_time = None if k_exit >= T else float(t[k_exit])
        runs.append(SimulationRun(
            label=labels[r], x0=x0[r].tolist(), xhat0=xhat0[r].tolist(), noise=kinds[r],
            within_conditions=within, exit_time=exit_time,
            exit_reason=reasons[r] if exit_time is not None else "stayed within the conditions",
            max_ratio=max_ratio, breach=breach, mse=mse, final_error=float(e_r[-1]),
            t=t[keep].tolist(), error=e_r[keep].tolist(),
            bound=curve[r, keep].tolist() if curve is not None else [],
            x=fine.x[keep, r].tolist(), xhat=fine.xhat[keep, r].tolist(), tolerance=tol))

    exits = [f"'{run.label}' at {run.exit_reason}" for run in runs if run.exit_time is not None]
    exit_text = (f"{len(exits)} of {R} runs left the validity conditions: " + " | ".join(exits)
                 if exits else f"All {R} runs stayed within the validity conditions")
    src_run = next((run for run in runs if run.noise == "gaussian"), None)
    src_text = (f" Source protocol (outside the conditions): MSE {src_run.mse:.4g}."
                if src_run is not None else "")
    vtext = f"bounded noise ||v||_2 = {vbar:g}"
    if bounds is not None and abs(bounds.vbar - settings.noise) > 0:
        vtext += f" (the bound's vbar; settings.noise = {settings.noise:g})"
    seconds = time.perf_counter() - start_time

    if curve is None:
        why = ("no bounds were computed" if bounds is None else
               "no proved error bound (" + (bounds.iss.reason if bounds.iss else
                                            bounds.message) + ")")
        status, msg = Status.SKIPPED, (f"nothing to compare: {why}. Simulated {R} runs with "
                                       f"{vtext}. {exit_text}.{src_text}")
    elif breaches:
        if certified:
            status = Status.ERROR
            msg = ("PROVED certificate breached by simulation: " + "; ".join(breaches)
                   + ". The error left a proved bound inside its validity conditions: this is "
                   "a bug in certify (an unsound bound or prover); do not trust this "
                   "certificate, and please report it.")
        else:
            status = Status.VIOLATED
            msg = ("the error bound fails in simulation inside its conditions: "
                   + "; ".join(breaches) + ". The certificate does not pass (not every input "
                   "of the bound was proved), and this shows that at least one of lam_cert, "
                   "eps_bar, L is wrong for this network.")
    elif compared == 0:
        status = Status.UNKNOWN
        msg = (f"no bounded-noise run stayed within the validity conditions beyond t = 0, so "
               f"nothing was compared. {exit_text}.{src_text}")
    else:
        worst = max((run.max_ratio for run in runs if run.max_ratio is not None), default=0.0)
        status = Status.PASSED  # evidence, not proof
        late = f"; after one time constant 1/(2 lam_cert): {late_ratio:.3g}" \
            if late_ratio is not None else ""
        msg = (f"no breach: in {compared} bounded-noise runs ({vtext}, RK4 dt = {dt:g}) the "
               f"error stayed under the proved bound ({', '.join(names)}) up to each run's "
               f"first exit; largest error/bound {worst:.3g} (1 at t = 0 by construction)"
               f"{late}. {exit_text}.{src_text} Simulation is evidence, not proof.")
    progress.finish("simulation", status.value)
    return SimulationResult(status=status, message=msg, runs=runs, seconds=seconds)


# ----------------------------------------------------------------------------- check protocol

class SimulationCheck(Check):
    """Plant + observer simulated; the error against the proved bound inside its conditions.

    A breach while every input of the bound was proved (the certificate would pass) is a bug
    in certify: the result is ERROR and the check joins the required ones, so the gate never
    passes on it.
    """

    name = "simulation"
    title = "Simulation vs bound"
    result_type = SimulationResult
    reads = ("sim_time", "sim_dt", "sim_initial_conditions", "noise", "seed",
             "allow_unknown")
    needs = ("bounds",)
    uses = ("necessary", "mpdi", "rate", "residual", "lipschitz")

    def run(self, context: Context) -> SimulationResult:
        from certify.certificate import decide_verdict

        bounds = context.result("bounds")
        verdict, _ = decide_verdict(context.results, context.required,
                                    context.settings.allow_unknown)
        certified = verdict == "CERTIFIED" and bounds.status == Status.PROVED
        result = check_simulation(context.problem, bounds, context.settings,
                                  progress=context.progress, certified=certified)
        if result.status == Status.ERROR and self.name not in context.required:
            context.required.append(self.name)  # a breached proof is a bug: never certify
        return result

    def present(self, r: SimulationResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        ratios = [run.max_ratio for run in r.runs if run.max_ratio is not None]
        exits = sum(run.exit_time is not None for run in r.runs)
        breaches = sum(bool(run.breach) for run in r.runs)
        worst = max(ratios) if ratios else None
        numbers = [Quantity("runs", len(r.runs)), Quantity("breaches", breaches),
                   Quantity("exits", exits), Quantity("max error/bound", worst, sig=6)]
        for run in r.runs:
            numbers += [Quantity(f"run {run.label}: max error/bound", run.max_ratio),
                        Quantity(f"run {run.label}: first exit at t =", run.exit_time, "never"),
                        Quantity(f"run {run.label}: exit reason", run.exit_reason)]
        return Presentation(
            sampled=Quantity("max error / bound (valid times)", worst, "no bound to compare"),
            proved=Quantity("breaches / exits from X, Y",
                            f"{breaches} breach{'es' if breaches != 1 else ''}, "
                            f"{exits} of {len(r.runs)} runs exit"),
            setting=(Quantity("runs", len(r.runs)),
                     Quantity("T =", s.get("sim_time"), suffix=" s"),
                     Quantity("dt =", s.get("sim_dt")), Quantity("v\u0304 =", s.get("noise"))),
            numbers=tuple(numbers),
            facts=(Quantity("Status", r.status.value), Quantity("Runs", len(r.runs)),
                   Quantity("Breaches", breaches), Quantity("Runs that exit", exits),
                   Quantity("Largest error / bound", worst, "no bound to compare")))


CHECK = SimulationCheck()
