"""Linear relaxations of the activations, their derivatives and products: every line bounds
every sampled value."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.intervals import Interval
from certify.enclose.relax import (
    _combine,
    _Ends,
    _piece_extrema,
    _piece_extrema_where,
    mccormick,
    relax_dtanh,
    relax_slope,
    relax_tanh,
    relax_value,
)
from certify.model import activations

from ..soak import examples

F64 = torch.float64
SETTINGS = settings(max_examples=examples(40), deadline=None)


def _slack(v: torch.Tensor) -> torch.Tensor:
    return 8 * 2.0**-53 * (1 + v.abs())  # the float evaluation of a x + b and of f(x) itself


def _check(relax, f, lo: torch.Tensor, hi: torch.Tensor) -> None:
    lb = relax(lo, hi)
    t = torch.linspace(0, 1, 401, dtype=F64)
    x = lo[:, None] + (hi - lo)[:, None] * t[None]
    x = torch.cat([x, lo[:, None], hi[:, None]], 1)
    v = f(x)
    low = lb.lower_slope[:, None] * x + lb.lower_icpt[:, None]
    upp = lb.upper_slope[:, None] * x + lb.upper_icpt[:, None]
    assert bool((low <= v + _slack(v)).all()), float((low - v).max())
    assert bool((v <= upp + _slack(v)).all()), float((v - upp).max())
    assert bool((lb.lower_icpt <= lb.upper_icpt).all())


@SETTINGS
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-12, 1e-4, 0.1, 1.0, 4.0, 20.0]),
       centre=st.floats(-8, 8))
@pytest.mark.slow
def test_tanh_and_dtanh_relaxations_are_sound(seed: int, scale: float, centre: float) -> None:
    g = torch.Generator().manual_seed(seed)
    a = centre + scale * torch.randn(64, generator=g, dtype=F64)
    b = a + scale * torch.rand(64, generator=g, dtype=F64)
    b[:4] = a[:4]  # degenerate intervals
    _check(relax_tanh, torch.tanh, a, b)
    _check(relax_dtanh, lambda x: 1 - torch.tanh(x) ** 2, a, b)


@pytest.mark.parametrize("name", activations.names())
@settings(max_examples=examples(6), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-12, 1e-4, 0.1, 1.0, 4.0, 20.0]),
       centre=st.floats(-8, 8))
def test_prover_relaxations_of_every_activation_are_sound(name: str, seed: int, scale: float,
                                                          centre: float) -> None:
    """What the linear bound propagation uses for f and f' (tanh's own, else the
    activation's generic lines): parallel, and bounding every sampled value."""
    act = activations.get(name)
    g = torch.Generator().manual_seed(seed)
    a = centre + scale * torch.randn(64, generator=g, dtype=F64)
    b = a + scale * torch.rand(64, generator=g, dtype=F64)
    b[:4] = a[:4]  # degenerate intervals
    for relax, f in ((relax_value, act.f), (relax_slope, act.d1)):
        lb = relax(act, a, b)
        assert torch.equal(lb.lower_slope, lb.upper_slope)
        _check(lambda lo, hi, r=relax: r(act, lo, hi), f, a, b)


def test_relaxations_are_tight_on_small_intervals() -> None:
    lo = torch.linspace(-3, 3, 61, dtype=F64)
    hi = lo + 1e-3
    for relax in (relax_tanh, relax_dtanh):
        lb = relax(lo, hi)
        assert float((lb.upper_icpt - lb.lower_icpt).max()) < 1e-6  # O(w^2) gap


@SETTINGS
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-9, 0.1, 1.0, 30.0]))
def test_mccormick_is_sound(seed: int, scale: float) -> None:
    g = torch.Generator().manual_seed(seed)
    sl = scale * torch.randn(32, generator=g, dtype=F64)
    su = sl + scale * torch.rand(32, generator=g, dtype=F64)
    tl = scale * torch.randn(32, generator=g, dtype=F64)
    tu = tl + scale * torch.rand(32, generator=g, dtype=F64)
    bb = mccormick(Interval(sl, su), Interval(tl, tu))
    u = torch.rand(32, 500, 2, generator=g, dtype=F64)
    u[:, :4] = torch.tensor([[0, 0], [0, 1], [1, 0], [1, 1]], dtype=F64)
    s = sl[:, None] + (su - sl)[:, None] * u[..., 0]
    t = tl[:, None] + (tu - tl)[:, None] * u[..., 1]
    lin = bb.slope_s[:, None] * s + bb.slope_t[:, None] * t
    v = s * t
    tol = 8 * 2.0**-53 * (v.abs() + lin.abs() + 1e-300)
    assert bool((lin + bb.lower_icpt[:, None] <= v + tol).all())
    assert bool((v <= lin + bb.upper_icpt[:, None] + tol).all())


