"""Enclosure soundness, property-based: every enclosure contains the float64 point value."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import lam_max_upper_interval, lam_max_upper_point, rho_upper
from certify.arith.intervals import ROUNDING, Interval, ipow_int, ipow_real
from certify.enclose.mpdi import mpdi_box_bounds
from certify.enclose.network_interval import gain_enclosure
from certify.enclose.options import Technique, box_bound_options
from certify.enclose.preconditioner import make_preconditioner, to_lam_max_D
from certify.enclose.taylor import jcl_taylor
from certify.errors import SpecError
from certify.model import activations
from certify.model.activations.tanh import d2tanh_enclosure, dtanh_enclosure
from certify.model.kernels import gain_terms, mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.spec.enclosures import (
    h_enclosure,
    hessian_f_enclosure,
    hessian_f_point,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
)
from certify.spec.expr import DERIVED_FUNCTIONS, FUNCTIONS
from certify.spec.interval_rules import INTERVAL, RULES, enclose_function
from certify.spec.system import System, load_system

from ..soak import examples

SETTINGS = settings(max_examples=examples(20), deadline=None)
ACT_SETTINGS = settings(max_examples=examples(4), deadline=None)  # per activation
ACTIVATIONS = activations.names()
F64 = torch.float64

SPEC3 = """
name = "three"
states = ["a", "b", "c"]
outputs = ["y1", "y2"]
f = ["b + 0.1*sin(a)*c", "-a - b + cos(c)*0.3 + exp(-a**2)/4",
     "-c + tanh(a*b) - 0.2*sqrt(1 + b**2) + log(2 + a)/5"]
