"""The simulation check's computation (METHOD §3.8): runs integrated, compared, tabulated.

Plant + observer are simulated from the chosen starts under bounded noise of two kinds and
the source's protocol beside (`certify.simulate.batch`), all in one batch
(`certify.simulate.integrate.simulate_doubled`, the bounded runs again at 2 dt for the
integration error), over the horizon of `certify.simulate.horizon`. Each run is valid up to
its first exit from the conditions (`certify.simulate.exits`) and compared there with the
proved bounds (`certify.simulate.compare`); its row in the table of runs keeps a few
samples for the reports (`certify.simulate.samples`); the verdict and message come from the
rows (`certify.simulate.verdict`).
"""

from __future__ import annotations

import time

import numpy as np

from certify.model.problem import Problem
from certify.progress import NullProgress, Progress
from certify.results import BoundsResult, SimulationResult, SimulationRun
from certify.settings import VerifySettings
from certify.simulate.batch import RunBatch, plan_runs, run_count
from certify.simulate.compare import (
    BoundFormulas,
    Comparison,
    PeakTest,
    applicable,
    best_curve,
    compare_run,
    component_bounds,
)
from certify.simulate.exits import first_exit, needs_measured_output
from certify.simulate.horizon import MIN_TIME_CONSTANTS, best_bound, plan_horizon, time_constant
from certify.simulate.integrate import Trajectories, simulate_doubled
from certify.simulate.samples import TIME_DIGITS, keep_samples, series
from certify.simulate.starts import initial_conditions
from certify.simulate.verdict import not_applicable, summarise, verdict


def bound_radius(bounds: BoundsResult | None) -> float | None:
    """The best bound's ultimate radius in the P-norm, W_inf = ultimate / gain (None: no
    bound); Theorem 3 (P = I) has W = ||e||."""
    b = best_bound(bounds)
    if b is None or bounds is None or bounds.ultimate is None:
        return None
    if b.name == "theorem3" or not b.gain:
        return float(bounds.ultimate)
    return float(bounds.ultimate) / float(b.gain)


