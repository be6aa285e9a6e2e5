"""Backward linear bound propagation: every enclosure contains the sampled float64 values."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.enclose.crown import (
    forward_bounds,
    jacobian_crown,
    network_crown_tms,
    to_tm,
    value_crown,
)
from certify.enclose.mpdi import mpdi_box_bounds
from certify.enclose.options import box_bound_options
from certify.enclose.preconditioner import make_preconditioner, to_lam_max_D
from certify.model import activations
from certify.model.kernels import mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.spec.system import load_system

from ..soak import examples

F64 = torch.float64
SETTINGS = settings(max_examples=examples(8), deadline=None)
ACT_SETTINGS = settings(max_examples=examples(2), deadline=None)  # per activation
ACTIVATIONS = activations.names()


def _net(seed: int, d_in: int, depth: int, width: int, g: float, act: str = "tanh"
         ) -> GainNetwork:
    """A direct MLP with d_in inputs and d_in - 1 outputs, weights N(0, g^2 / fan_in)."""
    gen = torch.Generator().manual_seed(seed)
    net = GainNetwork(d_in - 1, 1, (width,) * depth, activation=act)
    with torch.no_grad():
        for layer in net.layers:
            fan = layer.weight.shape[1]
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen) * g / fan**0.5)
            layer.bias.copy_(0.3 * torch.randn(layer.bias.shape, generator=gen))
    return net.double()


def _boxes(seed: int, B: int, d: int, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed + 1)
    c = 2 * torch.rand(B, d, generator=gen, dtype=F64) - 1
    r = scale * torch.rand(B, d, generator=gen, dtype=F64)
    r[0] = 0.0  # a degenerate box
    return c - r, c + r


def _points(lo: torch.Tensor, hi: torch.Tensor, S: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed + 2)
    u = torch.rand(lo.shape[0], S, lo.shape[1], generator=gen, dtype=F64)
    u[:, :2] = torch.stack([torch.zeros_like(lo), torch.ones_like(lo)], 1)  # two corners
    return lo[:, None] + (hi - lo)[:, None] * u


@pytest.mark.parametrize("act", ACTIVATIONS)
@ACT_SETTINGS
@given(seed=st.integers(0, 10_000), depth=st.integers(1, 4), g=st.sampled_from([0.5, 2.0, 4.0]),
       scale=st.sampled_from([1e-7, 1e-3, 0.03, 0.3, 1.0]), d=st.integers(2, 5))
def test_jacobian_and_value_enclosures_contain_points(act: str, seed: int, depth: int, g: float,
                                                      scale: float, d: int) -> None:
    net = _net(seed, d, depth, 7, g, act)
    lo, hi = _boxes(seed, 12, d, scale)
    cols = list(range(d))
    fb = forward_bounds(net, lo, hi, cols=cols)
    z = _points(lo, hi, 150, seed)
    B, S, _ = z.shape
    val, jac = net.forward_with_jacobian(z.reshape(-1, d))
    val = val.reshape(B, S, -1)
    jac = jac.reshape(B, S, -1, d)
    dz = z - 0.5 * (lo + hi)[:, None]
    # intermediate ranges: checked through the final enclosures below and directly here
    for le, vals, sel in ((jacobian_crown(net, lo, hi, cols, fb), jac, "bsij"),
                          (value_crown(net, lo, hi, fb), val, "bsi")):
        gl = le.gl[:, None]
        gu = le.gu[:, None]
        low = (gl * dz.reshape(B, S, *([1] * (gl.ndim - 3)), d)).sum(-1) + le.cl[:, None]
        upp = (gu * dz.reshape(B, S, *([1] * (gu.ndim - 3)), d)).sum(-1) + le.cu[:, None]
        tol = 1e-13 * (1 + vals.abs())  # the float evaluation of the lines here
        assert bool((low <= vals + tol).all()), sel
        assert bool((vals <= upp + tol).all()), sel
    tm = to_tm(jacobian_crown(net, lo, hi, cols, fb), fb.r)
    lin = tm.c[:, None] + torch.einsum("bijd,bsd->bsij", tm.g, dz)
    assert bool(((jac - lin).abs() <= tm.e[:, None] + 1e-13 * (1 + jac.abs())).all())
    vt, jt, _ = network_crown_tms(net, lo, hi, cols, value=True)
    lin = jt.c[:, None] + torch.einsum("bijd,bsd->bsij", jt.g, dz)
    assert bool(((jac - lin).abs() <= jt.e[:, None] + 1e-13 * (1 + jac.abs())).all())
    linv = vt.c[:, None] + torch.einsum("bid,bsd->bsi", vt.g, dz)
    assert bool(((val - linv).abs() <= vt.e[:, None] + 1e-13 * (1 + val.abs())).all())
    # intermediate pre-activation ranges contain the sampled pre-activations
    Ws = [(W.double(), b.double()) for W, b in net.weights()]
    pre = z.reshape(-1, d) @ Ws[0][0].T + Ws[0][1]
    for li, (W, b) in enumerate(Ws[1:]):
        p = pre.reshape(B, S, -1)
        assert bool(((fb.pre[li].lo[:, None] <= p) & (p <= fb.pre[li].hi[:, None])).all())
        pre = net.act.f(pre) @ W.T + b


def test_crown_is_much_tighter_than_taylor_models_on_a_deep_network() -> None:
    net = _net(3, 3, 5, 30, 2.0)
    lo, hi = _boxes(3, 16, 3, 0.0)
    lo, hi = lo - 0.01, hi + 0.01
    fb = forward_bounds(net, lo, hi, cols=[0, 1])
    tm = to_tm(jacobian_crown(net, lo, hi, [0, 1], fb), fb.r)
    assert float(tm.e.median()) * 10 < float(fb.jac_tm.e[..., :2].median())


@pytest.mark.parametrize("act", ACTIVATIONS)
@ACT_SETTINGS
@given(seed=st.integers(0, 10_000), structure=st.sampled_from(["direct", "structural"]),
       scale=st.sampled_from([1e-6, 1e-3, 0.05, 0.3]), metric=st.booleans())
def test_mpdi_bound_with_crown_is_sound(act: str, seed: int, structure: str, scale: float,
                                       metric: bool) -> None:
    torch.manual_seed(seed)
    s = load_system("vdp")
    net = GainNetwork(2, 1, (6, 5), structure=structure, K=torch.randn(2, 1), activation=act)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(2.0)
    P = np.eye(2)
    if metric:
        R = np.random.default_rng(seed).normal(size=(2, 2))
        P = R @ R.T + 0.5 * np.eye(2)
    prob = Problem(s, net, 0.3, P)
    box = np.concatenate([s.X, s.Y])
    gen = torch.Generator().manual_seed(seed)
    c = torch.as_tensor(box[:, 0]) + torch.rand(8, 3, generator=gen, dtype=F64) * torch.as_tensor(
        box[:, 1] - box[:, 0])
    lo, hi = c - scale, c + scale
    pc = make_preconditioner(prob.P_t)
    bb = mpdi_box_bounds(box_bound_options(prob, prob.lam, pc=pc, crown=True), lo, hi)
    ub = to_lam_max_D(bb.upper, prob.P_t, pc)
    z = _points(lo, hi, 300, seed).reshape(-1, 3)
    v = mpdi_lam_max(s, prob.network, prob.P_t, prob.lam, z[:, :2], z[:, 2:]).reshape(8, -1)
    vmax = v.amax(1)
    assert bool((torch.isnan(ub) | (vmax <= ub + 1e-12 * (1 + vmax.abs()))).all())


@SETTINGS
@given(seed=st.integers(0, 10_000), n=st.integers(1, 6), rad=st.sampled_from([0.0, 1e-3, 0.3, 2.0]))
def test_hertz_bound_is_sound_and_never_above_centre_plus_radius(seed: int, n: int,
                                                                  rad: float) -> None:
    from certify.arith.eigen import hertz_upper, lam_max_upper_point, rho_upper

    g = torch.Generator().manual_seed(seed)
    C = torch.randn(16, n, n, generator=g, dtype=F64)
    C = 0.5 * (C + C.transpose(1, 2))
    R = rad * torch.rand(16, n, n, generator=g, dtype=F64)
    R = 0.5 * (R + R.transpose(1, 2))
    ub = hertz_upper(C, R)
    T = (2 * torch.rand(16, 200, n, n, generator=g, dtype=F64) - 1) * R[:, None]
    corner = torch.rand(16, 200, n, n, generator=g, dtype=F64) < 0.3
    T = torch.where(corner, T.sign() * R[:, None], T)
    S = C[:, None] + 0.5 * (T + T.transpose(-1, -2))
    assert bool((torch.linalg.eigvalsh(S)[..., -1].amax(1) <= ub).all())
    weyl = lam_max_upper_point(C) + rho_upper(R)
    assert bool((ub <= weyl + 1e-9 * (1 + weyl.abs())).all())


@pytest.mark.parametrize("act", ACTIVATIONS)
@settings(max_examples=examples(2), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-6, 1e-2, 0.1, 0.5]),
       g=st.sampled_from([1.0, 3.0]))
@pytest.mark.slow
def test_side_bounds_with_crown_contain_points(act: str, seed: int, scale: float,
                                               g: float) -> None:
    from certify.enclose.side import dk_dy_box_upper_crown, residual_box_upper_crown
    from certify.model.kernels import gain_terms

    torch.manual_seed(seed)
    s = load_system("vdp")
    net = GainNetwork(2, 1, (7, 7, 7), K=torch.randn(2, 1), activation=act)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(g)
    net = net.double()
    gen = torch.Generator().manual_seed(seed)
    box = torch.as_tensor(np.concatenate([s.X, s.Y]))
    c = box[:, 0] + torch.rand(8, 3, generator=gen, dtype=F64) * (box[:, 1] - box[:, 0])
    lo, hi = c - scale, c + scale
    z = _points(lo, hi, 200, seed)  # [8, 200, 3]
    ub, _ = dk_dy_box_upper_crown(s, net, lo, hi)
    flat = z.reshape(-1, 3)
    dky = gain_terms(s, net, flat[:, :2], flat[:, 2:]).dk_dy  # [N, 2, 1]
    nrm = torch.linalg.matrix_norm(dky, ord=2).reshape(8, -1).amax(1)
    assert bool((nrm <= ub * (1 + 1e-12)).all())
    ub_r, _ = residual_box_upper_crown(s, net, lo[:, :2], hi[:, :2])
    xz = _points(lo[:, :2], hi[:, :2], 200, seed).reshape(-1, 2)
    k = gain_terms(s, net, xz, s.h(xz)).k
    res = k.norm(dim=-1).reshape(8, -1).amax(1)
    assert bool((res <= ub_r * (1 + 1e-12) + 1e-300).all())


@settings(max_examples=examples(12), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-4, 1e-2, 0.1, 0.5]))
@pytest.mark.slow
def test_residual_norm_bound_holds_at_every_vertex_and_beats_the_entrywise_bound(
        seed: int, scale: float) -> None:
    """The residual's linear-bound norm is the vertex maximum of its linear part
    (`_tm_frobenius_upper` on k as an [n, 1] matrix): it contains ||k(x, h(x))|| at all
    four corners and at random points of each box, and is never above the entrywise bound
    (each component at its own worst vertex), which it replaced."""
    from certify.arith.intervals import gamma, up
    from certify.enclose.crown import AffineInputNetwork, forward_bounds, to_tm, value_crown
    from certify.enclose.side import _tm_mag, residual_box_upper_crown
    from certify.model.kernels import gain_terms

    torch.manual_seed(seed)
    s = load_system("vdp")
    net = GainNetwork(2, 1, (9, 9), activation="tanh").double()
    gen = torch.Generator().manual_seed(seed)
    X = torch.as_tensor(s.X)
    c = X[:, 0] + torch.rand(16, 2, generator=gen, dtype=F64) * (X[:, 1] - X[:, 0])
    lo, hi = c - scale, c + scale
    corners = torch.tensor([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]], dtype=F64)
    u = torch.cat([corners.expand(16, 4, 2), torch.rand(16, 60, 2, generator=gen, dtype=F64)], 1)
    x = (lo[:, None] + (hi - lo)[:, None] * u).reshape(-1, 2)
    k = gain_terms(s, net, x, s.h(x), with_dy=False).k
    worst = k.norm(dim=-1).reshape(16, -1).amax(1)
    ub, _ = residual_box_upper_crown(s, net, lo, hi)
    assert bool((worst <= ub * (1 + 1e-12)).all())
    # the entrywise form, as before
    A = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]], dtype=F64)
    vnet = AffineInputNetwork(net, A, torch.zeros(3, dtype=F64))
    fb = forward_bounds(vnet, lo, hi, cols=[], crown=True,
                        b0_slack=vnet.first_layer_slack(lo, hi), taylor=False)
    vt = to_tm(value_crown(vnet, lo, hi, fb), fb.r)
    mag = _tm_mag(vt.c, vt.g, vt.e, fb.r.unsqueeze(1))
    entrywise = up(torch.sqrt(up((mag * mag).sum(-1) * (1.0 + 2.0 * gamma(3)))))
    assert bool((ub <= entrywise).all())
