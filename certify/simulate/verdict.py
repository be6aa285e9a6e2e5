"""The simulation's verdict and its short message, from the table of runs.

Status: PASSED ("no breach seen": evidence, never proof) when some run stayed valid for at
least one time constant of the best bound; UNKNOWN (inconclusive evidence) when every valid
window is shorter, or nothing was compared; VIOLATED when the error left a bound that was
not fully proved; ERROR when it left a PROVED certificate's bound (a bug in this tool);
NOT APPLICABLE when there is no proved bound to compare with (then nothing is simulated:
`not_applicable`). The message is a short
summary; each run's start, window, exit, ratio and peak are in the table of runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from certify.arith.text import upper_text
from certify.results import BoundResult, BoundsResult, SimulationRun, Status
from certify.simulate.horizon import MIN_TIME_CONSTANTS, Horizon


@dataclass
class Summary:
    """The numbers the message and the result's summary fields share."""

    worst: SimulationRun | None  # the run with the largest peak after settling
    peaks: int  # bounded runs with a peak after settling
    long_runs: int  # bounded runs valid for >= MIN_TIME_CONSTANTS time constants
    bounded: int
    text: str  # the peak-vs-bound sentence and the horizon note ("" without a bound)
    note: str = ""  # the horizon note alone


def summarise(runs: list[SimulationRun], bounds: BoundsResult | None,
              best: BoundResult | None, tau: float | None, horizon: Horizon) -> Summary:
    """The worst run after settling (among those valid for `MIN_TIME_CONSTANTS` time
    constants, else among all) and the sentence comparing it with the headline."""
    bounded = [run for run in runs if run.noise == "bounded"]
    with_peak = [run for run in bounded if run.peak_error is not None]
    long = [run for run in bounded if tau and (run.window or 0.0)
            >= MIN_TIME_CONSTANTS * tau * (1 - 1e-9)]
    # a run that leaves the conditions at once shows its start, not what the noise does
    long_ids = {id(run) for run in long}
    pool = [run for run in with_peak if id(run) in long_ids] or with_peak
    worst = max(pool, key=lambda run: run.peak_error) if pool else None  # type: ignore
    parts: list[str] = []
    if best is not None and bounds is not None and bounds.headline is not None:
        T = bounds.settle_time or 0.0
        B = upper_text(bounds.headline)
        if worst is not None:
            parts.append(f"observed peak {worst.peak_error:.3g} ('{worst.label}') vs bound "
                         f"{B} after t >= {upper_text(T, 2)} s: "
                         + _how_far(worst.conservatism))
        elif not horizon.reaches_settle:
            parts.append(f"no run reached t = {upper_text(T, 2)} s, after which ||e|| <= {B} "
                         "is claimed, so no peak was compared with it")
        else:
            parts.append(f"no run stayed valid past t = {upper_text(T, 2)} s, so no peak was "
                         f"compared with the bound {B}")
        parts.append(f"{len(long)} of {len(bounded)} runs valid >= "
                     f"{MIN_TIME_CONSTANTS:g} time constants of {tau:.3g} s")
    if horizon.short:
        parts.append(horizon.short)
    return Summary(worst=worst, peaks=len(with_peak), long_runs=len(long),
                   bounded=len(bounded), text="; ".join(parts), note=horizon.short)


def _how_far(c: float | None) -> str:
    """How far the headline is above the worst peak, conservatism c = B / peak."""
    if c is None or not math.isfinite(c):
        return "the bound is infinitely far from the worst run (no error)"
    if c < 1.0:  # above B, but within the integrator's tolerance (else it is a breach)
        return "the worst run reaches the bound within the integrator's tolerance"
    return f"the bound is {c:.3g}x the worst run"


def not_applicable(bounds: BoundsResult | None) -> tuple[Status, str]:
    """The status and message when there is no proved bound to compare with: nothing is
    simulated then (a run with nothing to compare establishes nothing)."""
    why = ("no bounds were computed" if bounds is None else
           "no proved error bound to compare with (bounds " + bounds.status.value + ": "
           + (bounds.iss.reason if bounds.iss is not None else bounds.message) + ")")
    return Status.NOT_APPLICABLE, f"not applicable: {why}; nothing was simulated."


def verdict(runs: list[SimulationRun], breaches: list[str], certified: bool,
            tau: float | None, late_ratio: float | None, compared: list[SimulationRun],
            summary: Summary) -> tuple[Status, str]:
    """The status and a short summary of runs compared with a proved bound; the details of
    every run are in the runs table. `certified`: the bound's inputs were all proved (the
    certificate passes): a breach is then a bug in certify (ERROR)."""
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
    if not compared:
        return Status.UNKNOWN, (f"inconclusive: no bounded-noise run stayed within the "
                                f"validity conditions beyond t = 0, so nothing was compared. "
                                f"{where}{src_text}")
    worst = max(run.max_ratio for run in compared)  # type: ignore[type-var]
    if tau is not None and max(windows) < tau:
        note = f" ({summary.note})" if summary.note else ""
        return Status.UNKNOWN, (
            f"inconclusive evidence: no breach, but every valid window is shorter than "
            f"one time constant {tau:.3g} s ({span}{note}), so the runs compare almost "
            f"nothing; largest error/bound {worst:.3g}. {where}{src_text}")
    late = (f" ({late_ratio:.3g} after one time constant)" if late_ratio is not None else "")
    return Status.PASSED, (
        f"no breach in {len(compared)} runs (uniform and switching noise): "
        f"{summary.text}. Max error/bound "
        f"{worst:.3g}{late}. {where}{src_text} Evidence, not proof.")
