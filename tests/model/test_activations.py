"""Activations: enclosures and relaxations contain every sampled value; refusals say why.

The reference values are mpmath (50 digits) from independent closed forms, plus the float64
point formulas. Intervals are drawn at several scales (degenerate, tiny, moderate, wide) and
far into the tails.
"""

from __future__ import annotations

import math

import mpmath as mp
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.intervals import Interval
from certify.model.activations import get, names
from certify.model.activations.base import Activation

from ..soak import examples

mp.mp.dps = 50
F64 = torch.float64
SETTINGS = settings(max_examples=examples(12), deadline=None)
NAMES = ["tanh", "sigmoid", "softplus", "silu", "elu", "gelu"]


def _sig(x: mp.mpf) -> mp.mpf:
    return 1 / (1 + mp.exp(-x))


def _phi(x: mp.mpf) -> mp.mpf:
    return mp.exp(-x * x / 2) / mp.sqrt(2 * mp.pi)


def _Phi(x: mp.mpf) -> mp.mpf:
    return mp.erfc(-x / mp.sqrt(2)) / 2


# independent closed forms: name -> (f, f', f'' (a list of admissible values: ELU at 0), f''')
REF = {
    "tanh": (mp.tanh, lambda x: mp.sech(x) ** 2,
             lambda x: [-2 * mp.tanh(x) * mp.sech(x) ** 2],
             lambda x: -2 * mp.sech(x) ** 2 * (1 - 3 * mp.tanh(x) ** 2)),
    "sigmoid": (_sig, lambda x: _sig(x) * _sig(-x),
                lambda x: [_sig(x) * _sig(-x) * (_sig(-x) - _sig(x))],
                lambda x: _sig(x) * _sig(-x) * (1 - 6 * _sig(x) + 6 * _sig(x) ** 2)),
    "softplus": (lambda x: mp.log1p(mp.exp(x)), _sig, lambda x: [_sig(x) * _sig(-x)],
                 lambda x: _sig(x) * _sig(-x) * (1 - 2 * _sig(x))),
    "silu": (lambda x: x * _sig(x), lambda x: _sig(x) * (1 + x * _sig(-x)),
             lambda x: [_sig(x) * _sig(-x) * (2 + x * (_sig(-x) - _sig(x)))],
             lambda x: mp.diff(lambda t: t * _sig(t), x, 3)),
    "elu": (lambda x: x if x > 0 else mp.expm1(x), lambda x: 1 if x > 0 else mp.exp(x),
            lambda x: [0] if x > 0 else ([mp.exp(x), 0] if x == 0 else [mp.exp(x)]),
            lambda x: 0 if x > 0 else mp.exp(x)),
    "gelu": (lambda x: x * _Phi(x), lambda x: _Phi(x) + x * _phi(x),
             lambda x: [_phi(x) * (2 - x * x)], lambda x: _phi(x) * x * (x * x - 4)),
}


def _intervals(seed: int, B: int, scale: float, far: bool = False
               ) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    span = 700.0 if far else 8.0
    c = (2 * torch.rand(B, generator=g, dtype=F64) - 1) * span
    r = scale * torch.rand(B, generator=g, dtype=F64)
    return c - r, c + r


def _samples(lo: torch.Tensor, hi: torch.Tensor, act: Activation, k: int, seed: int
             ) -> torch.Tensor:
    """[B, k + 2 + crit] points in [lo, hi]: endpoints, random, and critical points inside."""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(lo.shape[0], k, generator=g, dtype=F64)
    pts = [lo[:, None], hi[:, None], lo[:, None] + (hi - lo)[:, None] * t]
    for order in range(3):
        for c in act.critical[order]:
            pts.append(torch.clamp(torch.full_like(lo, c.x), lo, hi)[:, None])
    return torch.cat(pts, 1)


def _mp_inside(lo: float, hi: float, v: mp.mpf) -> bool:
    return mp.mpf(float(lo)) <= v <= mp.mpf(float(hi))


def _check_enclosures(act: Activation, lo: torch.Tensor, hi: torch.Tensor, seed: int,
                      mp_points: int = 8) -> None:
    a = Interval(lo, hi)
    encl = [act.enclose_f(a), act.enclose_d1(a), act.enclose_d2(a)]
    for e in encl:
        assert bool((e.lo <= e.hi).all())
        assert not bool(torch.isnan(e.lo).any() | torch.isnan(e.hi).any())
    x = _samples(lo, hi, act, 16, seed)
    point = [act.f(x), act.d1(x), act.d2(x)]
    for order, (e, v) in enumerate(zip(encl, point)):
        inside = (e.lo[:, None] <= v) & (v <= e.hi[:, None])
        assert bool(inside.all()), (act.name, order, x[~inside][:3], v[~inside][:3])
    slope_lo, slope_hi = act.slope_range(a)
    assert torch.equal(slope_lo, encl[1].lo) and torch.equal(slope_hi, encl[1].hi)
    ref = REF[act.name]
    for b in range(min(mp_points, lo.shape[0])):
        for xv in x[b].tolist():
            xm = mp.mpf(xv)
            assert _mp_inside(encl[0].lo[b], encl[0].hi[b], ref[0](xm)), (act.name, 0, xv)
            assert _mp_inside(encl[1].lo[b], encl[1].hi[b], ref[1](xm)), (act.name, 1, xv)
            for v2 in ref[2](xm):
                assert _mp_inside(encl[2].lo[b], encl[2].hi[b], v2), (act.name, 2, xv)