def simulate_against_bounds(problem: Problem, bounds: BoundsResult | None,
                            settings: VerifySettings, formulas: BoundFormulas, *,
                            progress: Progress | None = None, certified: bool
                            ) -> SimulationResult:
    """Simulate plant + observer; compare the error with the proved bound inside the
    conditions. `formulas`: the bounds' curves; `certified`: whether the bound's inputs were
    all proved (the certificate passes): a breach is then a bug in certify (status ERROR).
    Without an applicable proved bound nothing is simulated (NOT APPLICABLE, no runs)."""
    start_time = time.perf_counter()
    progress = NullProgress() if progress is None else progress
    if not applicable(bounds, formulas):  # nothing to compare a run with: nothing simulated
        status, msg = not_applicable(bounds)
        progress.start("simulation", total=1)
        progress.finish("simulation", status.value)
        return SimulationResult(status=status, message=msg,
                                seconds=time.perf_counter() - start_time, horizon=None)
    assert bounds is not None
    system = problem.system
    P = np.asarray(problem.P, dtype=np.float64)
    horizon = plan_horizon(bounds, settings, runs=run_count(system, settings))
    dt, steps = horizon.dt, horizon.steps
    vbar = float(bounds.vbar)
    measured = needs_measured_output(bounds)
    best = best_bound(bounds)
    progress.start("simulation", total=3)

    ics = initial_conditions(system, settings.sim_initial_conditions, settings.seed, P=P,
                             horizon=steps * dt, vbar=vbar, L_is_local=measured,
                             radius=bound_radius(bounds), need_time=horizon.need)
    progress.update("simulation")
    batch = plan_runs(problem, ics, steps=steps, dt=dt, vbar=vbar, seed=settings.seed)
    e0 = batch.e0
    t_all = np.arange(steps + 1, dtype=np.float64) * dt
    curve = best_curve(bounds, formulas, e0, t_all)  # [R, T]
    assert curve is not None
    b_idx = batch.bounded
    # the bounded runs again at 2 dt in the same batch, for the integration error
    fine, coarse = simulate_doubled(system, problem.network, batch.x0, batch.xhat0, dt=dt,
                                    steps=steps, noise=batch.noise, doubled=b_idx,
                                    doubled_steps=steps // 2, feedback=batch.feedback)
    progress.update("simulation")
    v_norm = np.linalg.norm(fine.v.numpy(), axis=-1)  # [T, R]
    assert np.all(v_norm[:, b_idx] <= vbar), "bounded noise exceeded vbar"
    first, reasons = first_exit(system, fine.x, fine.xhat, fine.v, fine.t, measured)
    diff = doubling_difference(fine, coarse, b_idx)

    tau = time_constant(best)
    headline = bounds.headline if best is not None else None
    comp = component_bounds(bounds) if best is not None else None
    t = fine.t.numpy()
    e_all = (fine.x - fine.xhat).numpy()  # [T, R, n]
    runs: list[SimulationRun] = []
    breaches: list[str] = []
    late_ratio: float | None = None
    compared: list[SimulationRun] = []  # runs compared beyond t = 0
    for r in range(len(batch.labels)):
        within = batch.kinds[r] == "bounded"
        c = Comparison()
        if within:
            peak = (PeakTest(bounds, formulas, best.name, e0[r], float(headline), comp)
                    if best is not None and headline is not None else None)
            c = compare_run(batch.labels[r], t, e_all[:, r], int(first[r]), curve[r],
                            diff[:, r], tau=tau, peak=peak)
            breaches += c.breaches
            if c.late_ratio is not None:
                late_ratio = c.late_ratio if late_ratio is None else max(late_ratio,
                                                                         c.late_ratio)
        row = run_row(batch, r, fine, int(first[r]), reasons[r], c,
                      curve[r] if within else None, v_norm[:, r], tau, headline)
        runs.append(row)
        if c.compared:
            compared.append(row)
    summary = summarise(runs, bounds, best, tau, horizon)
    status, msg = verdict(runs, breaches, certified, tau, late_ratio, compared, summary)
    progress.finish("simulation", status.value)
    worst = summary.worst
    return SimulationResult(
        status=status, message=msg, runs=runs, seconds=time.perf_counter() - start_time,
        time_constant=tau, horizon=horizon.seconds, horizon_extended=horizon.extended,
        horizon_note=horizon.note, bound_name=best.name if best is not None else "",
        headline=headline, peak_error=worst.peak_error if worst is not None else None,
        peak_run=worst.label if worst is not None else "",
        conservatism=worst.conservatism if worst is not None else None,
        long_runs=summary.long_runs, min_time_constants=MIN_TIME_CONSTANTS)


def doubling_difference(fine: Trajectories, coarse: Trajectories | None, rows: list[int]
                        ) -> np.ndarray:
    """||e_dt - e_2dt|| at the even steps [T // 2 + 1, R] for the doubled runs `rows` (zero
    elsewhere): about 15x the dt run's own error (RK4), so it serves as the integration
    tolerance with a wide margin (for the norm and for each component)."""
    T, R = fine.x.shape[0], fine.x.shape[1]
    diff = np.zeros((T // 2 + 1, R))
    if coarse is not None:
        e_c = (coarse.x - coarse.xhat).numpy()
        c_steps = e_c.shape[0] - 1
        e_f = (fine.x[: 2 * c_steps + 1: 2, rows] - fine.xhat[: 2 * c_steps + 1: 2, rows])
        with np.errstate(invalid="ignore"):
            diff[: c_steps + 1, rows] = np.linalg.norm(e_f.numpy() - e_c, axis=-1)
    return diff


def run_row(batch: RunBatch, r: int, fine: Trajectories, k_exit: int, reason: str,
            c: Comparison, curve: np.ndarray | None, v_norm: np.ndarray, tau: float | None,
            headline: float | None) -> SimulationRun:
    """Run r's row in the table of runs, with its kept samples (`keep_samples`)."""
    t = fine.t.numpy()
    T = t.shape[0]
    within = batch.kinds[r] == "bounded"
    e_r = np.linalg.norm((fine.x[:, r] - fine.xhat[:, r]).numpy(), axis=-1)
    with np.errstate(invalid="ignore", over="ignore"):
        mse = float(np.mean(e_r ** 2))
    exit_time = None if k_exit >= T else float(t[k_exit])
    keep = keep_samples(e_r, exit_index=k_exit, worst_index=c.worst)
    window = float(t[-1]) if exit_time is None else exit_time
    peak = c.peak
    return SimulationRun(
        label=batch.labels[r], x0=batch.x0[r].tolist(), xhat0=batch.xhat0[r].tolist(),
        noise=batch.kinds[r], within_conditions=within, exit_time=exit_time,
        exit_reason=reason if exit_time is not None else "stayed within the conditions",
        max_ratio=c.max_ratio, breach=c.breach, mse=mse, final_error=float(e_r[-1]),
        t=series(t[keep], TIME_DIGITS), error=series(e_r[keep]),
        bound=series(curve[keep]) if curve is not None else [],
        x=series(fine.x[keep, r].numpy()), xhat=series(fine.xhat[keep, r].numpy()),
        tolerance=c.tol, start=batch.notes[r], window=window,
        noise_kind=batch.noise_kinds[r],
        max_noise=float(np.max(v_norm)) if within else None,
        time_constants=(window / tau if tau and within else None),
        settle_time=peak.settle, peak_error=peak.error, peak_time=peak.time,
        peak_components=peak.components, bound_at_peak=peak.bound_at,
        bound_after_settling=headline if peak.error is not None else None,
        conservatism=peak.conservatism)
