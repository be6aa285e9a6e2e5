"""The invariance check: a region inside X proved (found, or the spec's), the spec's region
refused with a witness when the flow leaves it, and the plant's attractor located (leaving
vdp's box, with a box suggested that holds it)."""

from __future__ import annotations

import numpy as np

from certify.checks.invariance import check_invariance, suggested_box
from certify.results import Status
from certify.spec.system import System, load_system


def test_vdp_attractor_leaves_its_box_and_a_box_that_holds_it_is_suggested():
    r = check_invariance(load_system("vdp"))
    assert r.status == Status.UNKNOWN and r.attractor == "cycle" and r.attractor_leaves_box
    att = np.asarray(r.attractor_box)
    assert np.allclose(np.abs(att).max(1), [2.0086, 2.6784], atol=2e-3)
    box = np.asarray(r.suggested_box)
    assert np.all(box[:, 0] < att[:, 0]) and np.all(box[:, 1] > att[:, 1])
    assert box.tolist() == [[-2.5, 2.5], [-3.3, 3.3]]
    # a polygon around the cycle is proved invariant, but it is not inside X
    assert r.candidates[0]["status"] == "PROVED"
    assert "not inside X" in r.message and "a box that holds it" in r.message


def test_vdp_wide_has_a_proved_region_inside_its_box():
    system = load_system("vdp_wide")
    r = check_invariance(system)
    assert r.status == Status.PROVED, r.message
    assert r.region["kind"] == "polygon" and r.region["origin"] == "found"
    hull = np.asarray(r.hull)
    assert np.all(hull[:, 0] > system.X[:, 0]) and np.all(hull[:, 1] < system.X[:, 1])
    assert not r.attractor_leaves_box and r.suggested_box is None
    assert r.margin is not None and r.margin < 0
    assert np.allclose(r.output_range, hull[:1])  # h = x1


SPEC = """
name = "spiral"
states = ["x1", "x2"]
outputs = ["y"]
f = ["-0.2*x1 + x2", "-x1 - 0.2*x2"]
h = ["x1"]

[box]
X = [[-2, 2], [-2, 2]]
Y = [[-2, 2]]

[invariance]
"""


def test_the_specs_region_is_used_and_refused_with_a_witness():
    # a box the rotation leaves through its faces
    r = check_invariance(System.from_text(SPEC + "box = [[-1, 1], [-1, 1]]\n", "spec s"))
    assert r.status == Status.VIOLATED and r.region["origin"] == "spec"
    assert r.witness is not None and np.isclose(np.abs(r.witness).max(), 1.0)
    assert r.candidates[0]["how"] == "given by the spec"
    # a circle is invariant for the contracting spiral
    ok = check_invariance(System.from_text(SPEC + 'V = "x1**2 + x2**2"\nlevel = 1.0\n',
                                           "spec s"))
    assert ok.status == Status.PROVED and ok.region["kind"] == "sublevel"
    assert np.allclose(np.asarray(ok.hull), [[-1, 1], [-1, 1]], atol=0.05)


def test_an_equilibrium_gets_an_ellipse_and_a_chaotic_attractor_none():
    spiral = System.from_text(SPEC.replace("[invariance]\n", ""), "spec s")
    r = check_invariance(spiral)
    assert r.status == Status.PROVED and r.attractor == "equilibrium"
    assert r.region["kind"] == "sublevel" and r.region["origin"] == "found"
    lorenz = check_invariance(load_system("lorenz"))
    assert lorenz.status == Status.UNKNOWN and lorenz.attractor == "other"
    assert "no invariant region" in lorenz.message


def test_the_suggested_box_rounds_outwards():
    box = suggested_box(np.array([[-2.0086, 2.0086], [0.1234, 0.4567]]))
    assert box.tolist() == [[-2.5, 2.5], [0.09, 0.5]]  # 0.4567 + 0.0333 = 0.49003 -> 0.5