h = ["a", "c + 0.1*a"]
[box]
X = [[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]]
Y = [[-1.0, 1.0], [-1.2, 1.2]]
[design]
lam = 0.2
"""


def three_state() -> System:
    return System.from_text(SPEC3, origin="test three")


def _boxes(seed: int, B: int, lo: np.ndarray, hi: np.ndarray, scale: float
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    lo_t = torch.as_tensor(lo, dtype=F64)
    w = torch.as_tensor(hi - lo, dtype=F64)
    c = lo_t + w * torch.rand(B, len(lo), generator=g, dtype=F64)
    r = scale * w * torch.rand(B, len(lo), generator=g, dtype=F64)
    blo = torch.maximum(c - r, lo_t)
    bhi = torch.minimum(c + r, lo_t + w)
    pts = blo + (bhi - blo) * torch.rand(B, len(lo), generator=g, dtype=F64)
    return blo, bhi, pts


def _inside(lo: torch.Tensor, hi: torch.Tensor, v: torch.Tensor) -> bool:
    return bool(((lo <= v) & (v <= hi)).all())


# ----- the function table ----------------------------------------------------------------
def test_table_covers_whitelist_and_quotes_rounding() -> None:
    assert set(RULES) == set(FUNCTIONS) | set(DERIVED_FUNCTIONS)
    for name, rule in RULES.items():
        assert rule.point is {**FUNCTIONS, **DERIVED_FUNCTIONS}[name][1]
    assert "nextafter" in ROUNDING and "LAPACK" in ROUNDING


def test_missing_rule_names_the_function() -> None:
    x = Interval(torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64))
    with pytest.raises(SpecError, match="'erf'"):
        enclose_function("erf", x)


@SETTINGS
@given(name=st.sampled_from(sorted(RULES)), seed=st.integers(0, 10_000),
       center=st.floats(-20, 20), width=st.floats(1e-9, 8.0))
def test_rules_contain_point_values(name: str, seed: int, center: float, width: float) -> None:
    g = torch.Generator().manual_seed(seed)
    lo = center + torch.rand(64, generator=g, dtype=F64) * 0.1
    if name in ("log", "sqrt"):
        lo = lo.abs() + 1e-6
    hi = lo + width * torch.rand(64, generator=g, dtype=F64)
    iv = RULES[name].enclose(Interval(lo, hi))
    t = torch.rand(64, 200, generator=g, dtype=F64)
    x = lo[:, None] + (hi - lo)[:, None] * t
    x = torch.cat([x, lo[:, None], hi[:, None]], 1)
    v = RULES[name].point(x)
    ok = torch.isnan(iv.lo)[:, None] | ((iv.lo[:, None] <= v) & (v <= iv.hi[:, None]))
    ok = ok | ~torch.isfinite(v)  # tan at a pole
    assert bool(ok.all()), name


def test_sin_cos_extrema_inside() -> None:
    x = Interval(torch.tensor([1.0, 3.0], dtype=F64), torch.tensor([2.0, 3.5], dtype=F64))
    s = RULES["sin"].enclose(x)
    c = RULES["cos"].enclose(x)
    assert float(s.hi[0]) == 1.0  # pi/2 inside [1, 2]
    assert float(c.lo[1]) == -1.0  # pi inside [3, 3.5]
    t = RULES["tan"].enclose(x)
    assert math.isinf(float(t.hi[0]))  # pole at pi/2


@SETTINGS
@given(k=st.integers(-4, 7), lo=st.floats(-3, 3), w=st.floats(0, 3))
def test_integer_powers(k: int, lo: float, w: float) -> None:
    a = torch.tensor([lo], dtype=F64)
    iv = ipow_int(Interval(a, a + w), k)
    x = torch.linspace(lo, lo + w, 501, dtype=F64)
    with np.errstate(all="ignore"):
        v = x**k if k >= 0 else 1.0 / x ** (-k)
    v = v[torch.isfinite(v)]
    assert _inside(iv.lo, iv.hi, v) or bool(torch.isinf(iv.lo) | torch.isinf(iv.hi))


def test_even_power_dependency() -> None:
    iv = ipow_int(Interval(torch.tensor([-1.0], dtype=F64), torch.tensor([2.0], dtype=F64)), 2)
    assert float(iv.lo) == 0.0 and float(iv.hi) >= 4.0


@SETTINGS
@given(e=st.floats(-2.5, 2.5).filter(lambda e: not float(e).is_integer()),
       lo=st.floats(0.01, 3), w=st.floats(0, 3))
def test_real_powers(e: float, lo: float, w: float) -> None:
    a = torch.tensor([lo], dtype=F64)
    iv = ipow_real(Interval(a, a + w), e)
    x = torch.linspace(lo, lo + w, 501, dtype=F64)
    assert _inside(iv.lo, iv.hi, x**e)


def test_real_power_of_negative_is_nan() -> None:
    iv = ipow_real(Interval(torch.tensor([-1.0], dtype=F64), torch.tensor([1.0], dtype=F64)), 0.5)
    assert bool(torch.isnan(iv.lo).all())


def test_dtanh_interval_containing_zero_has_max_one() -> None:
    iv = dtanh_enclosure(Interval(torch.tensor([-0.5], dtype=F64), torch.tensor([2.0], dtype=F64)))
    assert float(iv.hi) == 1.0  # endpoint evaluation alone would give 1 - tanh(0.5)^2 < 1
    assert float(iv.lo) <= 1 - math.tanh(2.0) ** 2


@SETTINGS
@given(lo=st.floats(-6, 6), w=st.floats(0, 6))
def test_tanh_derivatives(lo: float, w: float) -> None:
    a = torch.tensor([lo], dtype=F64)
    x = torch.linspace(lo, lo + w, 2001, dtype=F64)
    t = torch.tanh(x)
    d1 = dtanh_enclosure(Interval(a, a + w))
    d2 = d2tanh_enclosure(Interval(a, a + w))
    assert _inside(d1.lo, d1.hi, 1 - t * t)
    assert _inside(d2.lo, d2.hi, -2 * t * (1 - t * t))


# ----- f, h and their derivatives ---------------------------------------------------------
@pytest.mark.parametrize("name", ["vdp", "duffing", "three"])
@SETTINGS
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-6, 1e-2, 0.3, 1.0]))
@pytest.mark.slow
def test_system_enclosures(name: str, seed: int, scale: float) -> None:
    s = three_state() if name == "three" else load_system(name)
    lo, hi, x = _boxes(seed, 64, s.X[:, 0], s.X[:, 1], scale)
    for enc, point in ((jacobian_f_enclosure, s.jac_f), (jacobian_h_enclosure, s.jac_h),
                       (h_enclosure, s.h), (hessian_f_enclosure,
                                            lambda z: hessian_f_point(s, z))):
        a, b = enc(s, lo, hi)
        assert _inside(a, b, point(x)), enc.__name__


def test_interval_algebra_constants_are_widened() -> None:
    like = Interval(torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64))
    c = INTERVAL.const(0.1, like)
    assert float(c.lo) < 0.1 < float(c.hi) or float(c.lo) < float(c.hi)
    two = INTERVAL.const(2.0, like)
    assert float(two.lo) == float(two.hi) == 2.0


# ----- network, gain terms, D, eigenvalue bounds ------------------------------------------
def random_problem(seed: int, structure: str, system: System | None = None,
                   hidden: tuple[int, ...] = (5, 4, 3), with_K: bool = True,
                   metric: bool = False, activation: str = "tanh") -> Problem:
    torch.manual_seed(seed)
    s = system or load_system("vdp")
    K = torch.randn(s.n, s.p) if with_K else None
    net = GainNetwork(s.n, s.p, hidden, structure=structure, K=K, activation=activation)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(1.5)
    P = np.eye(s.n)
    if metric:
        R = np.random.default_rng(seed).normal(size=(s.n, s.n))
        P = R @ R.T + 0.5 * np.eye(s.n)
    return Problem(s, net, 0.3, P)


def _root(prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    box = np.concatenate([prob.system.X, prob.system.Y])
    return box[:, 0], box[:, 1]


@pytest.mark.parametrize("act", ACTIVATIONS)
@ACT_SETTINGS
@given(seed=st.integers(0, 10_000), structure=st.sampled_from(["direct", "structural"]),
       with_K=st.booleans(), scale=st.sampled_from([1e-5, 1e-2, 0.1, 0.5]),
       three=st.booleans())
def test_gain_enclosure_contains_points(act: str, seed: int, structure: str, with_K: bool,
                                        scale: float, three: bool) -> None:
    prob = random_problem(seed, structure, three_state() if three else None, with_K=with_K,
                          activation=act)
    s, net = prob.system, prob.network
    n = s.n
    lo, hi, z = _boxes(seed, 32, *_root(prob), scale)
    ge, _ = gain_enclosure(s, net, lo, hi, order=2)
    zr = z.clone().requires_grad_(True)
    terms = gain_terms(s, net, zr[:, :n], zr[:, n:])
    assert _inside(ge.k.lo, ge.k.hi, terms.k.detach())
    assert _inside(ge.dk_dx.lo, ge.dk_dx.hi, terms.dk_dx.detach())
    assert _inside(ge.dk_dy.lo, ge.dk_dy.hi, terms.dk_dy.detach())
    # second derivatives d2k_i / dx_j dz_m by autograd
    rows = []
    for i in range(n):
        for j in range(n):
            (g,) = torch.autograd.grad(terms.dk_dx[:, i, j].sum(), zr, retain_graph=True)
            rows.append(g)
    d2 = torch.stack(rows, 1).reshape(-1, n, n, z.shape[1])
    tol = 1e-9 * (1 + d2.abs())  # autograd's own rounding
    assert bool(((ge.d2k.lo - tol <= d2) & (d2 <= ge.d2k.hi + tol)).all())


@pytest.mark.parametrize("act", ACTIVATIONS)
@ACT_SETTINGS
@given(seed=st.integers(0, 10_000), structure=st.sampled_from(["direct", "structural"]),
       scale=st.sampled_from([1e-6, 1e-3, 0.05, 0.3]), three=st.booleans())
def test_taylor_model_contains_closed_loop_jacobian(act: str, seed: int, structure: str,
                                                    scale: float, three: bool) -> None:
    prob = random_problem(seed, structure, three_state() if three else None, activation=act)
    s, net = prob.system, prob.network
    n = s.n
    lo, hi, z = _boxes(seed, 32, *_root(prob), scale)
    tm = jcl_taylor(s, net, lo, hi)
    zc = 0.5 * (lo + hi)
    J = s.jac_f(z[:, :n]) + gain_terms(s, net, z[:, :n], z[:, n:]).dk_dx
    lin = tm.c + torch.einsum("bijd,bd->bij", tm.g, z - zc)
    slack = 1e-12 * (1 + J.abs())  # the float evaluation of J itself
    assert bool(((J - lin).abs() <= tm.e + slack).all())


@pytest.mark.parametrize("act", ACTIVATIONS)
@settings(max_examples=examples(12), deadline=None)
@given(seed=st.integers(0, 10_000), centre=st.floats(-6, 6),
       rad=st.sampled_from([1e-8, 1e-3, 0.1, 0.7, 2.0]), with_e=st.booleans())
def test_activation_taylor_models_contain_f_and_df(act: str, seed: int, centre: float,
                                                   rad: float, with_e: bool) -> None:
    """f(q) and f'(q) of a Taylor model q lie in the models `tm_activation` builds (second-
    order remainders with d3_bound; for ELU the first-order remainder of f')."""
    from certify.arith.taylor import TM
    from certify.model.gain.taylor import tm_activation

    a = activations.get(act)
    g = torch.Generator().manual_seed(seed)
    B, h, d = 8, 5, 3
    r = rad * torch.rand(B, d, generator=g, dtype=F64)
    c = centre + torch.randn(B, h, generator=g, dtype=F64)
    c[:, 0] = 0.0  # ELU's kink, the critical points of the others nearby
    gco = torch.randn(B, h, d, generator=g, dtype=F64)
    e = (rad * torch.rand(B, h, generator=g, dtype=F64)) if with_e else torch.zeros(B, h,
                                                                                    dtype=F64)
    A, S = tm_activation(a, TM(c, gco, e), r)
    u = 2 * torch.rand(B, 200, d, generator=g, dtype=F64) - 1
    u[:, :2] = torch.stack([-torch.ones(B, d, dtype=F64), torch.ones(B, d, dtype=F64)], 1)
    dz = u * r[:, None]
    sgn = 2 * torch.rand(B, 200, h, generator=g, dtype=F64) - 1
    sgn[:, :2] = torch.sign(sgn[:, :2])
    q = c[:, None] + torch.einsum("bhd,bsd->bsh", gco, dz) + sgn * e[:, None]
    for tm, fn in ((A, a.f), (S, a.d1)):
        v = fn(q)
        lin = tm.c[:, None] + torch.einsum("bhd,bsd->bsh", tm.g, dz)
        assert bool(((v - lin).abs() <= tm.e[:, None] + 1e-14 * (1 + v.abs())).all())
    # the remainders are second order (first order for f' of ELU) in the radius
    if rad <= 1e-3 and not with_e:
        assert float(A.e.max()) < 1e-9 + 100 * rad ** 2 * float((gco.abs().sum(-1)).max()) ** 2


