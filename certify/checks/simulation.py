"""Simulation check (METHOD §3.8): the observed error against the proved bound.

Plant + observer are simulated (one batched RK4 over every run, `certify.simulate.integrate`)
with bounded noise ||v(t)||_2 <= vbar of two kinds from every start: uniform (random
directions of norm vbar, held a few steps) and switching (worst-case-like: chosen from the
states to push the error up, `certify.simulate.noise`). The starts are chosen where the
bound's validity conditions can hold for at least `MIN_TIME_CONSTANTS` time constants of the
best bound (`certify.simulate.starts`: the plant stays in X that long with room, small
initial errors); when `sim_time` is left at its default and that is longer, the horizon is
extended (`plan_horizon`, said in the message). For each run the first time a validity
condition fails is found (x or xhat leaves X, h(x) leaves Y, y + v leaves Y when L is local
or the dissipation bound applies, a non-finite state): its valid window ends there.

Inside the window the error must stay under the tightest applicable proved bound (any of
`BOUND_NAMES`), up to the integrator's tolerance (estimated per run by a second
integration at twice the step, in the same batch). After the headline's settling time T
(when the best bound from the worst start in X falls to the headline B = 1.1 x the ultimate
value: the claim "||e|| <= B after t >= T" users read) the peak of ||e|| must stay under B
and each |e_i| under its per-component bound; the peak, B and the ratio B / peak (how
conservative the certificate is on that run) are reported per run and for the worst run.
A breach of a PROVED certificate is a bug in this tool, reported as
ERROR, never as a pass. The source's protocol (Gaussian noise of std 0.15, its initial
conditions) is run beside, labelled as outside the theorem's conditions, for its mean
squared error.

Status: PASSED ("no breach seen": evidence, never proof) when some run stayed valid for at
least one time constant of the best bound; UNKNOWN (inconclusive evidence) when every valid
window is shorter; NOT APPLICABLE when there is no proved bound to compare with (the runs are
still simulated and reported). The message is a short summary; each run's start, window,
exit, ratio and peak are in `runs` (the reports' table of runs).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.arith.text import upper_text
from certify.checks.base import Check, Context
from certify.figuredata import FIGURE_DIGITS, round_list
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.prove.error_bound import BOUND_NAMES, bound_curve, initial_value, settle_time
from certify.results import BoundResult, BoundsResult, SimulationResult, SimulationRun, Status
from certify.settings import DEFAULT_SIM_TIME, VerifySettings
from certify.simulate.integrate import bounded_noise, gaussian_noise, simulate_doubled
from certify.simulate.noise import SwitchingNoise
from certify.simulate.starts import (
    InitialConditions,
    choose_starts,
    source_initial_condition,
)

#: The source's simulation protocol: white Gaussian measurement noise of this std.
SOURCE_NOISE_STD = 0.15
#: Samples kept per run for reports (the check itself uses every step): a panel of the
#: report's figure is about 330 pixels wide; `keep_samples` chooses which.
MAX_SAMPLES = 150
#: significant digits of the kept times (the series keep `FIGURE_DIGITS`)
TIME_DIGITS = 7
#: Absolute part of the comparison tolerance (on top of the estimated integration error).
ATOL = 1e-9
#: The bounded noise kinds every start is run with: random directions of norm vbar held a
#: few steps (`certify.simulate.integrate.bounded_noise`), and worst-case-like noise chosen
#: from the state (`certify.simulate.noise.SwitchingNoise`)
NOISE_KINDS = ("uniform", "switching")
#: runs should stay valid this many time constants of the best bound (the horizon is
#: extended for it when sim_time is not set)
MIN_TIME_CONSTANTS = 5.0
#: time constants the automatic horizon keeps after the latest settling time of a start
AFTER_SETTLING = 2.0
#: the automatic horizon never exceeds this many steps of sim_dt
MAX_AUTO_STEPS = 50_000

__all__ = ["InitialConditions", "check_simulation", "initial_conditions",
           "source_initial_condition"]


def time_constant(b: BoundResult | None) -> float | None:
    """The time constant of a bound's approach to its ultimate value, in seconds (None: no
    bound). The ISS bounds and Theorem 3 decay as e^(-rate t): 1/rate; the dissipation
    bound is the square root of a quantity that decays as e^(-alpha t) (rate = alpha), so
    its distance to the ultimate value shrinks as e^(-alpha t / 2): 2/alpha."""
    if b is None or not b.applicable or not b.rate or not b.rate > 0:
        return None
    return (2.0 if b.name == "dissipation" else 1.0) / float(b.rate)


def best_bound(bounds: BoundsResult | None) -> BoundResult | None:
    """The bound the headline comes from (`BoundsResult.best`), None when there is none."""
    if bounds is None or not bounds.best or bounds.ultimate is None:
        return None
    b = getattr(bounds, bounds.best, None)
    return b if b is not None and b.applicable else None


def needs_measured_output(bounds: BoundsResult | None) -> bool:
    """Whether condition (d), y + v in Y, applies: L is a local bound, or the dissipation
    inequality (proved over X x Y only) is among the applicable bounds."""
    if bounds is None:
        return False
    joint = bounds.dissipation
    return bool(bounds.L_is_local or (joint is not None and joint.applicable))


def bound_radius(bounds: BoundsResult | None, P: np.ndarray) -> float | None:
    """The best bound's ultimate radius in the P-norm, W_inf = ultimate / gain (None: no
    bound); Theorem 3 (P = I) has W = ||e||."""
    b = best_bound(bounds)
    if b is None or bounds is None or bounds.ultimate is None:
        return None
    if b.name == "theorem3" or not b.gain:
        return float(bounds.ultimate)
    return float(bounds.ultimate) / float(b.gain)


def initial_conditions(system: Any, count: int, seed: int, *, P: np.ndarray | None = None,
                       horizon: float = 10.0, vbar: float = 0.0, L_is_local: bool = False,
                       radius: float | None = None, need_time: float | None = None
                       ) -> InitialConditions:
    """The bounded-noise runs' starts (see `certify.simulate.starts.choose_starts`)."""
    P = np.eye(system.n) if P is None else np.asarray(P, dtype=np.float64)
    return choose_starts(system, P, count, seed, horizon=horizon, vbar=vbar,
                         L_is_local=L_is_local, radius=radius, need_time=need_time)


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
    if not curves:
        return None, []
    return np.minimum.reduce(curves), names