@pytest.mark.parametrize("name", NAMES)
@SETTINGS
@given(seed=st.integers(0, 10**6), scale=st.sampled_from([0.0, 1e-9, 1e-3, 0.5, 3.0, 30.0]))
@pytest.mark.slow
def test_enclosures_contain_sampled_values(name: str, seed: int, scale: float) -> None:
    _check_enclosures(get(name), *_intervals(seed, 48, scale), seed=seed)


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=examples(5), deadline=None)
@given(seed=st.integers(0, 10**6), scale=st.sampled_from([0.0, 1.0, 50.0]))
def test_enclosures_far_in_the_tails(name: str, seed: int, scale: float) -> None:
    _check_enclosures(get(name), *_intervals(seed, 24, scale, far=True), seed=seed,
                      mp_points=4)


def _check_relaxation(act: Activation, order: int, lo: torch.Tensor, hi: torch.Tensor,
                      seed: int) -> None:
    lb = act.relax(lo, hi) if order == 0 else act.relax_d1(lo, hi)
    for t in (lb.lower_slope, lb.lower_icpt, lb.upper_slope, lb.upper_icpt):
        assert t.shape == lo.shape and bool(torch.isfinite(t).all())
    x = _samples(lo, hi, act, 16, seed)
    v = act.f(x) if order == 0 else act.d1(x)
    # float64 lines and point formulas err (1 - tanh^2 cancels): 1e-14 relative + 4 ulps of
    # 1 absolute; the mpmath check below is exact
    low = lb.lower_slope[:, None] * x + lb.lower_icpt[:, None]
    upp = lb.upper_slope[:, None] * x + lb.upper_icpt[:, None]
    tol = 1e-14 * (x.abs() * lb.upper_slope.abs()[:, None] + lb.upper_icpt.abs()[:, None]
                   + v.abs()) + 4 * 2.0**-52
    assert bool((low <= v + tol).all()) and bool((v <= upp + tol).all()), act.name
    ref = REF[act.name][order]
    for b in range(min(6, lo.shape[0])):
        for xv in x[b].tolist():
            xm, fx = mp.mpf(xv), ref(mp.mpf(xv))
            assert mp.mpf(lb.lower_slope[b].item()) * xm + mp.mpf(lb.lower_icpt[b].item()) <= fx
            assert fx <= mp.mpf(lb.upper_slope[b].item()) * xm + mp.mpf(lb.upper_icpt[b].item())


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("order", [0, 1])
@SETTINGS
@given(seed=st.integers(0, 10**6), scale=st.sampled_from([0.0, 1e-6, 0.3, 2.0, 20.0]))
def test_relaxations_are_sound(name: str, order: int, seed: int, scale: float) -> None:
    _check_relaxation(get(name), order, *_intervals(seed, 48, scale), seed=seed)


@pytest.mark.parametrize("name", NAMES)
def test_relaxation_is_tight_on_small_intervals(name: str) -> None:
    """Width 1e-3: the gap between the lines is second order (a chord is nearly exact)."""
    act = get(name)
    lo = torch.linspace(-5, 5, 41, dtype=F64)
    lb = act.relax(lo, lo + 1e-3)
    gap = (lb.upper_icpt - lb.lower_icpt).max().item()
    assert gap < 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_extrema_inside_the_interval_are_exact(name: str) -> None:
    """Around each critical point the enclosure is the exact range (dense grid), to 1e-9:
    the interior extremum is taken, not just the endpoints; the constants match mpmath."""
    act = get(name)
    point = (act.f, act.d1, act.d2)
    for order in range(3):
        for c in act.critical[order]:
            lo, hi = c.x - 0.3, c.x + 0.2
            e = act._enclose(order, Interval(torch.tensor([lo], dtype=F64),
                                             torch.tensor([hi], dtype=F64)))
            grid = point[order](torch.linspace(lo, hi, 200_001, dtype=F64))
            assert abs(e.lo.item() - grid.min().item()) < 1e-9, (name, order, c)
            assert abs(e.hi.item() - grid.max().item()) < 1e-9, (name, order, c)
            ref = REF[name][order](mp.mpf(c.x))
            for v in (ref if isinstance(ref, list) else [ref]):
                assert _mp_inside(c.lo, c.hi, mp.mpf(v))
            assert c.hi - c.lo < 1e-13 or name == "elu"


