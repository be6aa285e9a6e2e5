"""Simulation check (METHOD §3.8): the observed error against the proved bound.

The computation is `certify.simulate` (`certify.simulate.evidence`: the runs, the batched
integration, the comparison, the table of runs and the verdict); this module is the check:
it hands over the proved bounds' formulas (`certify.checks.bounds`) and says whether the
certificate passes (then a breach is a bug in certify, ERROR, and the check becomes
required), and presents the result.

Status: PASSED ("no breach seen": evidence, never proof) when some run stayed valid for at
least one time constant of the best bound; UNKNOWN (inconclusive evidence) when every valid
window is shorter; NOT APPLICABLE when there is no proved bound to compare with (then nothing
is simulated: a run with nothing to compare establishes nothing). Each run's start, window,
exit, ratio and peak are in the result's `runs` (the reports' table of runs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from certify.checks.base import Check, Context
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import Progress
from certify.prove.error_bound import BOUND_NAMES, bound_curve, initial_value, settle_time
from certify.results import BoundsResult, SimulationResult, Status
from certify.settings import VerifySettings
from certify.simulate.evidence import simulate_against_bounds
from certify.simulate.samples import MAX_SAMPLES, keep_samples

#: MAX_SAMPLES and keep_samples live in certify.simulate.samples (named here for old callers)
__all__ = ["MAX_SAMPLES", "check_simulation", "keep_samples"]


@dataclass
class ProvedFormulas:
    """The proved bounds' curves for `certify.simulate.compare.BoundFormulas`: the functions
    of `certify.checks.bounds` over `bounds` (None: no bounds, never asked), metric P."""

    bounds: BoundsResult | None
    P: np.ndarray
    names: tuple[str, ...] = BOUND_NAMES

    def start(self, which: str, e0: np.ndarray) -> np.ndarray:
        return initial_value(which, e0, self.P)

    def curve(self, which: str, start: float | np.ndarray, t: np.ndarray) -> np.ndarray:
        assert self.bounds is not None
        return bound_curve(self.bounds, which, start, t)

    def settle(self, which: str, start: float, level: float) -> float:
        assert self.bounds is not None
        return settle_time(self.bounds, which, start, level)


def check_simulation(problem: Problem, bounds: BoundsResult | None,
                     settings: VerifySettings, *, progress: Progress | None = None,
                     certified: bool) -> SimulationResult:
    """Simulate plant + observer; compare the error with the proved bound inside the conditions.

    `certified`: whether the bound's inputs were all proved (the certificate passes). Then a
    breach is a bug in certify: status ERROR with a loud message.
    """
    formulas = ProvedFormulas(bounds, np.asarray(problem.P, dtype=np.float64))
    return simulate_against_bounds(problem, bounds, settings, formulas, progress=progress,
                                   certified=certified)


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
        if not r.runs:  # nothing simulated (no proved bound to compare with)
            none = Quantity("Runs", 0, suffix=" (nothing simulated)")
            return Presentation(
                sampled=Quantity("max error / bound (valid times)", None,
                                 "no bound to compare"),
                proved=Quantity("breaches; longest valid window", None,
                                "no bound to compare with"),
                setting=(none,), numbers=(Quantity("runs", 0),),
                facts=(Quantity("Status", r.status.value), none))
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
