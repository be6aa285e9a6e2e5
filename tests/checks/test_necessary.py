"""Pre-flight necessary condition (METHOD §3.5): known answers for the built-ins, n x p."""

from __future__ import annotations

import numpy as np
import pytest

from certify.checks.necessary import check_necessary
from certify.design.manifold import vertex_upper_bound
from certify.design.metric import synthesize_metric
from certify.errors import SpecError
from certify.results import NecessaryResult, Status, from_jsonable, to_jsonable
from certify.spec.system import System, load_system

from ..conftest import SPEC_3X2


@pytest.mark.slow
def test_vdp_identity_metric_fails_with_known_numbers():
    lam = 2.5
    r = check_necessary(load_system("vdp"), np.eye(2), lam)
    assert r.status is Status.VIOLATED
    assert r.witness[0] == pytest.approx(0.0, abs=1e-6)  # worst at x1 = 0
    assert r.witness_y == [r.witness[0]]
    assert r.q_max == pytest.approx(1 + 2 * lam, abs=1e-9)
    assert r.rate_cap == pytest.approx(-0.5, abs=1e-9)
    assert r.residual_price == pytest.approx(3 * (1 + 2 * lam), rel=1e-6)  # = 18
    assert "no continuously differentiable gain" in r.explanation
    assert from_jsonable(NecessaryResult, to_jsonable(r)).q_max == r.q_max


@pytest.mark.slow
def test_duffing_identity_metric_fails():
    r = check_necessary(load_system("duffing"), np.eye(2), 2.5)
    assert r.status is Status.VIOLATED
    assert r.q_max == pytest.approx(5.0, abs=1e-9)
    assert r.rate_cap == pytest.approx(0.0, abs=1e-9)
    assert r.residual_price == pytest.approx(5.0, rel=1e-6)


@pytest.mark.slow
def test_vdp_with_synthesised_metric_is_proved():
    system = load_system("vdp")
    m = synthesize_metric(system, 2.5)
    r = check_necessary(system, np.array(m.P), 2.5)
    assert r.status is Status.PROVED
    assert r.q_upper is not None and r.q_max <= r.q_upper <= 0
    assert r.rate_cap >= 2.5


def test_vertex_bound_is_an_upper_bound():
    system = load_system("vdp")
    ub = vertex_upper_bound(system, np.eye(2), 2.5)
    assert ub >= 6.0  # the true max q


@pytest.mark.slow
def test_three_states_two_outputs():
    """ker C = span(e_b); with P = I, q = df_b/db + 2 lam = -0.5 + 2 lam everywhere."""
    system = System.from_text(SPEC_3X2, origin="test")  # h linear: ker C = span(e_b)
    bad = check_necessary(system, np.eye(3), 0.5, grid_points=20_000)
    assert bad.status is Status.VIOLATED
    assert bad.q_max == pytest.approx(0.5, abs=1e-9)
    assert bad.rate_cap == pytest.approx(0.25, abs=1e-9)
    assert bad.residual_price == pytest.approx(0.5 * 3.0 / 2.0, rel=1e-6)  # chord b in [-1.5, 1.5]
    assert len(bad.witness) == 3 and len(bad.witness_y) == 2
    good = check_necessary(system, np.eye(3), 0.2, grid_points=20_000)
    assert good.status is Status.PROVED and good.q_upper <= 0
    assert good.q_max == pytest.approx(-0.1, abs=1e-9)


@pytest.mark.slow
def test_three_states_nonlinear_output():
    """h = (a + 0.2 b^2, c): ker dh = span((-0.4 b, 1, 0)); at b = 0 it is e_b again, where
    q = -0.5 + 2 lam = 0.5 > 0 (P = I, lam = 0.5): a witness must be found."""
    spec = SPEC_3X2.replace('h = ["a", "c + 0.1*a"]', 'h = ["a + 0.2*b**2", "c"]')
    spec = spec.replace("[-1.2, 1.2], [-1.3, 1.3]", "[-1.5, 1.5], [-1.3, 1.3]")
    system = System.from_text(spec, origin="test")
    assert not system.h_is_linear
    r = check_necessary(system, np.eye(3), 0.5, grid_points=8_000)
    assert r.status is Status.VIOLATED and r.q_max >= 0.5 - 1e-9
    assert len(r.witness_y) == 2 and r.residual_price is None


def test_malformed_input_refused():
    system = load_system("vdp")
    with pytest.raises(ValueError):
        check_necessary(system, np.eye(2), -1.0)
    with pytest.raises(SpecError):
        check_necessary(system, np.array([[1.0, 2.0], [2.0, 1.0]]), 2.5)  # not PD