@dataclass
class Horizon:
    """How long the runs are: `steps` of `dt` (even), and in words why (empty: as set)."""

    steps: int
    dt: float
    extended: bool = False
    note: str = ""
    need: float | None = None  # how long a run should stay valid (s; None: no bound)
    short: str = ""  # the note in a few words, for the check's message

    @property
    def seconds(self) -> float:
        return self.steps * self.dt


def plan_horizon(bounds: BoundsResult | None, settings: VerifySettings) -> Horizon:
    """The simulated horizon: `sim_time`, or, when `sim_time` is left at its default and the
    best bound is slow, long enough that a run can stay valid for `MIN_TIME_CONSTANTS` time
    constants and still run `AFTER_SETTLING` of them after the headline's settling time T
    (`BoundsResult.settle_time`), capped at `MAX_AUTO_STEPS` steps. A `sim_time` the user
    set (any number, `DEFAULT_SIM_TIME` included) is kept as set (the note says when it is
    shorter than that); None is "not set": `DEFAULT_SIM_TIME`, extended as needed."""
    dt = float(settings.sim_dt)

    def even_steps(seconds: float) -> int:
        k = max(2, int(math.ceil(seconds / dt - 1e-9)))
        return k + k % 2

    chosen = settings.sim_time is not None
    base = float(settings.sim_time) if chosen else DEFAULT_SIM_TIME
    steps = even_steps(base)
    b = best_bound(bounds)
    tau = time_constant(b)
    if b is None or tau is None or bounds is None or bounds.headline is None:
        return Horizon(steps, dt)
    settle = float(bounds.settle_time) if bounds.settle_time is not None else 0.0
    need = max(MIN_TIME_CONSTANTS * tau, settle + AFTER_SETTLING * tau)
    if not math.isfinite(need):
        return Horizon(steps, dt, need=MIN_TIME_CONSTANTS * tau)
    if need <= steps * dt:
        return Horizon(steps, dt, need=need)
    why = (f"{MIN_TIME_CONSTANTS:g} time constants of the {b.name} bound ({tau:.3g} s each)"
           f", {AFTER_SETTLING:g} of them after the settling time T = {settle:.3g} s")
    if chosen:
        return Horizon(steps, dt, need=need,
                       short=f"sim_time {base:g} s < the {need:.3g} s needed",
                       note=f"the horizon sim_time = {base:g} s is shorter "
                            f"than {need:.3g} s ({why})")
    want = even_steps(need)
    capped = want > MAX_AUTO_STEPS
    steps = min(want, MAX_AUTO_STEPS - MAX_AUTO_STEPS % 2)
    cap = f" (capped at {MAX_AUTO_STEPS} steps of {dt:g} s)" if capped else ""
    return Horizon(steps, dt, extended=True, need=need,
                   short=f"horizon extended from {base:g} s to "
                         f"{steps * dt:.4g} s{cap} (sim_time was not set)",
                   note=f"horizon extended from {base:g} s to "
                        f"{steps * dt:.4g} s for {why}; sim_time was not set{cap}")


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
    horizon = plan_horizon(bounds, settings)
    dt, steps = horizon.dt, horizon.steps
    vbar = float(bounds.vbar) if bounds is not None else float(settings.noise)
    measured = needs_measured_output(bounds)
    radius = bound_radius(bounds, P)
    best = best_bound(bounds)
    progress.start("simulation", total=3)

    ics = initial_conditions(sysm, settings.sim_initial_conditions, settings.seed, P=P,
                             horizon=steps * dt, vbar=vbar, L_is_local=measured,
                             radius=radius, need_time=horizon.need)
    progress.update("simulation")
    S = len(ics.labels)
    # every start under each bounded noise kind, side by side: (start 1, uniform), (start 1,
    # switching), (start 2, uniform), ...
    labels, notes, kinds, noise_kinds = [], [], [], []
    for i in range(S):
        for kind in NOISE_KINDS:
            labels.append(f"{ics.labels[i]}, {kind} noise")
            notes.append(ics.notes[i])
            kinds.append("bounded")
            noise_kinds.append(kind)
    pick = torch.arange(S).repeat_interleave(len(NOISE_KINDS))
    x0, xhat0 = ics.x0[pick], ics.xhat0[pick]
    R_b = len(labels)
    noise = torch.zeros(steps, R_b, p, dtype=torch.float64)
    uni = [r for r in range(R_b) if noise_kinds[r] == "uniform"]
    sw = [r for r in range(R_b) if noise_kinds[r] == "switching"]
    noise[:, uni] = bounded_noise(steps, len(uni), p, vbar, dt, seed=settings.seed)
    feedback = SwitchingNoise(sysm, problem.network, P, vbar, sw, dt=dt,
                              seed=settings.seed + 3, max_window=steps * dt / 4)
    src = source_initial_condition(sysm)
    if src is not None:
        labels.append(f"source protocol (Gaussian noise, std {SOURCE_NOISE_STD:g}; outside "
                      "the theorem's conditions)")
        notes.append("the source's x0 and xhat0 with its Gaussian noise")
        x0 = torch.cat([x0, torch.tensor([src[0]], dtype=torch.float64)])
        xhat0 = torch.cat([xhat0, torch.tensor([src[1]], dtype=torch.float64)])
        noise = torch.cat([noise, gaussian_noise(steps, 1, p, SOURCE_NOISE_STD,
                                                 seed=settings.seed + 2)], dim=1)
        kinds.append("gaussian")
        noise_kinds.append("gaussian")
    R = len(labels)
    e0 = (x0 - xhat0).numpy()

    # One batched integrator: every run at dt, and (for the integration-error estimate by
    # step doubling) the bounded runs again at 2 dt in the same batch, when there is a bound
    # to compare with. ||e_dt - e_2dt|| is about 15x the error of the dt solution (RK4), so
    # it serves as the tolerance with a wide margin (for the norm and for each component).
    t_all = np.arange(steps + 1, dtype=np.float64) * dt
    curve, names = _best_bound(bounds, P, e0, t_all)  # [R, T] or None
    b_idx = [r for r in range(R) if kinds[r] == "bounded"]
    fine, coarse = simulate_doubled(sysm, problem.network, x0, xhat0, dt=dt, steps=steps,
                                    noise=noise, doubled=b_idx if curve is not None else None,
                                    doubled_steps=steps // 2,
                                    feedback=feedback if sw else None)
    progress.update("simulation")
    t = fine.t.numpy()
    T = t.shape[0]
    e_all = (fine.x - fine.xhat).numpy()  # [T, R, n]
    err = np.linalg.norm(e_all, axis=-1)  # [T, R]
    v_norm = np.linalg.norm(fine.v.numpy(), axis=-1)  # [T, R]
    assert np.all(v_norm[:, b_idx] <= vbar), "bounded noise exceeded vbar"
    first, reasons = _first_exit(problem, fine.x, fine.xhat, fine.v, fine.t, measured)
    diff = np.zeros((T // 2 + 1, R))
    if coarse is not None:
        e_c = (coarse.x - coarse.xhat).numpy()
        c_steps = e_c.shape[0] - 1
        with np.errstate(invalid="ignore"):
            diff[: c_steps + 1, b_idx] = np.linalg.norm(
                e_all[: 2 * c_steps + 1: 2, b_idx] - e_c, axis=-1)

    tau = time_constant(best)
    headline = bounds.headline if best is not None and bounds is not None else None
    comp = _component_bounds(bounds) if best is not None else None
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
        peak = Peak()
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
                j = worst_k
                breaches.append(f"run '{labels[r]}' at t = {t[j]:.4g}: ||e|| = {e_r[j]:.6g} > "
                                f"bound {b_r[j]:.6g} + tolerance {tol:.2g}")
            if best is not None and headline is not None and bounds is not None:
                peak = _peak_after_settling(bounds, best.name, P, e0[r], t, e_all[:, r],
                                            k_exit, float(headline), comp, tol)
                if peak.breach:
                    breach = True
                    breaches.append(f"run '{labels[r]}': {peak.breach}")
        exit_time = None if k_exit >= T else float(t[k_exit])
        keep = keep_samples(e_r, exit_index=k_exit, worst_index=worst_k)
        window = float(t[-1]) if exit_time is None else exit_time
        runs.append(SimulationRun(
            label=labels[r], x0=x0[r].tolist(), xhat0=xhat0[r].tolist(), noise=kinds[r],
            within_conditions=within, exit_time=exit_time,
            exit_reason=reasons[r] if exit_time is not None else "stayed within the conditions",
            max_ratio=max_ratio, breach=breach, mse=mse, final_error=float(e_r[-1]),
            t=_series(t[keep], TIME_DIGITS), error=_series(e_r[keep]),
            bound=_series(curve[r, keep]) if curve is not None and within else [],
            x=_series(fine.x[keep, r].numpy()), xhat=_series(fine.xhat[keep, r].numpy()),
            tolerance=tol,
            start=notes[r], window=window, noise_kind=noise_kinds[r],
            max_noise=float(np.max(v_norm[:, r])) if within else None,
            time_constants=(window / tau if tau and within else None),
            settle_time=peak.settle, peak_error=peak.error, peak_time=peak.time,
            peak_components=peak.components, bound_at_peak=peak.bound_at,
            bound_after_settling=headline if peak.error is not None else None,
            conservatism=peak.conservatism))
    summary = _summary(runs, bounds, best, tau, horizon)
    status, msg = _verdict(runs, bounds, curve is not None, breaches, certified, tau,
                           late_ratio, [runs[r] for r in compared], summary)
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


def _component_bounds(bounds: BoundsResult | None) -> np.ndarray | None:
    """The headline's bounds on |e_i| after the settling time: per_component[i] * headline /
    ultimate (`BoundsResult.per_component`), None when there are none."""
    if (bounds is None or bounds.per_component is None or bounds.ultimate is None
            or bounds.headline is None):
        return None
    pc = np.asarray(bounds.per_component, dtype=np.float64)
    if bounds.ultimate > 0:
        return pc * (float(bounds.headline) / float(bounds.ultimate)) * (1.0 + 1e-12)
    return pc


@dataclass
class Peak:
    """A run's observed peak after its own settling time (see `_peak_after_settling`)."""

    settle: float | None = None
    error: float | None = None
    time: float | None = None
    components: list[float] = field(default_factory=list)
    bound_at: float | None = None
    conservatism: float | None = None
    breach: str = ""


def _peak_after_settling(bounds: BoundsResult, which: str, P: np.ndarray, e0: np.ndarray,
                         t: np.ndarray, e: np.ndarray, k_exit: int, headline: float,
                         comp: np.ndarray | None, tol: float) -> Peak:
    """The peak of ||e|| (and of each |e_i|) over [settle, first exit) of one run, e [T, n].

    settle: the headline's settling time T (`BoundsResult.settle_time`: the worst start in X
    is within the headline value by then; a run's own curve of the best bound, `which`, from
    its start value, gets there no later), or that own time when T is not recorded. After it
    the certificate says ||e|| <= headline and |e_i| <= comp[i], the claim users read
    ("||e|| <= B after t >= T"), so that is what is tested; the transient of the start is
    mostly over by then, and the peak is what the noise holds the error at. conservatism =
    headline / peak. A peak above the headline (or a component above its bound) by more
    than `tol` is a breach, in words.
    """
    own = settle_time(bounds, which, float(initial_value(which, e0, P)), headline)
    settle = own if bounds.settle_time is None else max(own, float(bounds.settle_time))
    out = Peak(settle=settle)
    if not math.isfinite(settle):
        return out
    k0 = int(np.searchsorted(t, settle, side="left"))
    if k0 >= k_exit:
        return out
    seg = e[k0:k_exit]
    norms = np.linalg.norm(seg, axis=-1)
    j = int(np.argmax(np.where(np.isnan(norms), np.inf, norms)))
    out.error = float(norms[j])
    out.time = float(t[k0 + j])
    out.components = np.max(np.abs(seg), axis=0).tolist()
    out.bound_at = float(bound_curve(bounds, which, float(initial_value(which, e0, P)),
                                     np.array([out.time]))[0])
    out.conservatism = headline / out.error if out.error > 0 else math.inf
    if not out.error <= headline + tol:
        out.breach = (f"after the settling time {settle:.4g} s, ||e|| = {out.error:.6g} at "
                      f"t = {out.time:.4g} > the headline bound {headline:.6g} + tolerance "
                      f"{tol:.2g}")
    elif comp is not None:
        over = [i for i in range(len(comp)) if not out.components[i] <= comp[i] + tol]
        if over:
            i = over[0]
            out.breach = (f"after the settling time {settle:.4g} s, |e_{i + 1}| reached "
                          f"{out.components[i]:.6g} > its bound {comp[i]:.6g} + tolerance "
                          f"{tol:.2g}")
    return out


@dataclass
class Summary:
    """The numbers the message and the result's summary fields share."""

    worst: SimulationRun | None  # the run with the largest peak after settling
    peaks: int  # bounded runs with a peak after settling
    long_runs: int  # bounded runs valid for >= MIN_TIME_CONSTANTS time constants
    bounded: int
    text: str  # the peak-vs-bound sentence and the horizon note ("" without a bound)
    note: str = ""  # the horizon note alone


def _summary(runs: list[SimulationRun], bounds: BoundsResult | None,
             best: BoundResult | None, tau: float | None, horizon: Horizon) -> Summary:
    bounded = [run for run in runs if run.noise == "bounded"]
    with_peak = [run for run in bounded if run.peak_error is not None]
    long = [run for run in bounded if tau and (run.window or 0.0)
            >= MIN_TIME_CONSTANTS * tau * (1 - 1e-9)]
    # the worst run among those valid for five time constants (a run that leaves the
    # conditions at once shows its start, not what the noise does), else among all
    long_ids = {id(run) for run in long}
    pool = [run for run in with_peak if id(run) in long_ids] or with_peak
    worst = max(pool, key=lambda run: run.peak_error) if pool else None  # type: ignore
    long_runs = len(long)
    parts: list[str] = []
    if best is not None and bounds is not None and bounds.headline is not None:
        T = bounds.settle_time or 0.0
        if worst is not None:
            c = worst.conservatism
            parts.append(f"observed peak {worst.peak_error:.3g} ('{worst.label}') vs bound "
                         f"{upper_text(bounds.headline)} after t >= {upper_text(T, 2)} s: the "
                         "bound is "
                         + (f"{c:.3g}x the worst run" if c is not None and math.isfinite(c)
                            else "infinitely far from the worst run (no error)"))
        else:
            parts.append(f"no run stayed valid past t = {T:.3g} s, so no peak was compared "
                         f"with the bound {bounds.headline:.3g}")
        parts.append(f"{long_runs} of {len(bounded)} runs valid >= "
                     f"{MIN_TIME_CONSTANTS:g} time constants of {tau:.3g} s")
    if horizon.short:
        parts.append(horizon.short)
    return Summary(worst=worst, peaks=len(with_peak), long_runs=long_runs,
                   bounded=len(bounded), text="; ".join(parts), note=horizon.short)


def _verdict(runs: list[SimulationRun], bounds: BoundsResult | None, have_bound: bool,
             breaches: list[str], certified: bool, tau: float | None,
             late_ratio: float | None, compared: list[SimulationRun], summary: Summary
             ) -> tuple[Status, str]:
    """The status and a short summary; the details of every run are in the runs table."""
    bounded = [run for run in runs if run.noise == "bounded"]
    exits = sum(run.exit_time is not None for run in runs)
    windows = [run.window or 0.0 for run in bounded]
    src_run = next((run for run in runs if run.noise == "gaussian"), None)
    src_text = (f" Source protocol (outside the conditions): MSE {src_run.mse:.4g}."
                if src_run is not None else "")
    others = len(runs) - len(bounded)
    counted = (f"{len(runs)} runs ({len(bounded)} with bounded noise, {others} with the "
               "source's Gaussian noise)" if bounded and others else f"{len(runs)} runs")
    where = f"{exits} of {counted} left the validity conditions (see the table of runs)."
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
    tau_text = f"one time constant {tau:.3g} s" if tau else ""
    if not compared:
        return Status.UNKNOWN, (f"inconclusive: no bounded-noise run stayed within the "
                                f"validity conditions beyond t = 0, so nothing was compared. "
                                f"{where}{src_text}")
    worst = max(run.max_ratio for run in compared)  # type: ignore[type-var]
    if tau is not None and max(windows) < tau:
        note = f" ({summary.note})" if summary.note else ""
        return Status.UNKNOWN, (
            f"inconclusive evidence: no breach, but every valid window is shorter than "
            f"{tau_text} ({span}{note}), so the runs compare almost nothing; largest "
            f"error/bound {worst:.3g}. {where}{src_text}")
    late = (f" ({late_ratio:.3g} after one time constant)" if late_ratio is not None else "")
    return Status.PASSED, (
        f"no breach in {len(compared)} runs (uniform and switching noise): "
        f"{summary.text}. Max error/bound "
        f"{worst:.3g}{late}. {where}{src_text} Evidence, not proof.")


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
                   Quantity("one time constant of the bound (s)", r.time_constant, "no bound",
                            sig=4),
                   Quantity("horizon (s)", r.horizon, "not recorded", sig=4),
                   Quantity("bound after the settling time (headline)", r.headline,
                            "no bound", sig=6),
                   Quantity("worst observed peak after the settling time", r.peak_error,
                            "no run settled", sig=6),
                   Quantity("bound / worst peak", r.conservatism, "no run settled", sig=4),
                   Quantity(f"runs valid >= {r.min_time_constants:g} time constants",
                            r.long_runs)]
        for run in r.runs:
            numbers += [Quantity(f"run {run.label}: valid window (s)", run.window),
                        Quantity(f"run {run.label}: max error/bound", run.max_ratio),
                        Quantity(f"run {run.label}: peak after settling", run.peak_error),
                        Quantity(f"run {run.label}: bound / peak", run.conservatism),
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
                     Quantity("T =", r.horizon if r.horizon is not None
                              else s.get("sim_time"), suffix=" s"),
                     Quantity("dt =", s.get("sim_dt")), Quantity("v\u0304 =", s.get("noise"))),
            numbers=tuple(numbers),
            facts=(Quantity("Status", r.status.value), Quantity("Runs", len(r.runs)),
                   Quantity("Breaches", breaches), Quantity("Runs that exit", exits),
                   Quantity("Largest error / bound", worst, "no bound to compare"),
                   Quantity("Longest valid window", longest, "none", suffix=" s"),
                   Quantity("One time constant of the bound", r.time_constant,
                            "no bound", suffix=" s"),
                   Quantity("Worst observed peak after the settling time", r.peak_error,
                            "no run settled"),
                   Quantity("Bound there (headline)", r.headline, "no bound"),
                   Quantity("Bound / worst peak", r.conservatism, "no run settled",
                            suffix="x"),
                   Quantity("Horizon", r.horizon, "not recorded", suffix=" s")))


CHECK = SimulationCheck()