@pytest.mark.parametrize("act", ACTIVATIONS)
@ACT_SETTINGS
@given(seed=st.integers(0, 10_000), structure=st.sampled_from(["direct", "structural"]),
       scale=st.sampled_from([1e-6, 1e-3, 0.05, 0.3]), three=st.booleans(),
       metric=st.booleans(), taylor=st.sampled_from([True, "interval", False]))
@pytest.mark.slow
def test_mpdi_box_bound_is_sound(act: str, seed: int, structure: str, scale: float,
                                 three: bool, metric: bool, taylor: object) -> None:
    prob = random_problem(seed, structure, three_state() if three else None, metric=metric,
                          activation=act)
    s, net = prob.system, prob.network
    n = s.n
    lo, hi, _ = _boxes(seed, 16, *_root(prob), scale)
    bb = mpdi_box_bounds(box_bound_options(prob, prob.lam, technique=Technique.of(taylor)),
                         lo, hi)
    pc = make_preconditioner(prob.P_t)
    ub = to_lam_max_D(bb.upper, prob.P_t, pc)
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(16, 300, lo.shape[1], generator=g, dtype=F64)
    pts = (lo[:, None] + (hi - lo)[:, None] * t).reshape(-1, lo.shape[1])
    corners = torch.where(t[:, :8] > 0.5, hi[:, None], lo[:, None]).reshape(-1, lo.shape[1])
    allp = torch.cat([pts, corners])
    v = mpdi_lam_max(s, net, prob.P_t, prob.lam, allp[:, :n], allp[:, n:])
    vmax = torch.cat([v[: 16 * 300].reshape(16, 300), v[16 * 300:].reshape(16, 8)], 1).amax(1)
    assert bool((torch.isnan(ub) | (vmax <= ub + 1e-12 * (1 + vmax.abs()))).all())


@SETTINGS
@given(seed=st.integers(0, 10_000), n=st.integers(1, 5), rad=st.floats(0, 2))
def test_lam_max_bounds(seed: int, n: int, rad: float) -> None:
    g = torch.Generator().manual_seed(seed)
    C = torch.randn(8, n, n, generator=g, dtype=F64)
    C = 0.5 * (C + C.transpose(1, 2))
    R = rad * torch.rand(8, n, n, generator=g, dtype=F64)
    R = 0.5 * (R + R.transpose(1, 2))
    A = Interval(C - R, C + R)
    ub = lam_max_upper_interval(A)
    for _ in range(20):
        T = (2 * torch.rand(8, n, n, generator=g, dtype=F64) - 1) * R
        S = C + 0.5 * (T + T.transpose(1, 2))
        assert bool((torch.linalg.eigvalsh(S)[:, -1] <= ub).all())
    assert bool((torch.linalg.eigvalsh(C)[:, -1] <= lam_max_upper_point(C)).all())
    rho = torch.linalg.eigvals(R).abs().amax(-1)
    assert bool((rho <= rho_upper(R) * (1 + 1e-12)).all())
