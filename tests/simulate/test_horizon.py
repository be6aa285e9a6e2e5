"""The simulated horizon: bounded work whatever the settling time, and what is said then.

The planted case is the one a user meets with an observer that does nothing: a contracting
plant x' = -x, fully measured, and the zero gain. Its proved bound is astronomically small
(the ultimate value is a rounding residue) and is reached only after hundreds of seconds;
the simulation must stay cheap, say that its runs end before that time, compare what it can
(the transient, which holds at every t) and never call a float-noise excess a breach.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from certify.arith.text import upper_text
from certify.checks.bounds import check_bounds
from certify.checks.simulation import check_simulation
from certify.model.problem import Problem
from certify.results import SimulationRun, Status
from certify.settings import DEFAULT_SIM_TIME, VerifySettings
from certify.simulate import horizon as horizon_mod
from certify.simulate.horizon import MAX_WORK, plan_horizon
from certify.simulate.verdict import summarise
from certify.spec.system import System

from .test_simulation import linear_gain_net

CONTRACTING = """
name = "contracting"
states = ["x"]
outputs = ["y"]
f = ["-x"]
h = ["x"]
[box]
X = [[-1.0, 1.0]]
Y = [[-1.0, 1.0]]
"""


def zero_gain_case(tiny: float = 1e-162):
    """x' = -x, y = x, k = 0: lam_cert = 1/2 (the error contracts at rate 1), eps_bar and L
    a rounding residue `tiny` (as the provers return them for the zero gain)."""
    system = System.from_text(CONTRACTING, origin="test contracting")
    problem = Problem(system, linear_gain_net(1, 1, np.zeros((1, 1))), 0.5, np.eye(1))
    bounds = check_bounds(problem, lam_cert=0.5, eps_bar=tiny, L=tiny, vbar=0.15)
    return problem, bounds


def test_a_settling_time_of_hundreds_of_seconds_does_not_lengthen_the_runs():
    problem, bounds = zero_gain_case()
    assert bounds.status == Status.PROVED and bounds.headline < 1e-150
    assert bounds.settle_time is not None and bounds.settle_time > 300.0
    res = check_simulation(problem, bounds, VerifySettings(sim_dt=1e-2, seed=1),
                           certified=True)
    # five time constants of 1 s fit in the default horizon: it is kept, not extended
    assert res.horizon == pytest.approx(DEFAULT_SIM_TIME) and not res.horizon_extended
    assert res.status == Status.PASSED, res.message
    T = upper_text(bounds.settle_time, 4)
    assert f"the runs end at 10 s, before the settling time T = {T} s" in res.horizon_note
    assert f"no run reached t = {upper_text(bounds.settle_time, 2)} s" in res.message
    bounded = [r for r in res.runs if r.noise == "bounded"]
    assert len(bounded) == 12 and all(r.exit_time is None for r in bounded)
    for run in bounded:
        # the error follows the bound's transient e(0) e^(-t) to rounding: compared, never
        # a breach, however small the ultimate value
        assert not run.breach and run.max_ratio is not None and run.max_ratio <= 1.0
        assert run.peak_error is None and run.conservatism is None
        e0 = abs(run.x0[0] - run.xhat0[0])
        assert run.final_error == pytest.approx(e0 * math.exp(-10.0), rel=1e-8)


def test_the_cap_is_in_work_and_a_set_sim_time_is_kept():
    """The automatic horizon never asks for more than MAX_WORK run-steps (fewer steps for
    more runs); a sim_time the user set is kept as set, beyond the cap too."""
    _, bounds = zero_gain_case()
    slow = dataclasses.replace(bounds, settle_time=1e4)  # T far beyond any cap
    auto = VerifySettings(sim_dt=1e-3)
    for runs in (1, 13, 40):
        h = plan_horizon(slow, auto, runs=runs)
        assert h.steps * runs <= max(MAX_WORK, 10_000 * runs) and not h.reaches_settle
        assert h.steps % 2 == 0
    set_ = plan_horizon(slow, VerifySettings(sim_dt=1e-3, sim_time=500.0), runs=13)
    assert set_.steps == 500_000 and not set_.extended and not set_.reaches_settle
    assert set_.note.startswith("the horizon sim_time = 500 s is shorter than")


def test_slow_bound_extends_within_the_cap(monkeypatch):
    """A bound whose time constant is long: the horizon grows for five of them, as far as
    the cap allows, and says when it is capped."""
    _, bounds = zero_gain_case()
    slow = dataclasses.replace(bounds, settle_time=None)
    slow.iss_metric = dataclasses.replace(bounds.iss_metric, rate=0.01)  # tau = 100 s
    slow.iss = dataclasses.replace(bounds.iss, rate=0.01)
    monkeypatch.setattr(horizon_mod, "MAX_WORK", 100_000)
    h = plan_horizon(slow, VerifySettings(sim_dt=1e-2), runs=4)
    assert h.steps == 25_000 and h.extended and "capped at 100000 run-steps" in h.note


def test_a_peak_above_the_bound_within_the_tolerance_is_said_so():
    """conservatism < 1 with no breach (the excess was within the integrator's tolerance):
    the message never claims the bound is '0.5x the worst run'."""
    _, bounds = zero_gain_case()
    run = SimulationRun(label="r", x0=[0.1], xhat0=[0.0], noise="bounded",
                        within_conditions=True, exit_time=None, exit_reason="", max_ratio=0.9,
                        breach=False, mse=0.0, final_error=0.0, window=10.0,
                        peak_error=2 * bounds.headline, conservatism=0.5)
    s = summarise([run], bounds, bounds.iss_metric, 1.0,
                  plan_horizon(bounds, VerifySettings(sim_time=1e4, sim_dt=1.0)))
    assert "reaches the bound within the integrator's tolerance" in s.text
    assert "0.5x" not in s.text
