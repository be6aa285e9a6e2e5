"""Error bounds: Theorem 3 as stated, the ISS bound and its metric variant (METHOD §3.6-3.7)."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.checks.bounds import check_bounds
from certify.errors import SettingsError
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.error_bound import bound_curve, initial_value, ultimate_bound_per_unit_noise
from certify.results import BoundsResult, Status, from_jsonable, to_jsonable
from certify.spec.system import load_system

from ..soak import examples

REL = 1e-10


@functools.lru_cache(maxsize=1)
def _vdp():
    return load_system("vdp")


def problem(P=None) -> Problem:
    return Problem(_vdp(), GainNetwork(2, 1, (4,)), 2.5, np.eye(2) if P is None else np.asarray(P))


def test_iss_closed_form_identity_metric():
    # lam = 0.5, eps = 0.2, L = 2, vbar = 0.15: c = 0.2 + 0.3 = 0.5, c/(2 lam) = 0.5
    r = check_bounds(problem(), lam_cert=0.5, eps_bar=0.2, L=2.0, vbar=0.15)
    assert r.status == Status.PROVED
    iss = r.iss
    assert iss.applicable and iss.rate == pytest.approx(1.0, rel=REL)
    assert iss.bias == pytest.approx(0.5, rel=REL) and iss.bias >= 0.5
    assert iss.bias_per_unit_noise == pytest.approx(2.0, rel=REL)
    assert iss.gain == pytest.approx(1.0, rel=REL) and iss.gain >= 1.0
    t = np.linspace(0, 5, 11)
    e0 = 1.7
    want = np.exp(-t) * e0 + (1 - np.exp(-t)) * 0.5
    got = bound_curve(r, "iss", e0, t)
    np.testing.assert_allclose(got, want, rtol=REL)
    assert np.all(got >= want)  # rounded outward, never inward
    # vectorised over starts
    assert bound_curve(r, "iss", np.array([1.0, 2.0, 3.0]), t).shape == (3, 11)


def test_iss_with_metric_hand_numbers():
    # P = diag(4, 1): lam_min = 1, ||P^(1/2)|| = 2, kappa = 4
    P = np.diag([4.0, 1.0])
    r = check_bounds(problem(P), lam_cert=1.0, eps_bar=0.1, L=1.0, vbar=0.2)
    assert r.status == Status.PROVED
    assert r.kappa_P == pytest.approx(4.0, rel=REL)
    # c = 2 (0.1 + 0.2) = 0.6; bias = c / (2 lam) / sqrt(lam_min) = 0.3
    assert r.iss.bias == pytest.approx(0.3, rel=REL)
    assert r.iss.rate == pytest.approx(2.0)
    e0 = np.array([0.5, 1.0])
    W0 = initial_value("iss", e0, P)
    assert W0 == pytest.approx(math.sqrt(4 * 0.25 + 1.0), rel=REL)
    t = np.array([0.0, 0.3, 2.0])
    want = np.exp(-2 * t) * W0 + (1 - np.exp(-2 * t)) * 0.3
    np.testing.assert_allclose(bound_curve(r, "iss", W0, t), want, rtol=REL)
    # the comparison-table number is the same ultimate bound
    u = ultimate_bound_per_unit_noise(lam_cert=1.0, eps_bar=0.1, L=1.0, vbar=0.2,
                                      kappa_P=r.kappa_P)
    assert u == pytest.approx(0.3, rel=REL)
    # Theorem 3 is for P = I only
    assert not r.theorem3.applicable and "P = I" in r.theorem3.reason


def test_theorem3_hand_numbers():
    # lam = 3: eta = 1; bias = (0.1 + 2 * 0.15) / 2 = 0.2
    r = check_bounds(problem(), lam_cert=3.0, eps_bar=0.1, L=2.0, vbar=0.15)
    th = r.theorem3
    assert th.applicable
    assert th.rate == pytest.approx(1.0) and th.gain == 1.0
    assert th.bias == pytest.approx(0.2, rel=REL)
    assert th.bias_per_unit_noise == pytest.approx(1.0, rel=REL)
    t = np.array([0.0, 1.0])
    np.testing.assert_allclose(bound_curve(r, "theorem3", 2.0, t),
                               [2.2, 2 * math.exp(-1) + 0.2], rtol=REL)


@pytest.mark.parametrize("lam", [2.0, 1.5, 0.3])
def test_theorem3_not_applicable_at_or_below_two(lam):
    r = check_bounds(problem(), lam_cert=lam, eps_bar=0.1, L=1.0, vbar=0.15)
    assert not r.theorem3.applicable
    assert "<= 2" in r.theorem3.reason and f"{lam:.6g}" in r.theorem3.reason
    assert r.theorem3.bias is None
    with pytest.raises(ValueError, match="not applicable"):
        bound_curve(r, "theorem3", 1.0, np.array([0.0]))
    # the ISS bound needs only lam > 0
    assert r.iss.applicable and r.status == Status.PROVED


@settings(max_examples=examples(200), deadline=None)
@given(lam=st.floats(2.0001, 60.0), eps=st.floats(0.0, 10.0), L=st.floats(0.0, 50.0),
       vbar=st.floats(0.0, 2.0), e0=st.floats(0.0, 10.0))
@pytest.mark.slow
def test_iss_never_larger_than_theorem3(lam, eps, L, vbar, e0):
    r = check_bounds(problem(), lam_cert=lam, eps_bar=eps, L=L, vbar=vbar)
    assert r.theorem3.applicable and r.iss.applicable
    t = np.concatenate([[0.0], np.geomspace(1e-4, 50.0, 60)])
    iss = bound_curve(r, "iss", e0, t)
    th3 = bound_curve(r, "theorem3", e0, t)
    assert np.all(iss <= th3 * (1 + 1e-9) + 1e-12)
    assert r.iss.bias <= r.theorem3.bias * (1 + 1e-9) + 1e-15


def test_no_contraction_no_bound():
    """lam_cert <= 0 settles it: no bound exists (NOT APPLICABLE), not "unknown"."""
    r = check_bounds(problem(), lam_cert=-0.5, eps_bar=0.1, L=1.0, vbar=0.15)
    assert r.status == Status.NOT_APPLICABLE
    assert r.message.startswith("no error bound exists: lam_cert = -0.5 <= 0")
    assert not r.iss.applicable and not r.theorem3.applicable
    assert "lam_cert = -0.5 <= 0: no contraction was certified, so no bound exists" in r.iss.reason
    assert "no bound exists" in r.message


def test_bound_larger_than_the_box_is_valid_but_vacuous():
    """VdP's X = [-2, 2] x [-3, 3] has half-diagonal sqrt(13) = 3.606: a bound above it is
    flagged, in words and in the field; one below it is not."""
    big = check_bounds(problem(), lam_cert=0.5, eps_bar=0.0, L=40.0, vbar=0.15)  # bias 6
    assert big.status == Status.PROVED and big.iss.bias == pytest.approx(6.0)
    assert big.box_half_diagonal == pytest.approx(math.sqrt(13.0))
    assert big.vacuous and "valid but vacuous: larger than the box" in big.message
    small = check_bounds(problem(), lam_cert=0.5, eps_bar=0.0, L=20.0, vbar=0.15)  # bias 3
    assert small.status == Status.PROVED and not small.vacuous
    assert "vacuous" not in small.message
    # with lam_cert <= 0 and an invalid input too, it stays UNKNOWN
    bad = check_bounds(problem(), lam_cert=-1.0, eps_bar=float("nan"), L=1.0, vbar=0.15)
    assert bad.status == Status.UNKNOWN and not bad.vacuous


def test_missing_and_nonfinite_inputs():
    r = check_bounds(problem(), lam_cert=1.0, eps_bar=None, L=1.0, vbar=0.15)
    assert r.status == Status.SKIPPED and "eps_bar was not established" in r.iss.reason
    r = check_bounds(problem(), lam_cert=None, eps_bar=0.1, L=1.0, vbar=0.15)
    assert r.status == Status.SKIPPED and "lam_cert" in r.message
    r = check_bounds(problem(), lam_cert=1.0, eps_bar=0.1, L=float("nan"), vbar=0.15)
    assert r.status == Status.UNKNOWN and "not finite" in r.iss.reason
    r = check_bounds(problem(), lam_cert=float("inf"), eps_bar=0.1, L=1.0, vbar=0.15)
    assert r.status == Status.UNKNOWN
    r = check_bounds(problem(), lam_cert=1.0, eps_bar=-0.1, L=1.0, vbar=0.15)
    assert r.status == Status.UNKNOWN and "not a valid upper bound" in r.iss.reason
    for bad in (-0.1, float("nan"), None):
        with pytest.raises(SettingsError):
            check_bounds(problem(), lam_cert=1.0, eps_bar=0.1, L=1.0, vbar=bad)
    assert ultimate_bound_per_unit_noise(lam_cert=-1.0, eps_bar=0.1, L=1.0, vbar=0.1) is None
    assert ultimate_bound_per_unit_noise(lam_cert=1.0, eps_bar=None, L=1.0, vbar=0.1) is None


def test_metric_variant():
    P = np.array([[3.0, 1.0], [1.0, 2.0]])
    base = dict(lam_cert=1.0, eps_bar=0.2, L=1.5, vbar=0.15)
    r0 = check_bounds(problem(P), **base)
    assert not r0.iss_metric.applicable and "not computed" in r0.iss_metric.reason
    # with directly computed (smaller) constants the variant is sharper
    r = check_bounds(problem(P), **base, eps_bar_P=0.1, L_P=1.0)
    assert r.iss_metric.applicable
    lam_min = np.linalg.eigvalsh(P)[0]
    want = (0.1 + 1.0 * 0.15) / 2.0 / math.sqrt(lam_min)
    assert r.iss_metric.bias == pytest.approx(want, rel=1e-9)
    assert r.iss_metric.bias < r.iss.bias
    # with the sound fallbacks alone it equals the plain ISS bound
    r2 = check_bounds(problem(P), **base, eps_bar_P=None, L_P=1.0)
    assert r2.iss_metric.applicable and "eps_bar_P <= ||P^(1/2)|| eps_bar" in r2.iss_metric.reason
    r3 = check_bounds(problem(P), **base, eps_bar_P=float("nan"), L_P=1.0)
    assert not r3.iss_metric.applicable and r3.iss.applicable


def test_validity_conditions_words():
    g = check_bounds(problem(), lam_cert=1.0, eps_bar=0.1, L=1.0, vbar=0.15)
    loc = check_bounds(problem(), lam_cert=1.0, eps_bar=0.1, L=1.0, vbar=0.15, L_is_local=True)
    assert len(g.validity) == 4 and [c[:3] for c in g.validity] == ["(a)", "(b)", "(c)", "(d)"]
    assert "x1 in [-2, 2], x2 in [-3, 3]" in g.validity[0]
    assert "y in [-2, 2]" in g.validity[1]
    assert "vbar = 0.15" in g.validity[2] and "Gaussian" in g.validity[2]
    assert "not needed" in g.validity[3] and "global" in g.validity[3]
    assert "local" in loc.validity[3] and "stays in Y" in loc.validity[3]
    assert loc.L_is_local and not g.L_is_local


def test_json_round_trip():
    r = check_bounds(problem(), lam_cert=3.0, eps_bar=0.1, L=2.0, vbar=0.15, eps_bar_P=0.1,
                     L_P=2.0)
    back = from_jsonable(BoundsResult, to_jsonable(r))
    assert back == r
