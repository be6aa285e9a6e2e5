"""Forward invariance proofs: known invariant sets proved, planted non-invariant regions
refused (VIOLATED with a witness the flow really leaves through, or at least never PROVED),
the reach of a region bounded from outside, and the regions found around attractors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.prove import invariance as inv
from certify.results import Status
from certify.simulate.integrate import simulate_plant
from certify.spec.region import Region, check_polygon, parse_region
from certify.spec.system import load_system

from ..planted import linear_system

BUDGET = 50_000


def lyapunov(A: np.ndarray) -> np.ndarray:
    """S with A^T S + S A = -I."""
    n = A.shape[0]
    K = np.kron(np.eye(n), A.T) + np.kron(A.T, np.eye(n))
    S = np.linalg.solve(K, -np.eye(n).reshape(-1)).reshape(n, n)
    return 0.5 * (S + S.T)


def quadratic_text(S: np.ndarray, names: list[str]) -> str:
    n = len(names)
    terms = [f"{float(S[i, i] if i == j else 2 * S[i, j])!r}*{names[i]}*{names[j]}"
             for i in range(n) for j in range(i, n)]
    return " + ".join(terms)


def sublevel(system, text: str, level: float) -> Region:
    return parse_region({"V": text, "level": level}, X=system.X, states=system.states,
                        symbols=system.symbols, where="test")


def regular_polygon(m: int, radius: float, phase: float = 0.0,
                    centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    th = phase + 2 * math.pi * np.arange(m) / m
    return np.stack([centre[0] + radius * np.cos(th), centre[1] + radius * np.sin(th)], 1)


def outward_speed(system, vertices: np.ndarray, samples: int = 2001) -> float:
    """The largest sampled a^T f / |a| over the edges of a counter-clockwise polygon."""
    f = system.array_rows("f")
    worst = -math.inf
    for k in range(len(vertices)):
        p, q = vertices[k], vertices[(k + 1) % len(vertices)]
        d = q - p
        a = np.array([d[1], -d[0]]) / np.linalg.norm(d)
        s = np.linspace(0.0, 1.0, samples)[:, None]
        worst = max(worst, float((np.asarray(f(p + s * d)) @ a).max()))
    return worst


# ----------------------------------------------------------------------------- known answers

@settings(max_examples=15, deadline=None)
@given(a=st.floats(0.3, 3.0), b=st.floats(-2.0, 2.0), c=st.floats(0.3, 3.0),
       level=st.floats(0.05, 0.9))
def test_a_stable_linear_systems_lyapunov_ellipse_is_proved_invariant(a, b, c, level):
    A = np.array([[-a, b], [-b, -c]])
    S = lyapunov(A)
    system = linear_system(A, np.array([[1.0, 0.0]]), X=np.array([[-3.0, 3.0]] * 2))
    # the largest level inside X, scaled
    room = 9.0 / np.diag(np.linalg.inv(S)).max()
    region = sublevel(system, quadratic_text(S, system.states), level * room)
    proof = inv.prove_region(system, region, system.X, BUDGET)
    assert proof.status == Status.PROVED, proof.message
    assert proof.margin is not None and proof.margin < 0
    # the reach is an outer bound of the ellipse's true ranges, and not far from it
    true = np.sqrt(level * room * np.diag(np.linalg.inv(S)))
    assert np.all(proof.hull[:, 1] >= true) and np.all(proof.hull[:, 0] <= -true)
    assert np.all(proof.hull[:, 1] <= true + 0.05 * 6)


def test_a_three_state_lyapunov_ellipse_is_proved():
    A = np.array([[-1.0, 2.0, 0.0], [-2.0, -1.0, 0.5], [0.0, -0.5, -2.0]])
    system = linear_system(A, np.array([[1.0, 0.0, 0.0]]), X=np.array([[-2.0, 2.0]] * 3))
    region = sublevel(system, quadratic_text(lyapunov(A), system.states), 0.3)
    assert inv.prove_region(system, region, system.X, 200_000).status == Status.PROVED


@settings(max_examples=20, deadline=None)
@given(m=st.integers(3, 12), radius=st.floats(0.2, 0.9), phase=st.floats(0, 6.3),
       cx=st.floats(-0.05, 0.05), cy=st.floats(-0.05, 0.05))
def test_a_polygon_around_the_equilibrium_of_a_radial_flow_is_invariant(m, radius, phase, cx,
                                                                          cy):
    # x' = -x: a^T f = -a^T x < 0 on every edge whose line passes the origin on its inside
    system = linear_system(-np.eye(2), np.array([[1.0, 0.0]]))
    v = check_polygon(regular_polygon(m, radius, phase, (cx, cy)), system.X, "test")
    proof = inv.prove_region(system, Region("polygon", vertices=v), system.X, BUDGET)
    assert proof.status == Status.PROVED, proof.message
    assert np.allclose(proof.hull, np.stack([v.min(0), v.max(0)], 1), atol=1e-12)


def test_a_box_is_proved_invariant_for_a_contracting_flow():
    system = linear_system(np.array([[-1.0, 0.3], [-0.3, -1.0]]), np.array([[1.0, 0.0]]))
    box = np.array([[-0.5, 0.6], [-0.7, 0.4]])
    proof = inv.prove_region(system, Region("box", box=box), system.X, BUDGET)
    assert proof.status == Status.PROVED, proof.message
    assert np.allclose(proof.hull, box)


# ----------------------------------------------------------------------------- planted

@pytest.mark.parametrize("hair", [1e-3, 1e-6])
def test_a_polygon_edge_crossed_outwards_by_a_hair_is_refused(hair):
    # x' = J x - eps x spirals in; on a regular m-gon of circumradius 1 the outward speed
    # of an edge is largest at its vertex: sin(pi/m) - eps cos(pi/m) (a^T J x is linear
    # along the edge). eps is set so that it is +hair there: every edge crosses outwards
    # on a sliver near one vertex, inwards elsewhere
    m = 8
    eps = (math.sin(math.pi / m) - hair) / math.cos(math.pi / m)
    A = np.array([[-eps, 1.0], [-1.0, -eps]])
    system = linear_system(A, np.array([[1.0, 0.0]]), X=np.array([[-2.0, 2.0]] * 2))
    v = check_polygon(regular_polygon(m, 1.0, 0.1), system.X, "test")
    assert 0 < outward_speed(system, v) <= 1.01 * hair
    proof = inv.prove_region(system, Region("polygon", vertices=v), system.X, BUDGET)
    assert proof.status == Status.VIOLATED, proof.message
    # the witness is on the boundary and the flow there points out
    x = np.asarray(proof.witness)
    f = np.asarray(system.array_rows("f")(x[None]))[0]
    def cross(a, b):
        return a[0] * b[1] - a[1] * b[0]

    k = [i for i in range(m) if abs(cross(v[(i + 1) % m] - v[i], x - v[i])) < 1e-9]
    assert k, "the witness lies on an edge"
    d = v[(k[0] + 1) % m] - v[k[0]]
    assert float(np.array([d[1], -d[0]]) @ f) > 0
    # and a hair the other way is proved
    eps_in = (math.sin(math.pi / m) + hair) / math.cos(math.pi / m)
    system_in = linear_system(np.array([[-eps_in, 1.0], [-1.0, -eps_in]]),
                              np.array([[1.0, 0.0]]), X=np.array([[-2.0, 2.0]] * 2))
    assert inv.prove_region(system_in, Region("polygon", vertices=v), system.X,
                            BUDGET).status == Status.PROVED


@settings(max_examples=25, deadline=None)
@given(m=st.integers(3, 10), radius=st.floats(0.1, 0.5), phase=st.floats(0, 6.3),
       cx=st.floats(-0.5, 0.5), cy=st.floats(-0.5, 0.5), rot=st.floats(-3.0, 3.0))
def test_a_region_the_flow_leaves_somewhere_is_never_proved(m, radius, phase, cx, cy, rot):
    # a rotating, contracting flow and polygons anywhere: PROVED only when no sampled edge
    # point crosses outwards; VIOLATED only when one really does
    system = linear_system(np.array([[-0.3, rot], [-rot, -0.3]]), np.array([[1.0, 0.0]]))
    v = check_polygon(regular_polygon(m, radius, phase, (cx, cy)), system.X, "test")
    proof = inv.prove_region(system, Region("polygon", vertices=v), system.X, BUDGET)
    sampled = outward_speed(system, v)
    if proof.status == Status.PROVED:
        assert sampled < 0
    elif proof.status == Status.VIOLATED:
        assert sampled > 0
    if sampled > 0:
        assert proof.status != Status.PROVED


def test_a_box_a_rotation_leaves_is_refused():
    system = linear_system(np.array([[0.0, 1.0], [-1.0, 0.0]]), np.array([[1.0, 0.0]]))
    proof = inv.prove_region(system, Region("box", box=np.array([[-0.5, 0.5]] * 2)),
                             system.X, BUDGET)
    assert proof.status == Status.VIOLATED
    x = np.asarray(proof.witness)
    assert np.isclose(np.abs(x).max(), 0.5)


def test_a_circle_inside_the_van_der_pol_cycle_is_left_by_the_flow():
    # V = x1^2 + x2^2: V' = 2 x2^2 (1 - x1^2) > 0 on the circle of radius 0.5 off x2 = 0
    system = load_system("vdp")
    proof = inv.prove_region(system, sublevel(system, "x1**2 + x2**2", 0.25), system.X,
                             BUDGET)
    assert proof.status == Status.VIOLATED, proof.message
    x = np.asarray(proof.witness)
    assert abs(float(x @ x) - 0.25) < 0.05 and abs(x[1]) > 0


def test_a_non_lyapunov_ellipse_is_never_proved():
    # a stable system whose flow leaves a thin ellipse across its long sides
    A = np.array([[-0.1, 1.0], [-1.0, -0.1]])
    system = linear_system(A, np.array([[1.0, 0.0]]))
    proof = inv.prove_region(system, sublevel(system, "x1**2 + 25*x2**2", 0.2),
                             system.X, BUDGET)
    assert proof.status != Status.PROVED


def test_a_sublevel_set_that_reaches_the_boundary_of_x_is_not_proved_inside():
    system = linear_system(-np.eye(2), np.array([[1.0, 0.0]]))
    region = Region("sublevel", V_text="x1**2 + x2**2", level=1.2,
                    V=sublevel(system, "x1**2 + x2**2", 0.5).V, symbols=tuple(system.symbols))
    proof = inv.prove_region(system, region, system.X, BUDGET)
    assert proof.status == Status.UNKNOWN and "boundary of X" in proof.message


# ----------------------------------------------------------------------------- finding R

def _simulate(system):
    return lambda x0, dt, steps: simulate_plant(system, x0, dt=dt, steps=steps).numpy()


def test_the_van_der_pol_cycle_gets_a_proved_polygon_around_it():
    system = load_system("vdp")
    att = inv.locate_attractor(system, system.X, _simulate(system))
    assert att.kind == "cycle"
    assert np.allclose(np.abs(att.box).max(1), [2.0086, 2.6784], atol=2e-3)
    region, how = next(inv.candidates(system, att, system.X))
    assert region.kind == "polygon" and len(region.vertices) == inv.POLYGON_EDGES[0]
    proof = inv.prove_region(system, region, system.X, BUDGET)
    assert proof.status == Status.PROVED, proof.message
    # around the cycle, and close to it
    assert np.all(proof.hull[:, 1] > [2.0086, 2.6784])
    assert np.all(proof.hull[:, 1] < [2.2, 2.9])
    assert outward_speed(system, region.vertices, 201) < 0


def test_an_equilibrium_gets_a_proved_lyapunov_ellipse():
    A = np.array([[0.0, 1.0], [-1.0, -0.4]])
    system = linear_system(A, np.array([[1.0, 0.0]]), X=np.array([[-1.0, 1.0], [-2.0, 2.0]]))
    att = inv.locate_attractor(system, system.X, _simulate(system))
    assert att.kind == "equilibrium" and np.abs(att.point).max() < 1e-9
    region, _ = next(inv.candidates(system, att, system.X))
    proof = inv.prove_region(system, region, system.X, BUDGET)
    assert proof.status == Status.PROVED
    assert np.all(proof.hull[:, 0] > system.X[:, 0]) and np.all(proof.hull[:, 1] < system.X[:, 1])
