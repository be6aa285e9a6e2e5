"""Taylor models of Jf and dh/dx (`certify.enclose.system_taylor`): they contain the sampled
Jacobians, the second-order form reaches the exact remainder on quadratic entries, and an
expression undefined on a box leaves NaN."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.intervals import Interval, up
from certify.arith.taylor import tm_from_intervals
from certify.enclose.system_taylor import jacobian_tm, quadratic_enclosure
from certify.spec.enclosures import hessian_f_enclosure, jacobian_f_enclosure, pad_y
from certify.spec.system import System, load_system

from ..soak import examples

F64 = torch.float64
SETTINGS = settings(max_examples=examples(20), deadline=None)

SPEC = """
name = "curvy"
states = ["a", "b", "c"]
outputs = ["y1", "y2"]
f = ["b + 0.1*sin(a)*c**2", "-a - b + cos(c)*0.3 + exp(-a**2)/4 + a*b*c",
     "-c + tanh(a*b) - 0.2*sqrt(1 + b**2) + log(2 + a)/5"]
h = ["a + 0.2*sin(b)", "c**3 + 0.1*a*c"]
[box]
X = [[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]]
Y = [[-1.0, 1.0], [-1.2, 1.2]]
[design]
lam = 0.2
"""


def _system(name: str) -> System:
    return System.from_text(SPEC, origin="test curvy") if name == "curvy" else load_system(name)


def _boxes(s: System, seed: int, B: int, scale: float):
    """B random sub-boxes of X x Y (radius up to `scale` of the root) and 32 points in each."""
    g = torch.Generator().manual_seed(seed)
    root = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=F64)
    w = root[:, 1] - root[:, 0]
    c = root[:, 0] + w * torch.rand(B, len(w), generator=g, dtype=F64)
    r = scale * w * torch.rand(B, len(w), generator=g, dtype=F64)
    lo, hi = torch.maximum(c - r, root[:, 0]), torch.minimum(c + r, root[:, 1])
    u = torch.rand(B, 32, len(w), generator=g, dtype=F64)
    pts = lo[:, None] + (hi - lo)[:, None] * u
    pts[:, 0], pts[:, 1] = lo, hi  # two vertices
    return lo, hi, pts


@pytest.mark.parametrize("name", ["vdp", "duffing", "vdp3", "curvy"])
@pytest.mark.parametrize("which", ["f", "h"])
@SETTINGS
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-6, 1e-2, 0.1, 0.5]))
@pytest.mark.slow
def test_jacobian_tm_contains_sampled_jacobians(name: str, which: str, seed: int,
                                               scale: float) -> None:
    s = _system(name)
    lo, hi, pts = _boxes(s, seed, 24, scale)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    tm = jacobian_tm(s, which, lo, hi, r)
    B, P, d = pts.shape
    x = pts[..., : s.n].reshape(-1, s.n)
    J = (s.jac_f(x) if which == "f" else s.jac_h(x)).reshape(B, P, *tm.c.shape[1:])
    lin = tm.c[:, None] + torch.einsum("b...d,bpd->bp...", tm.g, pts - zc[:, None])
    e = tm.e[:, None]
    slack = 1e-12 * (J.abs() + 1.0)  # the float evaluation of the model's affine part
    assert bool(((J - lin).abs() <= e + slack).all())
    assert bool(torch.isfinite(tm.e).all())


def test_second_order_remainder_is_exact_on_van_der_pol() -> None:
    """Jf = [[0, 1], [-1 - 2 mu x1 x2, mu (1 - x1^2)]]: the remainders of the quadratic
    entries are 2 mu r1 r2 and mu r1^2 / 2 (the mean-value form's are 4 mu r1 r2 and
    2 mu r1^2)."""
    s = load_system("vdp")
    mu = 1.0
    lo = torch.tensor([[-0.3, 0.2, -1.0], [0.5, -0.9, 0.0]], dtype=F64)
    hi = lo + torch.tensor([[0.2, 0.1, 0.5], [0.1, 0.3, 0.5]], dtype=F64)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    tm = jacobian_tm(s, "f", lo, hi, r)
    r1, r2 = r[:, 0], r[:, 1]
    assert torch.allclose(tm.e[:, 1, 0], 2 * mu * r1 * r2, rtol=1e-9, atol=1e-15)
    assert torch.allclose(tm.e[:, 1, 1], mu * r1**2 / 2, rtol=1e-9, atol=1e-15)
    # the mean-value form it replaces, for comparison
    xc = zc[:, :2]
    mv = tm_from_intervals(Interval(*jacobian_f_enclosure(s, xc, xc)),
                           pad_y(Interval(*hessian_f_enclosure(s, lo[:, :2], hi[:, :2])), 1), r)
    assert torch.allclose(mv.e[:, 1, 0], 4 * mu * r1 * r2, rtol=1e-9)
    assert bool((tm.e <= mv.e).all())


def test_quadratic_enclosure_is_none_for_linear_and_quadratic_systems() -> None:
    s = System.from_text(SPEC.replace(
        'f = ["b + 0.1*sin(a)*c**2", "-a - b + cos(c)*0.3 + exp(-a**2)/4 + a*b*c",\n'
        '     "-c + tanh(a*b) - 0.2*sqrt(1 + b**2) + log(2 + a)/5"]',
        'f = ["b", "-a - b + a*b", "-c + a**2"]'), origin="test quadratic")
    lo = torch.zeros(3, 3, dtype=F64)
    assert quadratic_enclosure(s, "f", lo, lo + 0.1, lo + 0.05) is None
    assert quadratic_enclosure(s, "h", lo, lo + 0.1, lo + 0.05) is not None  # c**3


def test_undefined_third_derivative_gives_nan_not_a_model() -> None:
    """sqrt(a + 1.5) is undefined left of a = -1.5 (outside the spec's box, which the spec
    check guards): on a box reaching past it the entry's remainder is NaN (neither form is a
    model there), and on a box inside the domain it is finite."""
    s = System.from_text(SPEC.replace('"b + 0.1*sin(a)*c**2"', '"b + sqrt(a + 1.5)*c"'),
                         origin="test sqrt")
    lo = torch.tensor([[-1.7, 0.0, 0.0, 0.0, 0.0], [-0.5, 0.0, 0.0, 0.0, 0.0]], dtype=F64)
    hi = lo + 0.3
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    tm = jacobian_tm(s, "f", lo, hi, r)
    assert bool(torch.isnan(tm.e[0, 0]).any())
    assert bool(torch.isfinite(tm.e[1]).all())
