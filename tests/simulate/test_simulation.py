"""Batched RK4 for plant + observer, and the simulation check against the proved bound."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from certify.checks.bounds import check_bounds
from certify.checks.simulation import check_simulation
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.results import SimulationResult, Status, from_jsonable, to_jsonable
from certify.settings import VerifySettings
from certify.simulate.integrate import (
    GainFunction,
    bounded_noise,
    gaussian_noise,
    hold_steps,
    simulate,
)
from certify.simulate.samples import MAX_SAMPLES
from certify.simulate.starts import initial_conditions
from certify.spec.system import System, load_system
from tests.conftest import random_network

# x' = A x with A = [[0, 1], [-1, -1]], y = x1; gain K = (1, 0): A - K C = [[-1, 1], [-1, -1]],
# He{A - K C} = -I, so D = He{J} + 2 lam I <= 0 exactly for lam = 1/2 (P = I): lam_cert = 1/2,
# eps_bar = 0 (k(x, h(x)) = K (h(x) - h(x)) = 0), L = ||K|| = 1 (global).
LINEAR = """
name = "damped"
states = ["x1", "x2"]
outputs = ["y"]
f = ["x2", "-x1 - x2"]
h = ["x1"]
[box]
X = [[-5.0, 5.0], [-5.0, 5.0]]
Y = [[-6.0, 6.0]]
[design]
lam = 0.5
[simulation]
x0 = [1.0, -1.0]
xhat0 = [0.0, 0.0]
"""
A = np.array([[0.0, 1.0], [-1.0, -1.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [0.0]])


def linear_gain_net(n: int, p: int, K: np.ndarray) -> GainNetwork:
    """Zero MLP plus the exact linear injection K (y - h(xhat))."""
    net = GainNetwork(n, p, (4,), K=torch.as_tensor(K))
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.zero_()
            layer.bias.zero_()
    return net


def linear_problem(text: str = LINEAR) -> Problem:
    system = System.from_text(text, origin="test linear")
    return Problem(system, linear_gain_net(2, 1, K), 0.5, np.eye(2))


def fast(**kw) -> VerifySettings:
    base = dict(sim_time=4.0, sim_dt=1e-2, sim_initial_conditions=4, seed=3)
    base.update(kw)
    return VerifySettings(**base)


# ----- integrator ------------------------------------------------------------------------

def test_rk4_fourth_order_on_linear_plant_and_observer():
    problem = linear_problem()
    x0 = torch.tensor([[1.0, -1.0], [0.3, 2.0]], dtype=torch.float64)
    xh0 = torch.tensor([[0.0, 0.0], [-1.0, 0.5]], dtype=torch.float64)
    # joint linear system [x; xhat]' = M [x; xhat]
    M = np.block([[A, np.zeros((2, 2))], [K @ C, A - K @ C]])
    T = 2.0
    exact = np.stack([scipy.linalg.expm(M * T) @ np.concatenate([a, b])
                      for a, b in zip(x0.numpy(), xh0.numpy())])
    errs = []
    for dt in (0.1, 0.05, 0.025):
        steps = int(round(T / dt))
        tr = simulate(problem.system, problem.network, x0, xh0, dt=dt, steps=steps)
        assert tr.x.shape == (steps + 1, 2, 2) and tr.t.shape == (steps + 1,)
        got = torch.cat([tr.x[-1], tr.xhat[-1]], dim=1).numpy()
        errs.append(np.abs(got - exact).max())
    r1, r2 = errs[0] / errs[1], errs[1] / errs[2]
    assert 13.0 < r1 < 19.0 and 13.0 < r2 < 19.0, errs  # 2^4 = 16
    assert errs[-1] < 1e-6


def test_bounded_noise_is_bounded_held_and_seeded():
    v = bounded_noise(1000, 5, 3, 0.15, 1e-3, hold=0.01, seed=7)
    assert v.shape == (1000, 5, 3) and v.dtype == torch.float64
    norms = torch.linalg.vector_norm(v, dim=-1)
    assert float(norms.max()) <= 0.15
    assert float(norms.min()) > 0.15 * (1 - 1e-12)  # the largest admissible magnitude
    k = hold_steps(1e-3, 0.01)
    assert k == 10
    assert torch.equal(v[0], v[k - 1]) and not torch.equal(v[0], v[k])
    assert torch.equal(v, bounded_noise(1000, 5, 3, 0.15, 1e-3, hold=0.01, seed=7))
    assert not torch.equal(v, bounded_noise(1000, 5, 3, 0.15, 1e-3, hold=0.01, seed=8))
    assert hold_steps(1e-3, 0.0031) % 2 == 0
    g = gaussian_noise(20000, 2, 1, 0.15, seed=1)
    assert abs(float(g.std()) - 0.15) < 0.005


@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_gain_function_matches_kernel(system3, structure):
    net = random_network(3, 2, structure=structure, seed=4).double()
    gen = torch.Generator().manual_seed(0)
    xh = torch.rand(17, 3, generator=gen, dtype=torch.float64) * 2 - 1
    y = torch.rand(17, 2, generator=gen, dtype=torch.float64) * 2 - 1
    want = gain_terms(system3, net, xh, y, with_dy=False).k
    got = GainFunction(system3, net)(xh, y)
    assert isinstance(got, np.ndarray) and got.shape == (17, 3)
    torch.testing.assert_close(torch.from_numpy(got), want, rtol=1e-13, atol=1e-13)


# ----- the check -----------------------------------------------------------------------

def test_linear_gain_stays_below_the_bound():
    problem = linear_problem()
    bounds = check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=0.15)
    assert bounds.status == Status.PROVED
    res = check_simulation(problem, bounds, fast(), certified=True)
    assert res.status == Status.PASSED, res.message
    bounded = [r for r in res.runs if r.noise == "bounded"]
    assert len(bounded) == 8 and bounded[0].label.startswith("source x0")  # 4 starts x 2
    for run in bounded:
        assert run.within_conditions and run.exit_time is None and not run.breach
        assert run.max_ratio is not None and run.max_ratio <= 1.0
        assert 0 < run.tolerance < 1e-6
        err, bnd = np.array(run.error), np.array(run.bound)
        assert np.all(err <= bnd + run.tolerance)
        assert len(run.t) <= MAX_SAMPLES and len(run.x) == len(run.t) and len(run.x[0]) == 2
        # initial states inside X, h(x0) inside Y
        assert np.all(np.abs(run.x0) <= 5.0) and np.all(np.abs(run.xhat0) <= 5.0)
    # the bound is tight here (He{J} = -I, noise of norm vbar): the error gets close to it
    assert "after one time constant" in res.message
    src = [r for r in res.runs if r.noise == "gaussian"]
    assert len(src) == 1 and not src[0].within_conditions and src[0].max_ratio is None
    assert math.isfinite(src[0].mse) and src[0].mse > 0
    # JSON round trip of the whole result
    assert from_jsonable(SimulationResult, to_jsonable(res)) == res


def test_planted_breach_of_a_proved_certificate_is_an_error():
    problem = linear_problem()
    # deliberately too small: rate 100 and a noise gain of 0.001 (the true L is 1)
    bad = check_bounds(problem, lam_cert=50.0, eps_bar=0.0, L=1e-3, vbar=0.15)
    res = check_simulation(problem, bad, fast(sim_time=1.0), certified=True)
    assert res.status == Status.ERROR
    assert res.message.startswith("PROVED certificate breached by simulation")
    assert "bug in certify" in res.message
    assert any(r.breach and r.max_ratio > 1 for r in res.runs)
    # the same numbers without a passing certificate: a violation, not a bug
    res2 = check_simulation(problem, bad, fast(sim_time=1.0), certified=False)
    assert res2.status == Status.VIOLATED


def test_no_bound_is_not_applicable_and_nothing_is_simulated(monkeypatch):
    """Nothing to compare a run with: NOT APPLICABLE (not "SKIPPED"), a short message saying
    so, no runs, and the integrator never called."""
    import certify.simulate.evidence as evidence

    def never(*a, **k):
        raise AssertionError("integrated although there is no bound to compare with")

    monkeypatch.setattr(evidence, "simulate_doubled", never)
    monkeypatch.setattr(evidence, "initial_conditions", never)
    problem = linear_problem()
    bounds = check_bounds(problem, lam_cert=-0.2, eps_bar=0.0, L=1.0, vbar=0.15)
    res = check_simulation(problem, bounds, fast(sim_time=1.0), certified=False)
    assert res.status == Status.NOT_APPLICABLE and "no bound exists" in res.message
    assert res.message.startswith("not applicable: no proved error bound to compare with")
    assert res.message.endswith("nothing was simulated.") and len(res.message) < 400
    assert res.runs == [] and res.horizon is None and res.bound_name == ""
    assert res.peak_error is None and res.time_constant is None
    res_none = check_simulation(problem, None, fast(sim_time=1.0), certified=False)
    assert res_none.status == Status.NOT_APPLICABLE and res_none.runs == []
    assert "no bounds were computed" in res_none.message
    assert from_jsonable(SimulationResult, to_jsonable(res)) == res
    from types import SimpleNamespace

    from certify.checks.simulation import CHECK

    shown = CHECK.present(res, SimpleNamespace(settings={}))
    assert [(q.label, q.value, q.suffix) for q in shown.facts] == [
        ("Status", "NOT APPLICABLE", ""), ("Runs", 0, " (nothing simulated)")]


def test_vdp_source_protocol_leaves_X():
    vdp = load_system("vdp")
    problem = Problem(vdp, random_network(2, 1, seed=1), 2.5, np.eye(2))
    # a loose bound, only so that there is one to compare with (nothing is simulated without)
    bounds = check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1e3, vbar=0.15)
    res = check_simulation(problem, bounds, fast(sim_time=2.0, sim_initial_conditions=2),
                           certified=False)
    src = next(r for r in res.runs if r.noise == "gaussian")
    assert src.x0 == [-1.0, 2.5] and src.xhat0 == [0.0, 0.0]
    assert not src.within_conditions and "outside the theorem's conditions" in src.label
    assert src.exit_time is not None and 0.1 < src.exit_time < 0.6
    assert "the plant state x left X: x2 =" in src.exit_reason
    assert max(abs(row[1]) for row in src.x) > 3.8  # METHOD: the plant reaches |x2| = 3.90
    assert math.isfinite(src.mse)
    bounded_src = res.runs[0]
    assert bounded_src.label.startswith("source x0") and bounded_src.exit_time is not None
    assert "left the validity conditions" in res.message


def test_exits_are_compared_only_inside_the_window():
    # X is small and x0 sits on its edge moving outwards: the plant leaves X at the first step
    text = (LINEAR.replace("X = [[-5.0, 5.0], [-5.0, 5.0]]", "X = [[-1.2, 1.2], [-1.2, 1.2]]")
            .replace("x0 = [1.0, -1.0]", "x0 = [1.2, 1.0]"))
    problem = linear_problem(text)
    # a bound far too small, breached right after the exit: not a breach, nothing compared
    bad = check_bounds(problem, lam_cert=50.0, eps_bar=0.0, L=1e-3, vbar=0.15)
    res = check_simulation(problem, bad, fast(sim_initial_conditions=1), certified=True)
    run = res.runs[0]
    assert run.exit_time == pytest.approx(0.01) and "x1 = 1.20" in run.exit_reason
    assert not run.breach and run.max_ratio <= 1.0
    assert res.status == Status.UNKNOWN and "nothing was compared" in res.message
    # with the true bound and a later exit, the window is compared and holds
    text2 = text.replace("x0 = [1.2, 1.0]", "x0 = [1.0, 1.1]")
    problem2 = linear_problem(text2)
    good = check_bounds(problem2, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=0.15)
    res2 = check_simulation(problem2, good, fast(), certified=True)
    run2 = res2.runs[0]
    assert run2.exit_time is not None and run2.exit_time > 0.05
    assert "the plant state x left X" in run2.exit_reason
    assert run2.max_ratio is not None and not run2.breach
    assert res2.status == Status.PASSED, res2.message


def test_local_lipschitz_adds_the_measured_output_condition():
    # h(X) = [-1, 1] inside Y = [-1.1, 1.1]; y + v with |v| = 0.15 can leave Y near x1 = 1
    text = (LINEAR.replace("X = [[-5.0, 5.0], [-5.0, 5.0]]", "X = [[-1.0, 1.0], [-1.0, 1.0]]")
            .replace("Y = [[-6.0, 6.0]]", "Y = [[-1.1, 1.1]]")
            .replace("x0 = [1.0, -1.0]", "x0 = [1.0, 0.0]"))
    problem = linear_problem(text)
    s = fast(sim_time=1.0)
    glob = check_simulation(problem, check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0,
                                                  vbar=0.15), s, certified=True)
    loc = check_simulation(problem, check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0,
                                                 vbar=0.15, L_is_local=True), s,
                           certified=True)
    assert not any("measured output" in r.exit_reason for r in glob.runs)
    assert any("measured output" in r.exit_reason for r in loc.runs)
    assert loc.status != Status.ERROR and glob.status != Status.ERROR


def test_three_states_two_outputs(system3):
    net = random_network(3, 2, seed=2)
    problem = Problem(system3, net, system3.lam, system3.P)
    bounds = check_bounds(problem, lam_cert=0.4, eps_bar=0.05, L=1.0, vbar=0.1)
    assert bounds.status == Status.PROVED and bounds.theorem3.applicable is False
    res = check_simulation(problem, bounds, fast(sim_time=1.0, sim_initial_conditions=3),
                           certified=False)
    assert res.status in (Status.PASSED, Status.VIOLATED, Status.UNKNOWN)
    assert len(res.runs) == 7  # 3 starts x (uniform, switching) + the source protocol
    for run in res.runs:
        assert len(run.x0) == 3 and len(run.x[0]) == 3 and len(run.xhat[0]) == 3
        # a run outside the conditions (Gaussian noise) carries no bound: none is claimed
        assert len(run.bound) == (len(run.t) if run.within_conditions else 0)
        assert len(run.t) == len(run.error)
    ics = initial_conditions(system3, 5, seed=0)
    hy = system3.h(ics.x0).numpy()
    Y = system3.Y
    assert np.all((hy >= Y[:, 0]) & (hy <= Y[:, 1]))
    X = system3.X
    assert np.all((ics.xhat0.numpy() >= X[:, 0]) & (ics.xhat0.numpy() <= X[:, 1]))


def test_same_seed_same_numbers():
    problem = linear_problem()
    bounds = check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=0.15)
    a = check_simulation(problem, bounds, fast(sim_time=1.0), certified=True)
    b = check_simulation(problem, bounds, fast(sim_time=1.0), certified=True)
    assert [r.error for r in a.runs] == [r.error for r in b.runs]
    c = check_simulation(problem, bounds, fast(sim_time=1.0, seed=4), certified=True)
    assert [r.error for r in a.runs] != [r.error for r in c.runs]


def test_linear_three_states_two_outputs_proved():
    # A with He{A - K C} = diag(-2, -1, -2) <= -2 lam I at lam = 1/2; K = C^T, ||K|| = 1
    text = """