@SETTINGS
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-9, 0.1, 1.0, 30.0]))
def test_mccormick_of_a_point_factor_is_exact_to_an_ulp(seed: int, scale: float) -> None:
    """t a point (the first layer's tangent): the planes hold at sampled s and their
    intercepts are -sc t to an ulp on each side (no corner slack)."""
    g = torch.Generator().manual_seed(seed)
    sl = scale * torch.randn(32, generator=g, dtype=F64)
    su = sl + scale * torch.rand(32, generator=g, dtype=F64)
    t = scale * torch.randn(32, generator=g, dtype=F64)
    bb = mccormick(Interval(sl, su), Interval(t, t.clone()))
    s = sl[:, None] + (su - sl)[:, None] * torch.rand(32, 200, generator=g, dtype=F64)
    lin = bb.slope_s[:, None] * s + bb.slope_t[:, None] * t[:, None]
    v = s * t[:, None]
    tol = 8 * 2.0**-53 * (v.abs() + lin.abs() + 1e-300)
    assert bool((lin + bb.lower_icpt[:, None] <= v + tol).all())
    assert bool((v <= lin + bb.upper_icpt[:, None] + tol).all())
    exact = -(0.5 * (sl + su)) * t
    assert bool((bb.lower_icpt <= exact).all()) and bool((exact <= bb.upper_icpt).all())
    assert bool((bb.upper_icpt - bb.lower_icpt <= 4 * 2.0**-52 * exact.abs() + 1e-300).all())


def test_dtanh_critical_points_solve_the_cubic_on_their_pieces() -> None:
    """`_dtanh_crit` (closed form) returns, per piece of known curvature, the x where
    tanh''(x) = a when the piece has one: it only places the tangent of the sound bound,
    so a wrong root costs tightness; this pins that it is the right root."""
    import math

    from certify.enclose.relax import _C_D1, _dtanh_crit

    gmax = 4.0 / (3.0 * math.sqrt(3.0))
    a = torch.linspace(-0.999 * gmax, 0.999 * gmax, 2001, dtype=F64)
    x_left, x_mid, x_right = _dtanh_crit(a)

    def d2(x: torch.Tensor) -> torch.Tensor:
        t = torch.tanh(x)
        return -2.0 * t * (1.0 - t * t)

    assert bool((x_mid.abs() <= _C_D1 + 1e-9).all())
    assert float((d2(x_mid) - a).abs().max()) < 1e-9
    pos, neg = a > 1e-3, a < -1e-3  # a root on the left (right) convex piece
    assert bool((x_left[pos] <= -_C_D1 + 1e-9).all()) and bool((x_right[neg] >= _C_D1 - 1e-9).all())
    assert float((d2(x_left[pos]) - a[pos]).abs().max()) < 1e-9
    assert float((d2(x_right[neg]) - a[neg]).abs().max()) < 1e-9
    # no root on a piece: the point lies beyond the piece's far end (clamped there later)
    assert bool((x_left[neg] <= -15).all()) and bool((x_right[pos] >= 15).all())


def test_point_enclosures_match_the_general_path() -> None:
    """A point interval (lo is hi) takes one libm call; the enclosure is bit-identical to
    the general path's (lo and hi equal but distinct tensors)."""
    from certify.model.activations.tanh import d2tanh_enclosure, dtanh_enclosure, tanh_enclosure

    g = torch.Generator().manual_seed(3)
    x = torch.cat([torch.randn(500, generator=g, dtype=F64) * s for s in (0.01, 1.0, 30.0)]
                  + [torch.tensor([0.0, -0.0, 25.0, -40.0], dtype=F64)])
    for enc in (tanh_enclosure, dtanh_enclosure, d2tanh_enclosure):
        fast, general = enc(Interval(x, x)), enc(Interval(x, x.clone()))
        assert torch.equal(fast.lo, general.lo) and torch.equal(fast.hi, general.hi)


@settings(max_examples=examples(20), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-9, 0.1, 1.0, 5.0]),
       centre=st.floats(-4, 4), kind=st.sampled_from(["tanh", "dtanh"]))
def test_pieces_on_the_elements_that_meet_them_equal_the_full_evaluation(
        seed: int, scale: float, centre: float, kind: str) -> None:
    """`_piece_extrema_where` (each curvature piece evaluated only on the intervals that meet
    it) gives bit for bit what evaluating every piece on every interval gives, once the
    pieces are combined: the same intercepts."""
    gen = torch.Generator().manual_seed(seed)
    lo = centre + scale * torch.randn(300, generator=gen, dtype=F64)
    hi = lo + scale * torch.rand(300, generator=gen, dtype=F64)
    a = 0.3 * torch.randn(300, generator=gen, dtype=F64)
    x0 = lo + (hi - lo) * torch.rand(300, generator=gen, dtype=F64)
    ends = _Ends(kind, lo, hi)
    pieces = [(-math.inf, -0.7, True, x0), (-0.7, -0.6, None, None), (-0.6, 0.6, False, x0),
              (0.6, math.inf, True, x0)]
    full = _combine([_piece_extrema(ends, a, p, q, c, x) for p, q, c, x in pieces])
    some = _combine([_piece_extrema_where(ends, a, p, q, c, x) for p, q, c, x in pieces])
    assert torch.equal(full[0], some[0]) and torch.equal(full[1], some[1])