@pytest.mark.parametrize("name", NAMES)
def test_critical_points_are_complete(name: str) -> None:
    """g' changes sign only at the listed critical points (dense float64 grid on [-30, 30])."""
    act = get(name)
    x = torch.linspace(-30, 30, 600_001, dtype=F64)
    derivs = [act.d1(x), act.d2(x), None]
    for order in (0, 1):
        d = derivs[order]
        s = torch.sign(d)
        flips = torch.nonzero((s[1:] * s[:-1]) < 0).flatten()
        where = x[flips]
        listed = torch.tensor([c.x for c in act.critical[order]], dtype=F64)
        big = d[flips].abs() > 1e-12  # ignore noise where g' underflows in the tails
        for w in where[big].tolist():
            assert listed.numel() and bool(((listed - w).abs() < 1e-3).any()), (name, order, w)


@pytest.mark.parametrize("name", NAMES)
def test_global_slope_and_third_derivative_bounds(name: str) -> None:
    act = get(name)
    e = act.enclose_d1(Interval(torch.tensor([-60.0], dtype=F64), torch.tensor([60.0],
                                                                           dtype=F64)))
    lo, hi = act.slope_bounds
    assert lo - 1e-12 <= e.lo.item() and e.hi.item() <= hi + 1e-12
    assert e.lo.item() <= lo + 1e-9 and e.hi.item() >= hi - 1e-9
    xs = [mp.mpf(i) / 20 for i in range(-200, 201) if i != 0 or name != "elu"]
    assert max(abs(REF[name][3](x)) for x in xs) <= act.d3_bound


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.slow
def test_point_values_module_and_autograd(name: str, dtype: torch.dtype) -> None:
    act = get(name)
    x = torch.linspace(-7, 7, 301, dtype=dtype).requires_grad_(True)
    y = act.f(x)
    (g,) = torch.autograd.grad(y.sum(), x, create_graph=True)
    (g2,) = torch.autograd.grad(g.sum(), x)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    xd = x.detach()
    assert torch.allclose(g, act.d1(xd), atol=tol)
    keep = xd != 0  # ELU's f'' jumps at 0
    assert torch.allclose(g2[keep], act.d2(xd)[keep], atol=tol)
    f1, d1 = act.f_and_d1(xd)
    assert torch.allclose(f1, act.f(xd), atol=tol) and torch.allclose(d1, act.d1(xd), atol=tol)
    assert torch.allclose(act.torch_module()(xd), act.f(xd), atol=tol)
    assert act.f(xd).dtype == dtype


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=examples(40), deadline=None)
@given(st.lists(st.floats(-800.0, 800.0, allow_nan=False), min_size=1, max_size=40))
def test_numpy_form_equals_the_torch_form(name: str, values: list[float]) -> None:
    """`f_array` (the simulation's NumPy form) gives `f`'s values to a few ulps, also far in
    the tails (no overflow to NaN), on float64 arrays of any shape."""
    import numpy as np

    act = get(name)
    x = np.array(values, dtype=np.float64).reshape(-1, 1)
    with np.errstate(all="raise", under="ignore"):
        got = act.f_array(x)
    assert isinstance(got, np.ndarray) and got.shape == x.shape and got.dtype == np.float64
    want = act.f(torch.from_numpy(x))
    torch.testing.assert_close(torch.from_numpy(got), want, rtol=4e-15, atol=1e-300)


@pytest.mark.parametrize("name, why", [("relu", "jumps at 0"), ("ReLU", "jumps at 0"),
                                       ("leaky_relu", "jumps"), ("LeakyReLU", "jumps"),
                                       ("hardtanh", "jumps at -1 and 1"), ("selu", "jumps")])
def test_non_c1_activations_are_refused_with_the_reason(name: str, why: str) -> None:
    with pytest.raises(ValueError) as err:
        get(name)
    msg = str(err.value)
    assert why in msg and "D would be discontinuous" in msg and "Theorem 1 needs a C^1 gain" in msg


def test_unknown_activation_lists_the_supported_ones() -> None:
    with pytest.raises(ValueError, match="unknown activation 'mish'; supported: elu, gelu, "
                                         "sigmoid, silu, softplus, tanh"):
        get("mish")
    assert names() == sorted(NAMES)
    assert get("Swish") is get("silu") and get(" TANH ") is get("tanh")


def test_nan_gives_nan_not_a_bound() -> None:
    nan = torch.tensor([math.nan], dtype=F64)
    for name in NAMES:
        e = get(name).enclose_d1(Interval(nan, nan))
        assert bool(torch.isnan(e.lo).all() or torch.isnan(e.hi).all()), name
