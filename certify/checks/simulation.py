"""Simulation check (METHOD §3.8): the observed error against the proved bound.

Plant + observer are simulated (one batched RK4 over every run, `certify.simulate.integrate`) with
bounded noise ||v(t)||_2 <= vbar, from starts chosen where the bound's validity conditions can
hold for a useful time (`certify.simulate.starts`: the plant stays in X for long, small initial
errors). For each run the first time a validity condition fails is found (x or xhat leaves X,
h(x) leaves Y, y + v leaves Y when L is local, a non-finite state): its valid window ends
there. Inside the window the error must stay under the tightest applicable proved bound, up
to the integrator's tolerance (estimated per run by a second integration at twice the step,
in the same batch). A breach of a PROVED certificate is a bug in this tool, reported as
ERROR, never as a pass. The source's protocol (Gaussian noise of std 0.15, its initial
conditions) is run beside, labelled as outside the theorem's conditions, for its mean
squared error.

Status: PASSED ("no breach seen": evidence, never proof) when some run stayed valid for at
least one time constant 1/(2 lam_cert); UNKNOWN (inconclusive evidence) when every valid
window is shorter; NOT APPLICABLE when there is no proved bound to compare with (the runs are
still simulated and reported). The message is a short summary; each run's start, window,
exit and ratio are in `runs` (the reports' table of runs).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from certify.checks.base import Check, Context
from certify.checks.bounds import BOUND_NAMES, bound_curve, initial_value, metric_constants
from certify.figuredata import FIGURE_DIGITS, round_list
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.results import BoundsResult, SimulationResult, SimulationRun, Status
from certify.settings import VerifySettings
from certify.simulate.integrate import bounded_noise, gaussian_noise, simulate_doubled
from certify.simulate.starts import InitialConditions, choose_starts, source_initial_condition

#: The source's simulation protocol: white Gaussian measurement noise of this std.
SOURCE_NOISE_STD = 0.15
#: Samples kept per run for reports (the check itself uses every step): a panel of the
#: report's figure is about 330 pixels wide; `keep_samples` chooses which.
MAX_SAMPLES = 150
#: significant digits of the kept times (the series keep `FIGURE_DIGITS`)
TIME_DIGITS = 7
#: Absolute part of the comparison tolerance (on top of the estimated integration error).
ATOL = 1e-9

__all__ = ["InitialConditions", "check_simulation", "initial_conditions",
           "source_initial_condition"]


def bound_radius(bounds: BoundsResult | None, P: np.ndarray) -> float | None:
    """The ultimate radius c/(2 lam) of the best ISS bound in the P-norm (None: no bound)."""
    if bounds is None:
        return None
    lam_min = metric_constants(P)[0]
    biases = [b.bias for b in (bounds.iss, bounds.iss_metric)
              if b is not None and b.applicable and b.bias is not None]
    if not biases or not lam_min > 0:
        return None
    return min(biases) * math.sqrt(lam_min)


def initial_conditions(system: Any, count: int, seed: int, *, P: np.ndarray | None = None,
                       horizon: float = 10.0, vbar: float = 0.0, L_is_local: bool = False,
                       radius: float | None = None) -> InitialConditions:
    """The bounded-noise runs' starts (see `certify.simulate.starts.choose_starts`)."""
    P = np.eye(system.n) if P is None else np.asarray(P, dtype=np.float64)
    return choose_starts(system, P, count, seed, horizon=horizon, vbar=vbar,
                         L_is_local=L_is_local, radius=radius)


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