name = "lin3"
states = ["a", "b", "c"]
outputs = ["ya", "yc"]
f = ["-a + b", "-a - b + 0.5*c", "-0.5*b - c"]
h = ["a", "c"]
[box]
X = [[-4, 4], [-4, 4], [-4, 4]]
Y = [[-5, 5], [-5, 5]]
[simulation]
x0 = [1.0, -2.0, 0.5]
xhat0 = [0.0, 0.0, 0.0]
"""
    system = System.from_text(text, origin="test lin3")
    Kc = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    problem = Problem(system, linear_gain_net(3, 2, Kc), 0.5, np.eye(3))
    bounds = check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=0.2)
    res = check_simulation(problem, bounds, fast(sim_time=3.0), certified=True)
    assert res.status == Status.PASSED, res.message
    assert all(not r.breach for r in res.runs)


# ----- batched integration, starts, valid windows ------------------------------------------

def test_doubled_runs_share_the_batch_and_equal_separate_integrations():
    """The 2 dt runs ride in the dt batch (no extra right-hand-side calls) and give the same
    numbers as integrating them on their own, up to the rounding of the network's matrix
    products (BLAS may take another kernel for another batch size: bit-equal on some CPUs,
    not on all)."""
    from certify.simulate.integrate import simulate_doubled

    vdp = load_system("vdp")
    net = random_network(2, 1, seed=1)
    x0 = torch.tensor([[0.5, 0.2], [1.0, -1.0], [0.1, 0.1]], dtype=torch.float64)
    xh = 0.9 * x0
    noise = bounded_noise(200, 3, 1, 0.15, 0.01, seed=1)
    calls = []
    rows = vdp.array_rows

    def counted(key):
        fn = rows(key)
        return (lambda s: (calls.append(1), fn(s))[1]) if key == "fh" else fn

    vdp.array_rows = counted
    try:
        fine, coarse = simulate_doubled(vdp, net, x0, xh, dt=0.01, steps=200, noise=noise,
                                        doubled=[0, 2], doubled_steps=60)
    finally:
        del vdp.array_rows
    assert len(calls) == 4 * 200  # one f (and h) call per stage, the doubled runs included
    alone = simulate(vdp, net, x0, xh, dt=0.01, steps=200, noise=noise)
    same = dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fine.x, alone.x, **same)
    torch.testing.assert_close(fine.xhat, alone.xhat, **same)
    ref = simulate(vdp, net, x0[[0, 2]], xh[[0, 2]], dt=0.02, steps=60,
                   noise=noise[:120:2][:, [0, 2]])
    torch.testing.assert_close(coarse.x, ref.x, **same)
    torch.testing.assert_close(coarse.xhat, ref.xhat, **same)


def test_starts_keep_the_plant_in_X_with_small_errors_in_the_P_norm():
    """Chosen starts: the plant alone stays in X the longest; W(0) = half the room, so xhat(0)
    is in X; with room for the bound's radius the checkable form is said to hold."""
    from certify.simulate.starts import ellipsoid_room, plant_windows

    vdp = load_system("vdp")
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    ics = initial_conditions(vdp, 6, seed=0, P=P, horizon=5.0, vbar=0.1, L_is_local=True,
                             radius=0.01)
    assert ics.labels[0].startswith("source x0") and len(ics.labels) == 6
    x0, xh0 = ics.x0[1:].numpy(), ics.xhat0[1:].numpy()
    window, room = plant_windows(vdp, P, ics.x0[1:], horizon=5.0, y_margin=0.1)
    # VdP's limit cycle leaves X: only starts near the unstable origin stay in for 5 s
    assert np.all(window >= 4.0) and np.all(np.abs(x0) < 1.0)
    W0 = np.sqrt(np.einsum("ri,ij,rj->r", x0 - xh0, P, x0 - xh0))
    assert np.allclose(W0, 0.5 * room, rtol=1e-9)
    assert np.all(room <= ellipsoid_room(vdp.X, P, x0) + 1e-12)
    assert np.all((xh0 >= vdp.X[:, 0]) & (xh0 <= vdp.X[:, 1]))
    assert all("checkable form of 'xhat stays in X' holds" in n for n in ics.notes[1:]
               if f"room {0.01:.3g}" not in n)
    wide = initial_conditions(vdp, 3, seed=0, P=P, horizon=5.0, radius=50.0)
    assert all("cannot hold" in n for n in wide.notes[1:])


