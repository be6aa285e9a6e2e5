"""How long the simulation runs: the horizon, from the settings and the proved bound.

A run tests the bound best when it stays valid for `MIN_TIME_CONSTANTS` time constants of
the best bound and still runs `AFTER_SETTLING` of them after the headline's settling time T
(`BoundsResult.settle_time`: "||e|| <= B after t >= T" is the claim users read). When
`sim_time` is not set the horizon is extended for that, within a cap on the *work*,
`MAX_WORK` run-steps (steps times the runs integrated side by side), never in seconds alone:
a settling time of hours never asks for hours of integration. When T lies beyond the cap,
the horizon is extended only as far as the time constants ask (the runs cannot reach T
anyway) and the note says that the runs end before T; the bound's transient curve, which
holds at every t, is still compared. A `sim_time` the user set is kept as set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from certify.arith.text import upper_text
from certify.results import BoundResult, BoundsResult
from certify.settings import DEFAULT_SIM_TIME, VerifySettings

#: runs should stay valid this many time constants of the best bound (the horizon is
#: extended for it when sim_time is not set)
MIN_TIME_CONSTANTS = 5.0
#: time constants the automatic horizon keeps after the latest settling time of a start
AFTER_SETTLING = 2.0
#: the automatic horizon never asks for more than this many run-steps (steps of sim_dt
#: times the runs integrated side by side)
MAX_WORK = 100_000


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


@dataclass
class Horizon:
    """How long the runs are: `steps` of `dt` (even), and in words why (empty: as set).

    `need`: how long a run should stay valid (s; None: no bound); `settle`: the headline's
    settling time T (None: none recorded); `reaches_settle`: whether the horizon goes past
    T (False: no run can show the peak after T)."""

    steps: int
    dt: float
    extended: bool = False
    note: str = ""
    need: float | None = None
    short: str = ""  # the note in a few words, for the check's message
    settle: float | None = None
    reaches_settle: bool = True

    @property
    def seconds(self) -> float:
        return self.steps * self.dt


def even_steps(seconds: float, dt: float) -> int:
    """Steps of dt covering `seconds`, at least 2 and even (the 2 dt runs take half)."""
    k = max(2, int(math.ceil(seconds / dt - 1e-9)))
    return k + k % 2


def plan_horizon(bounds: BoundsResult | None, settings: VerifySettings, runs: int = 1
                 ) -> Horizon:
    """The simulated horizon for `runs` runs integrated side by side (see the module
    docstring): `sim_time`, or, when it is not set (None), `DEFAULT_SIM_TIME` extended for
    a slow bound within `MAX_WORK` run-steps."""
    dt = float(settings.sim_dt)
    chosen = settings.sim_time is not None
    base = float(settings.sim_time) if chosen else DEFAULT_SIM_TIME
    steps = even_steps(base, dt)
    b = best_bound(bounds)
    tau = time_constant(b)
    if b is None or tau is None or bounds is None or bounds.headline is None:
        return Horizon(steps, dt)
    settle = float(bounds.settle_time) if bounds.settle_time is not None else None
    enough = MIN_TIME_CONSTANTS * tau
    need = max(enough, (settle or 0.0) + AFTER_SETTLING * tau)
    if not math.isfinite(need):
        need = enough
    if need <= steps * dt:
        return Horizon(steps, dt, need=need, settle=settle)
    why = (f"{MIN_TIME_CONSTANTS:g} time constants of the {b.name} bound ({tau:.3g} s each)"
           f", {AFTER_SETTLING:g} of them after the settling time T = "
           f"{upper_text(settle or 0.0)} s")
    if chosen:
        return Horizon(steps, dt, need=need, settle=settle,
                       reaches_settle=settle is None or settle < steps * dt,
                       short=f"sim_time {base:g} s < the {need:.3g} s needed",
                       note=f"the horizon sim_time = {base:g} s is shorter "
                            f"than {need:.3g} s ({why})")
    cap = max(steps, MAX_WORK // max(int(runs), 1))
    cap -= cap % 2
    want = even_steps(need, dt)
    if want <= cap:
        return Horizon(want, dt, extended=True, need=need, settle=settle,
                       short=f"horizon extended from {base:g} s to {want * dt:.4g} s "
                             "(sim_time was not set)",
                       note=f"horizon extended from {base:g} s to {want * dt:.4g} s for "
                            f"{why}; sim_time was not set")
    limit = f"{MAX_WORK} run-steps ({runs} runs of at most {cap} steps of {dt:g} s)"
    if settle is None or settle < cap * dt:
        return Horizon(cap, dt, extended=True, need=need, settle=settle,
                       short=f"horizon extended from {base:g} s to {cap * dt:.4g} s "
                             f"(capped at {limit}; sim_time was not set)",
                       note=f"horizon extended from {base:g} s to {cap * dt:.4g} s for "
                            f"{why}; sim_time was not set (capped at {limit})")
    # T is out of reach within the cap: extend only for the time constants
    T = upper_text(settle, 4)
    steps = min(max(steps, even_steps(enough, dt)), cap)
    return Horizon(steps, dt, extended=steps * dt > base, need=need, settle=settle,
                   reaches_settle=False,
                   short=f"runs end at {steps * dt:.4g} s (a cap of {MAX_WORK} run-steps)",
                   note=f"the runs end at {steps * dt:.4g} s, before the settling time T = "
                        f"{T} s after which the headline bound holds (reaching it would take "
                        f"more than {limit}); the bound's transient, which holds at every t, "
                        "is compared")
