"""Simulation that tests the bound: switching (worst-case-like) noise beside uniform noise,
peaks after settling against the headline bound, the horizon and the starts."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given
from hypothesis import settings as settings_h
from hypothesis import strategies as st

from certify.arith.text import upper_text
from certify.checks.bounds import check_bounds
from certify.checks.simulation import check_simulation
from certify.model.problem import Problem
from certify.results import DissipationResult, SimulationResult, Status, from_jsonable, to_jsonable
from certify.settings import VerifySettings
from certify.simulate import horizon as horizon_mod
from certify.simulate.horizon import time_constant
from certify.simulate.integrate import bounded_noise, simulate_doubled
from certify.simulate.noise import SwitchingNoise, clip_to_ball
from certify.spec.system import System, load_system

from ..conftest import random_network
from .test_simulation import LINEAR, A, C, K, linear_gain_net, linear_problem

# the linear example of test_simulation: x' = A x, y = x1, k = K (y - h(xhat)), K = (1, 0):
# e' = (A - K C) e - K v with He{A - K C} = -I, so lam_cert = 1/2 (P = I), eps_bar = 0, L = 1;
# and with V = |e|^2, V' = -2|e|^2 - 2 e1 v <= -|e|^2 + v^2: a true dissipation inequality
# with alpha = mu = 1.
VBAR = 0.15


def settings(**kw) -> VerifySettings:
    base = dict(sim_dt=1e-2, sim_initial_conditions=3, seed=3)
    base.update(kw)
    return VerifySettings(**base)


def true_bounds(problem: Problem, **kw):
    return check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=VBAR, **kw)


@functools.cache
def worst_case_peak(vbar: float) -> float:
    """sup over unit c of vbar * int_0^inf |c^T e^((A - K C) s) K| ds: the largest ||e|| any
    noise within vbar can hold the linear observer's error at (L1 norm of the impulse
    response, maximised over directions on a fine grid). A - K C = [[-1, 1], [-1, -1]], so
    e^((A - K C) s) K = e^(-s) (cos s, -sin s)."""
    s = np.linspace(0.0, 40.0, 40001)
    resp = np.exp(-s)[:, None] * np.stack([np.cos(s), -np.sin(s)], axis=1)  # [S, 2]
    probe = scipy.linalg.expm((A - K @ C) * 0.7) @ K
    assert np.allclose(probe[:, 0], math.exp(-0.7) * np.array([math.cos(0.7), -math.sin(0.7)]))
    ds = s[1] - s[0]
    phis = np.linspace(0.0, np.pi, 1441)
    cs = np.stack([np.cos(phis), np.sin(phis)], axis=1)
    return vbar * float((np.abs(resp @ cs.T).sum(axis=0) * ds).max())


# ----- the noise --------------------------------------------------------------------------

@pytest.mark.parametrize("policy", ["adjoint", "greedy"])
@pytest.mark.parametrize("which", ["vdp", "three"])
def test_switching_noise_never_exceeds_vbar_and_is_seeded(policy, which, system3):
    system = load_system("vdp") if which == "vdp" else system3
    n, p = system.n, system.p
    net = random_network(n, p, seed=2)
    gen = torch.Generator().manual_seed(0)
    X = torch.as_tensor(system.X, dtype=torch.float64)
    x0 = X[:, 0] + 0.3 * (X[:, 1] - X[:, 0]) * (1 + torch.rand(4, n, generator=gen,
                                                                  dtype=torch.float64))
    xh0 = x0 + 0.05 * torch.randn(4, n, generator=gen, dtype=torch.float64)
    steps, dt, vbar = 120, 0.01, 0.2

    def run():
        fb = SwitchingNoise(system, net, np.eye(n), vbar, [1, 3], dt=dt, seed=5, policy=policy)
        noise = bounded_noise(steps, 4, p, vbar, dt, seed=1)
        fine, coarse = simulate_doubled(system, net, x0, xh0, dt=dt, steps=steps, noise=noise,
                                        doubled=[0, 1, 3], doubled_steps=steps // 2,
                                        feedback=fb)
        return fb, noise, fine, coarse

    fb, noise, fine, coarse = run()
    norms = torch.linalg.vector_norm(fine.v, dim=-1)
    assert float(norms.max()) <= vbar
    assert float(norms[:, [1, 3]].min()) > vbar * (1 - 1e-12)  # the largest admissible size
    # the rows without feedback keep their given noise; the fed-back ones were replaced
    assert torch.equal(fine.v[:-1, [0, 2]], noise[:, [0, 2]])
    assert not torch.equal(fine.v[:-1, [1, 3]], noise[:, [1, 3]])
    # held over `hold` steps, and the run at 2 dt replays the same signal
    v = fine.v[:-1, [1, 3]].numpy()
    assert np.array_equal(v[0::2], v[1::2])
    assert torch.equal(coarse.v[:-1, 1:], fine.v[: 2 * (steps // 2): 2, [1, 3]])
    fb2, _, fine2, _ = run()  # deterministic: the same seed, the same states, the same signal
    assert torch.equal(fine.v, fine2.v) and np.array_equal(fb.switches, fb2.switches)


def test_clip_to_ball_keeps_every_row_inside():
    gen = np.random.default_rng(0)
    for vbar in (0.15, 1e-300, 3.0, 0.1 + 0.2):
        d = gen.standard_normal((1000, 3))
        v = vbar * d / np.linalg.norm(d, axis=1, keepdims=True)
        assert np.all(np.linalg.norm(clip_to_ball(v, vbar), axis=1) <= vbar)
    with pytest.raises(AssertionError):
        clip_to_ball(np.array([[np.nan]]), 1.0)  # a NaN is never passed off as bounded


def test_greedy_direction_is_the_first_order_worst():
    """With a linear gain dk/dy = K: u = -K^T P e / |K^T P e| (sign of -e^T P K for p = 1)."""
    problem = linear_problem()
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    fb = SwitchingNoise(problem.system, problem.network, P, VBAR, [0, 1, 2], dt=0.01,
                        policy="greedy")
    x = np.array([[1.0, 0.5], [0.2, -0.4], [-1.0, 2.0]])
    xhat = np.array([[0.5, 0.5], [0.4, -0.1], [-1.0, 2.0]])  # the last: e = 0
    last = fb._last.copy()
    v = fb(0, x, xhat, 5)
    assert v.shape == (1, 3, 1)  # greedy: one hold at a time
    v = v[0]
    e = x - xhat
    want = -np.sign((e @ P @ K)[:, 0]) * VBAR
    np.testing.assert_allclose(v[:2, 0], want[:2], rtol=1e-13)
    np.testing.assert_allclose(v[2], VBAR * last[2], rtol=1e-13)  # undefined: kept


def test_adjoint_noise_reaches_the_linear_worst_case():
    """Known answer: for the linear observer the largest error any noise within vbar holds
    is vbar times the L1 norm of the impulse response (maximised over directions); the
    adjoint switching noise gets within 2% of it, the uniform noise and the greedy policy
    stay well below, and nothing exceeds it."""
    problem = linear_problem()
    steps, dt = 1500, 0.01
    zero = torch.zeros(3, 2, dtype=torch.float64)
    fb = SwitchingNoise(problem.system, problem.network, np.eye(2), VBAR, [0], dt=dt, seed=1)
    noise = bounded_noise(steps, 3, 1, VBAR, dt, seed=1)
    fine, _ = simulate_doubled(problem.system, problem.network, zero, zero, dt=dt,
                               steps=steps, noise=noise, feedback=fb)
    greedy = SwitchingNoise(problem.system, problem.network, np.eye(2), VBAR, [0], dt=dt,
                            seed=1, policy="greedy")
    fine_g, _ = simulate_doubled(problem.system, problem.network, zero[:1], zero[:1], dt=dt,
                                 steps=steps, noise=noise[:, :1], feedback=greedy)
    err = np.linalg.norm((fine.x - fine.xhat).numpy(), axis=-1)[500:]
    err_g = np.linalg.norm((fine_g.x - fine_g.xhat).numpy(), axis=-1)[500:, 0]
    sup = worst_case_peak(VBAR)
    adj, uni = float(err[:, 0].max()), float(err[:, 1:].max())
    assert sup * 0.98 <= adj <= sup * (1 + 1e-3)
    assert uni < 0.8 * adj
    # the greedy policy slides along e^T P K = 0: |e| -> vbar / sqrt(2) here
    assert float(err_g.max()) == pytest.approx(VBAR / math.sqrt(2), rel=0.02)
    assert fb.switches[0] >= 2  # bang-bang: it does switch


def test_a_zero_gain_keeps_the_direction_and_asks_once_per_window():
    """A zero gain: dk/dy = 0, so no noise reaches the error: the plan keeps the previous
    (seeded) direction over its whole window, returned in one block; an unstable
    linearisation has no plan at all: the direction is kept MIN_WINDOW_HOLDS holds, then a
    new plan is tried (not at every hold)."""
    from certify.simulate.noise import MIN_WINDOW_HOLDS, WINDOW_DECAYS

    def noise(f: list[str]) -> tuple[SwitchingNoise, list[int]]:
        text = LINEAR.replace('f = ["x2", "-x1 - x2"]', "f = " + str(f).replace("'", '"'))
        system = System.from_text(text, origin="test")
        fb = SwitchingNoise(system, linear_gain_net(2, 1, np.zeros((2, 1))), np.eye(2), VBAR,
                            [0, 1], dt=0.01, seed=1)
        tries: list[int] = []
        plan = fb.plan
        fb.plan = lambda *a: tries.append(1) or plan(*a)  # type: ignore[method-assign]
        return fb, tries

    x = np.array([[0.5, 0.1], [-0.2, 0.3]])
    fb, tries = noise(["x2", "-x1 - x2"])  # eigenvalues -1/2 +- i sqrt(3)/2: decay 1/2
    seeded = VBAR * fb._last
    v = fb(0, x, 0.9 * x, 10_000)
    J = int(math.ceil(WINDOW_DECAYS / 0.5 / (fb.hold * fb.dt)))
    assert v.shape == (J, 2, 1) and len(tries) == 2
    np.testing.assert_allclose(v, np.broadcast_to(seeded, v.shape), rtol=1e-13)
    assert np.all(np.linalg.norm(v, axis=-1) <= VBAR)
    assert fb.switches.tolist() == [0, 0]

    fb, tries = noise(["x1", "x2"])  # unstable: no plan
    seeded = VBAR * fb._last
    k = 0
    for _ in range(3):
        v = fb(k, x, 0.9 * x, 10_000)
        assert v.shape == (MIN_WINDOW_HOLDS, 2, 1)
        np.testing.assert_allclose(v, np.broadcast_to(seeded, v.shape), rtol=1e-13)
        k += len(v) * fb.hold
    assert len(tries) == 2 * 3


# ----- the check: a planted example with a known bound ------------------------------------

def test_linear_example_peaks_stay_below_the_known_bound():
    problem = linear_problem()
    bounds = true_bounds(problem)
    assert bounds.best == "iss" and bounds.ultimate == pytest.approx(0.15, rel=1e-9)
    res = check_simulation(problem, bounds, settings(), certified=True)
    assert res.status == Status.PASSED, res.message
    bounded = [r for r in res.runs if r.noise == "bounded"]
    assert [r.noise_kind for r in bounded] == ["uniform", "switching"] * 3
    assert res.bound_name == "iss" and res.headline == bounds.headline
    assert res.time_constant == pytest.approx(1.0) and res.horizon == pytest.approx(10.0)
    comp = np.array(bounds.per_component) * bounds.headline / bounds.ultimate
    for run in bounded:
        assert not run.breach and run.max_ratio <= 1.0
        assert run.max_noise <= VBAR
        assert run.settle_time is not None and run.peak_error is not None
        assert run.peak_time >= run.settle_time
        assert run.peak_error <= bounds.headline and run.conservatism >= 1.0
        assert run.conservatism == pytest.approx(bounds.headline / run.peak_error)
        assert run.bound_at_peak <= bounds.headline * (1 + 1e-12)
        assert run.bound_after_settling == bounds.headline
        assert np.all(np.array(run.peak_components) <= comp)
        assert run.time_constants == pytest.approx(10.0)
        # after settling no noise within vbar exceeds the linear worst case, plus what is
        # left of the start: ||e^((A - K C) t)|| <= e^(-t) as He{A - K C} = -I
        left = math.exp(-run.settle_time) * float(np.linalg.norm(np.subtract(run.x0,
                                                                             run.xhat0)))
        assert run.peak_error <= worst_case_peak(VBAR) + left + 1e-6
    for uni, sw in zip(bounded[0::2], bounded[1::2]):  # the same start, both kinds
        assert uni.x0 == sw.x0 and uni.xhat0 == sw.xhat0
        assert sw.peak_error > uni.peak_error
    worst = max(bounded, key=lambda r: r.peak_error)
    assert worst.noise_kind == "switching" and res.peak_run == worst.label
    assert res.peak_error == worst.peak_error
    assert res.conservatism == pytest.approx(bounds.headline / worst.peak_error)
    assert 1.0 <= res.conservatism < 1.5  # this bound is nearly tight against switching noise
    assert f"observed peak {worst.peak_error:.3g}" in res.message
    assert f"the bound is {res.conservatism:.3g}x the worst run" in res.message
    assert res.long_runs == 6 and "6 of 6 runs valid >= 5 time constants of 1 s" in res.message
    assert (f"vs bound {upper_text(bounds.headline)} after t >= "
            f"{upper_text(bounds.settle_time, 2)} s") in res.message  # rounded up
    assert not res.horizon_extended and "horizon" not in res.message
    assert from_jsonable(SimulationResult, to_jsonable(res)) == res


def test_dissipation_bound_is_tested_like_the_others():
    """The joint dissipation bound alone (no rate): its curve, its time constant 2/alpha,
    condition (d), the horizon extended to five time constants (sim_time not set)."""
    problem = linear_problem()
    d = DissipationResult(status=Status.PROVED, message="planted", alpha=1.0, mu=1.0)
    bounds = check_bounds(problem, lam_cert=None, eps_bar=None, L=None, vbar=VBAR,
                          dissipation=d)
    assert bounds.status == Status.PROVED and bounds.best == "dissipation"
    assert time_constant(bounds.dissipation) == pytest.approx(2.0)
    res = check_simulation(problem, bounds, settings(), certified=True)
    assert res.status == Status.PASSED, res.message
    assert res.bound_name == "dissipation" and res.time_constant == pytest.approx(2.0)
    assert res.horizon_extended and res.horizon > 10.0
    assert "horizon extended from 10 s to" in res.message and "sim_time was not set" in (
        res.message)
    assert "5 time constants of the dissipation bound (2 s each)" in res.horizon_note
    bounded = [r for r in res.runs if r.noise == "bounded"]
    assert all(not r.breach and r.conservatism >= 1.0 for r in bounded)
    assert all(r.time_constants >= 5.0 for r in bounded)
    assert res.long_runs == len(bounded)


def test_dissipation_with_a_measured_output_condition():
    """The dissipation inequality is proved over X x Y only: runs end when y + v leaves Y."""
    problem = linear_problem()
    text = (LINEAR.replace("X = [[-5.0, 5.0], [-5.0, 5.0]]", "X = [[-1.0, 1.0], [-1.0, 1.0]]")
            .replace("Y = [[-6.0, 6.0]]", "Y = [[-1.05, 1.05]]")
            .replace("x0 = [1.0, -1.0]", "x0 = [1.0, 0.0]"))
    problem = Problem(System.from_text(text, origin="t"), problem.network, 0.5, np.eye(2))
    d = DissipationResult(status=Status.PROVED, message="planted", alpha=1.0, mu=1.0)
    bounds = check_bounds(problem, lam_cert=None, eps_bar=None, L=None, vbar=VBAR,
                          dissipation=d)
    res = check_simulation(problem, bounds, settings(sim_time=1.0), certified=True)
    assert any("measured output" in r.exit_reason for r in res.runs)
    assert res.status != Status.ERROR


@pytest.mark.parametrize("planted", ["iss", "dissipation", "component"])
def test_a_planted_too_small_bound_is_an_error_naming_the_run(planted):
    problem = linear_problem()
    if planted == "iss":  # rate 100 and a noise gain of 0.001 (the true L is 1)
        bounds = check_bounds(problem, lam_cert=50.0, eps_bar=0.0, L=1e-3, vbar=VBAR)
    elif planted == "dissipation":  # mu 1e-4 (the true mu is 1)
        d = DissipationResult(status=Status.PROVED, message="planted", alpha=1.0, mu=1e-4)
        bounds = check_bounds(problem, lam_cert=None, eps_bar=None, L=None, vbar=VBAR,
                              dissipation=d)
    else:  # the norm bound is true; the per-component bounds planted 100x too small
        bounds = true_bounds(problem)
        bounds.per_component = [v / 100 for v in bounds.per_component]
    res = check_simulation(problem, bounds, settings(), certified=True)
    assert res.status == Status.ERROR, res.message
    assert res.message.startswith("PROVED certificate breached by simulation")
    named = [r for r in res.runs if r.breach]
    assert named and all(r.noise == "bounded" for r in named)
    assert f"run '{named[0].label}'" in res.message
    if planted == "component":
        assert "|e_" in res.message and "after the settling time" in res.message
    # without a passing certificate the same numbers are a violation, not a bug
    res2 = check_simulation(problem, bounds, settings(), certified=False)
    assert res2.status == Status.VIOLATED


# ----- the horizon and the starts ---------------------------------------------------------

def test_horizon_extended_only_when_sim_time_is_not_set(monkeypatch):
    """A slow (true) rate lam = 0.1: one time constant is 5 s. With sim_time at its default
    the horizon grows to five of them and the message says so; a sim_time the user set is
    kept and the message says it is short; the extension is capped."""
    problem = linear_problem()
    slow = check_bounds(problem, lam_cert=0.1, eps_bar=0.0, L=1.0, vbar=VBAR)
    auto = check_simulation(problem, slow, settings(sim_initial_conditions=1),
                            certified=True)
    assert auto.horizon_extended and auto.horizon >= 25.0
    assert auto.status == Status.PASSED, auto.message
    assert "horizon extended from 10 s" in auto.message
    assert all(r.window >= 25.0 for r in auto.runs if r.noise == "bounded")
    set_ = check_simulation(problem, slow, settings(sim_time=4.0, sim_initial_conditions=1),
                            certified=True)
    assert not set_.horizon_extended and set_.horizon == pytest.approx(4.0)
    assert "sim_time 4 s < the" in set_.message
    assert set_.horizon_note.startswith("the horizon sim_time = 4 s is shorter than")
    ten = check_simulation(problem, slow, settings(sim_time=10.0, sim_initial_conditions=1),
                           certified=True)  # the default's value, but set: kept as set
    assert not ten.horizon_extended and ten.horizon == pytest.approx(10.0)
    assert "sim_time 10 s < the" in ten.message
    # the cap is in run-steps: 3 runs here (one start under two noise kinds, the source's
    # protocol); T = 25.9 s is within a cap of 3000 steps, not T + two time constants
    assert slow.settle_time == pytest.approx(25.9, abs=0.1)
    monkeypatch.setattr(horizon_mod, "MAX_WORK", 9000)
    capped = check_simulation(problem, slow, settings(sim_initial_conditions=1),
                              certified=True)
    assert capped.horizon == pytest.approx(30.0) and "capped at 9000 run-steps" in (
        capped.message)
    assert capped.peak_error is not None  # the runs reached T
    # a cap of 1200 steps ends the runs before T: said, the peak after T not compared, the
    # horizon only as long as five time constants ask within the cap
    monkeypatch.setattr(horizon_mod, "MAX_WORK", 3600)
    short = check_simulation(problem, slow, settings(sim_initial_conditions=1),
                             certified=True)
    assert short.horizon == pytest.approx(12.0) and short.status == Status.PASSED
    assert short.peak_error is None and all(r.peak_error is None for r in short.runs)
    assert "runs end at 12 s (a cap of 3600 run-steps)" in short.message
    assert f"before the settling time T = {upper_text(slow.settle_time, 4)} s" in (
        short.horizon_note)
    assert f"no run reached t = {upper_text(slow.settle_time, 2)} s" in short.message
    assert "the bound's transient, which holds at every t, is compared" in short.horizon_note


@pytest.mark.parametrize("lam_cert", [2.512, 0.5])
def test_vdp_starts_stay_valid_five_time_constants(lam_cert):
    """On the vdp spec (the shipped LMI observer, its proved rate 2.512 and a slower true
    rate 0.5) the chosen starts stay valid for at least five time constants of the bound
    under both noise kinds: the plant alone leaves X within a few seconds from most of the
    box, so the starts are found near the unstable origin."""
    from certify.model.checkpoint import load

    ck = load("examples/vdp_lmi.ckpt")
    assert ck.problem.system.name == "vdp"
    bounds = check_bounds(ck.problem, lam_cert=lam_cert, eps_bar=0.0, L=94.69, vbar=VBAR)
    res = check_simulation(ck.problem, bounds, VerifySettings(sim_dt=5e-3,
                                                              sim_initial_conditions=4),
                           certified=True)
    assert res.status == Status.PASSED, res.message
    chosen = [r for r in res.runs if r.label.startswith("start")]
    assert len(chosen) == 6
    assert all(r.time_constants >= 5.0 for r in chosen), [r.window for r in chosen]
    assert res.long_runs >= len(chosen)
    assert all(r.max_noise <= VBAR and r.conservatism >= 1.0 for r in chosen)


@settings_h(max_examples=40, deadline=None)
@given(vbar=st.floats(1e-6, 10.0), seed=st.integers(0, 2**31 - 1),
       policy=st.sampled_from(["adjoint", "greedy"]))
def test_switching_noise_is_inside_the_ball_for_any_state(vbar, seed, policy):
    """Whatever the states (far outside X, equal, huge) and vbar, every value the policy
    returns has 2-norm <= vbar (numpy's and torch's norms), at the full size where a
    direction exists."""
    problem = linear_problem()
    gen = np.random.default_rng(seed)
    x = gen.standard_normal((5, 2)) * 10.0 ** gen.integers(-3, 4, size=(5, 1))
    xhat = x + gen.standard_normal((5, 2)) * 10.0 ** gen.integers(-8, 3, size=(5, 1))
    xhat[0] = x[0]  # e = 0: no direction, the previous one is kept
    fb = SwitchingNoise(problem.system, problem.network, np.eye(2), vbar, list(range(5)),
                        dt=0.01, seed=seed, policy=policy)
    k = 0
    for _ in range(3):
        v = fb(k, x, xhat, 3)
        assert 1 <= len(v) <= 3 and v.shape[1:] == (5, 1)
        assert np.all(np.linalg.norm(v, axis=-1) <= vbar)
        assert float(torch.linalg.vector_norm(torch.from_numpy(v), dim=-1).max()) <= vbar
        assert np.all(np.linalg.norm(v, axis=-1) >= vbar * (1 - 1e-12))
        k += len(v) * fb.hold