def test_all_windows_shorter_than_a_time_constant_is_inconclusive():
    """lam_cert = 0.01 is a true (loose) rate here, its time constant 1/(2 lam) = 50 s; runs
    of 1 s compare almost nothing: UNKNOWN (inconclusive evidence), not PASSED."""
    problem = linear_problem()
    slow = check_bounds(problem, lam_cert=0.01, eps_bar=0.0, L=1.0, vbar=0.15)
    res = check_simulation(problem, slow, fast(sim_time=1.0), certified=True)
    assert res.status == Status.UNKNOWN and res.time_constant == pytest.approx(50.0)
    assert res.message.startswith("inconclusive evidence: no breach")
    assert all(r.window is not None and r.window <= 1.0 + 1e-9 for r in res.runs)
    good = check_bounds(problem, lam_cert=0.5, eps_bar=0.0, L=1.0, vbar=0.15)
    res2 = check_simulation(problem, good, fast(sim_time=2.0), certified=True)
    assert res2.status == Status.PASSED and res2.time_constant == pytest.approx(1.0)


@pytest.mark.slow
def test_vdp_certified_runs_stay_valid_beyond_a_time_constant():
    """Issue 8.5: on the certified VdP observer the old random starts left the conditions
    within 0.03-0.07 s; chosen starts stay valid for more than one time constant."""
    from certify.model.checkpoint import load

    ck = load("examples/vdp_certified.ckpt")
    bounds = check_bounds(ck.problem, lam_cert=2.53, eps_bar=0.0, L=78.7, vbar=0.15,
                          eps_bar_P=0.0, L_is_local=True)
    assert bounds.vacuous  # 29.3 > the box's half-diagonal 3.6
    res = check_simulation(ck.problem, bounds, fast(sim_time=2.0, sim_dt=2e-3,
                                                    sim_initial_conditions=4),
                           certified=True)
    assert res.status == Status.PASSED, res.message
    chosen = [r for r in res.runs if r.label.startswith("start")]
    assert len(chosen) == 6 and all(r.window > res.time_constant for r in chosen)
    assert len(res.message) < 700 and "see the table of runs" in res.message


