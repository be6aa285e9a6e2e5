"""The validity region: the initial errors r0 derived from an invariant plant region and the
bound's curve, in closed form on a linear plant, refused where it cannot hold, and checked
against simulated trajectories (a start with ||e(0)|| <= r0 keeps xhat in X and the error
under the bound)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.checks.bounds import check_bounds
from certify.checks.invariance import check_invariance
from certify.presentation import error_headline
from certify.prove.error_bound import bound_curve, inverse_diagonal_upper
from certify.results import InvarianceResult, Status
from certify.spec.region import parse_region

from ..planted import lam_cert_linear, linear_problem

A = np.array([[0.0, 1.0], [-2.0, -3.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [-2.0]])
P = np.array([[2.0, 0.3], [0.3, 1.0]])
VBAR = 0.05


def problem():
    return linear_problem(A, C, K, lam=0.2, P=P)


def bounds(inv, vbar=VBAR, local=False):
    lam = lam_cert_linear(A, C, K, P) * (1 - 1e-9)
    # k = K (y - C xhat): residual 0, Lipschitz constant in y exactly ||K|| (global)
    L = float(np.linalg.norm(K, 2)) * (1 + 1e-9)
    return check_bounds(problem(), lam_cert=lam, eps_bar=0.0, L=L, vbar=vbar,
                        L_is_local=local, invariance=inv)


def synthetic(hull, output, status=Status.PROVED) -> InvarianceResult:
    return InvarianceResult(status=status, message="", hull=hull, output_range=output,
                            region={"kind": "box", "origin": "spec", "text": "the box"})


def test_r0_is_the_room_the_region_leaves_over_the_metrics_reach():
    hull = [[-0.4, 0.3], [-0.2, 0.5]]
    r = bounds(synthetic(hull, [[-0.4, 0.3]]))
    assert r.status == Status.PROVED and r.region, r.region_reason
    d = [min(-0.4 + 1, 1 - 0.3), min(-0.2 + 1, 1 - 0.5)]  # X = [-1, 1]^2
    gamma = np.sqrt(inverse_diagonal_upper(P))
    room = min(di / gi for di, gi in zip(d, gamma))
    assert r.r0_W <= room and r.r0_W == pytest.approx(room, rel=1e-8)
    assert r.r0 == pytest.approx(room / math.sqrt(np.linalg.eigvalsh(P).max()), rel=1e-8)
    assert r.r0 * math.sqrt(np.linalg.eigvalsh(P).max()) <= r.r0_W
    assert r.proved_conditions == ["a", "b"]  # L is global: (d) is not needed
    assert r.region_settle_time is not None and r.region_settle_time <= r.settle_time
    text = error_headline(r).validity_text(unicode=False)
    assert text.startswith("for every x(0) in R and ||e(0)|| <= ")
    assert "xhat stays in X" in text and "(c) ||v|| <= 0.05 assumed" in text
    assert "Validity: for every x(0) in R" in r.message


@pytest.mark.parametrize("inv, words", [
    (None, "the invariance check did not run"),
    (synthetic([[-0.4, 0.3], [-0.2, 0.5]], [[-0.4, 0.3]], Status.UNKNOWN),
     "no plant region inside X was proved forward invariant (invariance UNKNOWN)"),
    (synthetic([[-1.4, 0.3], [-0.2, 0.5]], [[-1.4, 0.3]]), "is not inside X"),
    (synthetic([[-0.4, 0.3], [-0.2, 0.5]], [[-0.4, 1.3]]), "condition (b) is not proved"),
    (synthetic([[-0.999, 0.3], [-0.2, 0.5]], [[-0.999, 0.3]]), "does not fit in the room"),
])
def test_no_region_where_it_cannot_be_derived(inv, words):
    r = bounds(inv)
    assert r.status == Status.PROVED and r.region == "" and r.r0 is None
    assert words in r.region_reason
    assert "not proved for any set of starts" in r.message
    assert error_headline(r).validity_text() == ""


def test_condition_d_is_proved_where_the_outputs_stay_vbar_inside_y():
    hull = [[-0.4, 0.3], [-0.2, 0.5]]
    assert bounds(synthetic(hull, [[-0.4, 0.3]]), local=True).proved_conditions == \
        ["a", "b", "d"]
    # (an output range wider than h over the hull: the rule alone is tested)
    near = bounds(synthetic(hull, [[-0.4, 0.97]]), local=True)
    assert near.region and near.proved_conditions == ["a", "b"]
    assert "(d) y + v in Y assumed" in error_headline(near).validity_text(unicode=False)


# ----------------------------------------------------------------------------- simulated

_CACHE: dict[str, object] = {}


def proved_setup():
    """The invariance check on the linear plant (a Lyapunov ellipse it finds) and the
    bounds with it (cached: the hypothesis examples share them)."""
    if "r" not in _CACHE:
        system = problem().system
        inv = check_invariance(system, budget=50_000)
        assert inv.status == Status.PROVED, inv.message
        region = parse_region({"V": inv.region["V"], "level": inv.region["level"]},
                              X=system.X, states=system.states, symbols=system.symbols,
                              where="test")
        from certify.spec.expr import compile_numpy_rows

        _CACHE.update(r=bounds(inv), inv=inv, V=compile_numpy_rows([region.V], system.symbols),
                      level=float(inv.region["level"]))
    return _CACHE["r"], _CACHE["inv"], _CACHE["V"], _CACHE["level"]


def simulate(x0, xhat0, omega, phase, dt=0.004, steps=4000):
    """Plant x' = A x and observer xhat' = A xhat + K (y + v - C xhat) under the noise
    v = VBAR sign(sin(omega t + phase)) (RK4, the noise held over each step)."""
    def rhs(z, v):
        x, xh = z[:2], z[2:]
        return np.concatenate([A @ x, A @ xh + K[:, 0] * (C @ x + v - C @ xh)])

    z = np.concatenate([x0, xhat0])
    out = [z]
    for k in range(steps):
        v = VBAR * (1.0 if math.sin(omega * k * dt + phase) >= 0 else -1.0)
        k1 = rhs(z, v)
        k2 = rhs(z + dt / 2 * k1, v)
        k3 = rhs(z + dt / 2 * k2, v)
        k4 = rhs(z + dt * k3, v)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(z)
    traj = np.array(out)
    return np.arange(steps + 1) * dt, traj[:, :2], traj[:, 2:]


@settings(max_examples=20, deadline=None)
@given(u=st.floats(0.0, 1.0), angle=st.floats(0.0, 2 * math.pi),
       err=st.floats(0.0, 2 * math.pi), omega=st.floats(0.5, 20.0), phase=st.floats(0, 6.3))
def test_a_start_within_r0_keeps_xhat_in_x_and_the_error_under_the_bound(u, angle, err,
                                                                         omega, phase):
    r, inv, V, level = proved_setup()
    assert r.region and r.r0 > 0
    # x(0) in R: along a ray from the equilibrium, a fraction u of the way to the level set
    direction = np.array([math.cos(angle), math.sin(angle)])
    lo, hi = 0.0, 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(V((mid * direction)[None])[0, 0]) <= level else (lo, mid)
    x0 = u * lo * direction
    e0 = r.r0 * np.array([math.cos(err), math.sin(err)])  # on the sphere ||e(0)|| = r0
    t, x, xh = simulate(x0, x0 - e0, omega, phase)
    X = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    assert np.all(np.asarray(V(x))[:, 0] <= level + 1e-9)  # the plant stays in R
    assert np.all((xh >= X[:, 0]) & (xh <= X[:, 1]))  # xhat stays in X
    e = x - xh
    w0 = math.sqrt(float(e0 @ P @ e0))
    curve = bound_curve(r, r.best, w0, t)
    assert np.all(np.linalg.norm(e, axis=1) <= curve + 1e-7)
    after = t >= r.region_settle_time
    assert np.all(np.linalg.norm(e[after], axis=1) <= r.headline)