def keep_samples(error: np.ndarray, *, exit_index: int, worst_index: int | None = None,
                 limit: int = MAX_SAMPLES) -> np.ndarray:
    """The steps a run keeps for the reports: at most `limit` (>= 16) indices into error
    [T], increasing, no repeats.

    Always kept: the first and last step, the last step before the first exit and the exit
    itself, the worst step (`worst_index`: the largest error / bound, so a breach is always
    drawn where it happened), the largest and smallest error and the first non-finite one;
    then, in each of the equal buckets the remaining room allows, the bucket's smallest and
    largest error, so a spike between two kept steps is never hidden (the error is drawn on
    a log scale: its dips matter as much as its peaks).
    """
    T = len(error)
    if T <= limit:
        return np.arange(T)
    finite = np.isfinite(error)
    hi = np.where(finite, error, -np.inf)
    lo = np.where(finite, error, np.inf)
    special = {0, T - 1, int(np.argmax(hi)), int(np.argmin(lo))}
    if exit_index < T:
        special |= {max(exit_index - 1, 0), exit_index}
    if worst_index is not None and 0 <= worst_index < T:
        special.add(int(worst_index))
    if not finite.all():
        special.add(int(np.argmin(finite)))
    buckets = max((limit - len(special)) // 2, 1)
    edges = np.linspace(0, T, buckets + 1).round().astype(np.int64)
    picks = [int(np.argmax(hi[a:b])) + a for a, b in zip(edges[:-1], edges[1:]) if b > a]
    picks += [int(np.argmin(lo[a:b])) + a for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return np.sort(np.fromiter(special | set(picks), dtype=np.int64))


def _series(values: np.ndarray, digits: int = FIGURE_DIGITS) -> list:
    """Kept samples as float lists at figure precision (`certify.figuredata.round_list`)."""
    return round_list(values.tolist(), digits)


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
    radius = bound_radius(bounds, P)
    progress.start("simulation", total=3)

    ics = initial_conditions(sysm, settings.sim_initial_conditions, settings.seed, P=P,
                             horizon=steps * dt, vbar=vbar, L_is_local=L_is_local,
                             radius=radius)
    progress.update("simulation")
    R_b = len(ics.labels)
    src = source_initial_condition(sysm)
    labels, notes = list(ics.labels), list(ics.notes)
    x0, xhat0 = ics.x0, ics.xhat0
    noise = bounded_noise(steps, R_b, p, vbar, dt, seed=settings.seed)
    kinds = ["bounded"] * R_b
    if src is not None:
        labels.append(f"source protocol (Gaussian noise, std {SOURCE_NOISE_STD:g}; outside "
                      "the theorem's conditions)")
        notes.append("the source's x0 and xhat0 with its Gaussian noise")
        x0 = torch.cat([x0, torch.tensor([src[0]], dtype=torch.float64)])
        xhat0 = torch.cat([xhat0, torch.tensor([src[1]], dtype=torch.float64)])
        noise = torch.cat([noise, gaussian_noise(steps, 1, p, SOURCE_NOISE_STD,
                                                 seed=settings.seed + 2)], dim=1)
        kinds.append("gaussian")
    R = len(labels)
    e0 = (x0 - xhat0).numpy()

    # One batched integrator: every run at dt, and (for the integration-error estimate by
    # step doubling) the bounded runs again at 2 dt in the same batch, when there is a bound
    # to compare with. |err_dt - err_2dt| is about 15x the error of the dt solution (RK4),
    # so it serves as the tolerance with a wide margin.
    t_all = torch.arange(steps + 1, dtype=torch.float64).numpy() * dt
    curve, names = _best_bound(bounds, P, e0, t_all)  # [R, T] or None
    b_idx = [r for r in range(R) if kinds[r] == "bounded"]
    fine, coarse = simulate_doubled(sysm, problem.network, x0, xhat0, dt=dt, steps=steps,
                                    noise=noise, doubled=b_idx if curve is not None else None,
                                    doubled_steps=steps // 2)
    progress.update("simulation")
    t = fine.t.numpy()
    T = t.shape[0]
    err = torch.linalg.vector_norm(fine.x - fine.xhat, dim=-1).numpy()  # [T, R]
    first, reasons = _first_exit(problem, fine.x, fine.xhat, fine.v, fine.t, L_is_local)
    diff = np.zeros((T // 2 + 1, R))
    if coarse is not None:
        err_c = torch.linalg.vector_norm(coarse.x - coarse.xhat, dim=-1).numpy()
        c_steps = err_c.shape[0] - 1
        with np.errstate(invalid="ignore"):
            diff[: c_steps + 1, b_idx] = np.abs(err[: 2 * c_steps + 1: 2, b_idx] - err_c)

    rate = bounds.iss.rate if bounds is not None and bounds.iss is not None else None
    tau = 1.0 / rate if rate else None  # one time constant 1/(2 lam_cert)
    runs: list[SimulationRun] = []
    breaches: list[str] = []
    late_ratio: float | None = None
    compared: list[int] = []  # runs compared beyond t = 0
    for r in range(R):
        k_exit = int(first[r])
        within = kinds[r] == "bounded"
        e_r = err[:, r]
        with np.errstate(invalid="ignore", over="ignore"):
            mse = float(np.mean(e_r ** 2))
        max_ratio, breach, tol, worst_k = None, False, 0.0, None
        if curve is not None and within and k_exit > 0:
            w = slice(0, k_exit)
            b_r = curve[r, w]
            d_w = diff[: (k_exit + 1) // 2, r]
            est = float(np.max(d_w)) if d_w.size and np.all(np.isfinite(d_w)) else math.inf
            tol = ATOL * (1.0 + float(np.max(b_r))) + est
            ratio = e_r[w] / (b_r + tol)
            max_ratio = float(np.max(ratio))
            with np.errstate(invalid="ignore"):
                worst_k = int(np.argmax(np.where(np.isnan(ratio), np.inf, ratio)))
            breach = bool(max_ratio > 1.0) or not math.isfinite(max_ratio)
            if k_exit > 1:
                compared.append(r)
            if tau is not None:
                lw = t[w] >= tau
                if lw.any():
                    m = float(np.max(ratio[lw]))
                    late_ratio = m if late_ratio is None else max(late_ratio, m)
            if breach:
                j = int(np.argmax(ratio))
                breaches.append(f"run '{labels[r]}' at t = {t[j]:.4g}: ||e|| = {e_r[j]:.6g} > "
                                f"bound {b_r[j]:.6g} + tolerance {tol:.2g}")
        exit_time = None if k_exit >= T else float(t[k_exit])
        keep = keep_samples(e_r, exit_index=k_exit, worst_index=worst_k)
        runs.append(SimulationRun(
            label=labels[r], x0=x0[r].tolist(), xhat0=xhat0[r].tolist(), noise=kinds[r],
            within_conditions=within, exit_time=exit_time,
            exit_reason=reasons[r] if exit_time is not None else "stayed within the conditions",
            max_ratio=max_ratio, breach=breach, mse=mse, final_error=float(e_r[-1]),
            t=_series(t[keep], TIME_DIGITS), error=_series(e_r[keep]),
            bound=_series(curve[r, keep]) if curve is not None and within else [],
            x=_series(fine.x[keep, r].numpy()), xhat=_series(fine.xhat[keep, r].numpy()),
            tolerance=tol,
            start=notes[r], window=float(t[-1]) if exit_time is None else exit_time))
    status, msg = _verdict(runs, bounds, curve is not None, breaches, certified, tau,
                           late_ratio, [runs[r] for r in compared])
    progress.finish("simulation", status.value)
    return SimulationResult(status=status, message=msg, runs=runs,
                            seconds=time.perf_counter() - start_time, time_constant=tau)


def _verdict(runs: list[SimulationRun], bounds: BoundsResult | None, have_bound: bool,
             breaches: list[str], certified: bool, tau: float | None,
             late_ratio: float | None, compared: list[SimulationRun]
             ) -> tuple[Status, str]:
    """The status and a short summary; the details of every run are in the runs table."""
    bounded = [run for run in runs if run.noise == "bounded"]
    exits = sum(run.exit_time is not None for run in runs)
    windows = [run.window or 0.0 for run in bounded]
    src_run = next((run for run in runs if run.noise == "gaussian"), None)
    src_text = (f" Source protocol (outside the conditions): MSE {src_run.mse:.4g}."
                if src_run is not None else "")
    where = (f"{exits} of {len(runs)} runs left the validity conditions (see the table of "
             "runs).")
    if not have_bound:
        why = ("no bounds were computed" if bounds is None else
               "no proved error bound to compare with (bounds " + bounds.status.value + ": "
               + (bounds.iss.reason if bounds.iss is not None else bounds.message) + ")")
        return Status.NOT_APPLICABLE, f"not applicable: {why}. {where}{src_text}"
    if breaches:
        if certified:
            return Status.ERROR, (
                "PROVED certificate breached by simulation: " + "; ".join(breaches)
                + ". The error left a proved bound inside its validity conditions: this is "
                "a bug in certify (an unsound bound or prover); do not trust this "
                "certificate, and please report it.")
        return Status.VIOLATED, (
            "the error bound fails in simulation inside its conditions: " + "; ".join(breaches)
            + ". The certificate does not pass (not every input of the bound was proved), and "
            "this shows that at least one of lam_cert, eps_bar, L is wrong for this network.")
    span = (f"valid windows {min(windows):.3g}\u2013{max(windows):.3g} s" if windows
            else "no bounded runs")
    tau_text = f"one time constant 1/(2 lam_cert) = {tau:.3g} s" if tau else ""
    if not compared:
        return Status.UNKNOWN, (f"inconclusive: no bounded-noise run stayed within the "
                                f"validity conditions beyond t = 0, so nothing was compared. "
                                f"{where}{src_text}")
    worst = max(run.max_ratio for run in compared)  # type: ignore[type-var]
    if tau is not None and max(windows) < tau:
        return Status.UNKNOWN, (
            f"inconclusive evidence: no breach, but every valid window is shorter than "
            f"{tau_text} ({span}), so the runs compare almost nothing; largest error/bound "
            f"{worst:.3g}. {where}{src_text}")
    late = (f"; {late_ratio:.3g} after one time constant" if late_ratio is not None else "")
    return Status.PASSED, (
        f"no breach in {len(compared)} bounded-noise runs: largest error/bound {worst:.3g} "
        f"(1 at t = 0 by construction{late}); {span}, {tau_text}. {where}{src_text} "
        "Evidence, not proof.")


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
        from certify.results import decide_verdict

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
        windows = [run.window for run in r.runs
                   if run.noise == "bounded" and run.window is not None]
        longest = max(windows) if windows else None
        worst = max(ratios) if ratios else None
        numbers = [Quantity("runs", len(r.runs)), Quantity("breaches", breaches),
                   Quantity("exits", exits), Quantity("max error/bound", worst, sig=6),
                   Quantity("longest valid window (s)", longest, sig=4),
                   Quantity("one time constant 1/(2 lam_cert) (s)", r.time_constant, "no bound",
                            sig=4)]
        for run in r.runs:
            numbers += [Quantity(f"run {run.label}: valid window (s)", run.window),
                        Quantity(f"run {run.label}: max error/bound", run.max_ratio),
                        Quantity(f"run {run.label}: exit", run.exit_reason)]
        plural = "es" if breaches != 1 else ""
        return Presentation(
            sampled=Quantity("max error / bound (valid times)", worst, "no bound to compare"),
            proved=Quantity("breaches; longest valid window",
                            None if not ratios else
                            f"{breaches} breach{plural}; "
                            + (f"window {longest:.3g} s" if longest is not None else "no window")
                            + (f" (\u03c4 = {r.time_constant:.3g} s)"
                               if r.time_constant is not None else ""),
                            "no bound to compare with"),
            setting=(Quantity("runs", len(r.runs)),
                     Quantity("T =", s.get("sim_time"), suffix=" s"),
                     Quantity("dt =", s.get("sim_dt")), Quantity("v\u0304 =", s.get("noise"))),
            numbers=tuple(numbers),
            facts=(Quantity("Status", r.status.value), Quantity("Runs", len(r.runs)),
                   Quantity("Breaches", breaches), Quantity("Runs that exit", exits),
                   Quantity("Largest error / bound", worst, "no bound to compare"),
                   Quantity("Longest valid window", longest, "none", suffix=" s"),
                   Quantity("One time constant 1/(2\u03bb_cert)", r.time_constant,
                            "no bound", suffix=" s")))


CHECK = SimulationCheck()