@pytest.mark.parametrize("structure,p", [("structural", 1), ("structural", 2), ("direct", 1),
                                         ("direct", 2)])
def test_simulation_gain_equals_the_general_point_evaluation(structure, p):
    """The simulation's NumPy value arithmetic gives the floats of `certify.model.gain.gain_value`
    with the general torch row arithmetic (the one every kernel uses) up to the libraries'
    rounding of the products and tanh: a few ulps."""
    from certify.model.gain import gain_value
    from certify.simulate.integrate import GainFunction

    text = ("name='t'\nstates=['a','b','c']\noutputs=" + str(["o1", "o2"][:p]) +
            "\nf=['b','c','-a']\nh=" + str(["a", "a*b"][:p]) +
            "\n[box]\nX=[[-1,1],[-1,1],[-1,1]]\nY=" + str([[-1, 1], [-1, 1]][:p]) + "\n")
    system = System.from_text(text, origin="test")
    net = random_network(3, p, structure=structure, seed=3)
    gen = torch.Generator().manual_seed(1)
    xhat = torch.rand(11, 3, generator=gen, dtype=torch.float64) * 2 - 1
    y = torch.rand(11, p, generator=gen, dtype=torch.float64) * 2 - 1
    with torch.no_grad():
        ref = gain_value(net.spec(torch.float64, detach=True), system, xhat, y)
        got = GainFunction(system, net)(xhat, y)
    assert isinstance(got, np.ndarray)
    torch.testing.assert_close(torch.from_numpy(got), ref, rtol=1e-14, atol=1e-15)
