"""How long the simulation runs: the horizon, from the settings and the proved bound.

A run tests the bound best when it stays valid for `MIN_TIME_CONSTANTS` time constants of
the best bound and still runs `AFTER_SETTLING` of them after the headline's settling time T
(`BoundsResult.settle_time`: "||e|| <= B after t >= T" is the claim users read). When
`sim_time` is not set the horizon is extended for that, capped at `MAX_AUTO_STEPS` steps. A
`sim_time` the user set is kept as set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from certify.results import BoundResult, BoundsResult
from certify.settings import DEFAULT_SIM_TIME, VerifySettings

#: runs should stay valid this many time constants of the best bound (the horizon is
#: extended for it when sim_time is not set)
MIN_TIME_CONSTANTS = 5.0
#: time constants the automatic horizon keeps after the latest settling time of a start
AFTER_SETTLING = 2.0
#: the automatic horizon never exceeds this many steps of sim_dt
MAX_AUTO_STEPS = 50_000


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

    `need`: how long a run should stay valid (s; None: no bound)."""

    steps: int
    dt: float
    extended: bool = False
    note: str = ""
    need: float | None = None
    short: str = ""  # the note in a few words, for the check's message

    @property
    def seconds(self) -> float:
        return self.steps * self.dt


def even_steps(seconds: float, dt: float) -> int:
    """Steps of dt covering `seconds`, at least 2 and even (the 2 dt runs take half)."""
    k = max(2, int(math.ceil(seconds / dt - 1e-9)))
    return k + k % 2


def plan_horizon(bounds: BoundsResult | None, settings: VerifySettings) -> Horizon:
    """The simulated horizon: `sim_time`, or, when `sim_time` is left at its default and the
    best bound is slow, long enough that a run can stay valid for `MIN_TIME_CONSTANTS` time
    constants and still run `AFTER_SETTLING` of them after the headline's settling time T
    (`BoundsResult.settle_time`), capped at `MAX_AUTO_STEPS` steps. A `sim_time` the user
    set (any number, `DEFAULT_SIM_TIME` included) is kept as set (the note says when it is
    shorter than that); None is "not set": `DEFAULT_SIM_TIME`, extended as needed."""
    dt = float(settings.sim_dt)
    chosen = settings.sim_time is not None
    base = float(settings.sim_time) if chosen else DEFAULT_SIM_TIME
    steps = even_steps(base, dt)
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
    want = even_steps(need, dt)
    capped = want > MAX_AUTO_STEPS
    steps = min(want, MAX_AUTO_STEPS - MAX_AUTO_STEPS % 2)
    cap = f" (capped at {MAX_AUTO_STEPS} steps of {dt:g} s)" if capped else ""
    return Horizon(steps, dt, extended=True, need=need,
                   short=f"horizon extended from {base:g} s to "
                         f"{steps * dt:.4g} s{cap} (sim_time was not set)",
                   note=f"horizon extended from {base:g} s to "
                        f"{steps * dt:.4g} s for {why}; sim_time was not set{cap}")
