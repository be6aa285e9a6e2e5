"""The prover's gain enclosures through `compose` equal the old hand-written ones.

`gain_enclosure` (intervals) and `network_taylor` / `jcl_taylor` (Taylor models) now run
`certify.model.gain.propagate` and `certify.model.gain.compose` with `IntervalArithmetic` /
`TaylorArithmetic`; the code they replaced is frozen below (kept only here). Every output
must match it bit for bit, except dk/dy of the interval gain, which `compose` forms as
dN/dy r + G (+ K) instead of summing G_il * 1 and K_il * 1 with their product and sum
rounding: there the new enclosure must lie inside the old one (tighter, same true value).
Random networks and boxes, every activation, both injection structures, with and without K,
a system whose h is nonlinear (so every second-order term is nonzero).
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.interval_ops import iadd, isum
from certify.arith.intervals import Interval, gamma, imul, up
from certify.arith.taylor import (
    TM,
    tm_absorb,
    tm_add,
    tm_from_intervals,
    tm_index,
    tm_linear,
    tm_mul,
    tm_sum,
)
from certify.enclose.network_interval import gain_enclosure, network_enclosure
from certify.enclose.system_taylor import jacobian_tm
from certify.enclose.taylor import gain_taylor, jcl_taylor, network_taylor
from certify.model import activations
from certify.model.gain import ROWS, compose_second, propagate
from certify.model.gain.taylor import tm_activation
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.spec.enclosures import (
    h_enclosure,
    hessian_f_enclosure,
    hessian_h_enclosure,
    jacobian_f_enclosure,
    jacobian_h_enclosure,
)
from certify.spec.system import System

from ..soak import examples

F64 = torch.float64

SPEC = """
name = "curved"
states = ["a", "b", "c"]
outputs = ["ya", "yb"]
f = ["b - a**3", "-a - 0.5*b + sin(c)", "-2*c + a*b"]
h = ["a + 0.2*sin(b)", "c*a + 0.1*b**2"]
[box]
X = [[-1, 1], [-1.5, 1.5], [-1, 1]]
Y = [[-1.5, 1.5], [-1.5, 1.5]]
"""


def _frozen_gain_enclosure(system, net, lo, hi, order=1, center_pre=None):
    """`gain_enclosure` as it was before it ran through `compose` (frozen)."""
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    ne = network_enclosure(net, lo, hi, order=order, second_cols=n, center_pre=center_pre)
    xl, xh = lo[:, :n], hi[:, :n]
    yI = Interval(lo[:, n:], hi[:, n:])
    K = net.K.to(torch.float64)
    has_K = bool(torch.any(K != 0))
    structural = net.structure == "structural"
    jf = Interval(*jacobian_f_enclosure(system, xl, xh))
    djf = None
    if order >= 2:
        hf = Interval(*hessian_f_enclosure(system, xl, xh))
        zpad = torch.zeros(B, n, n, p, dtype=torch.float64)
        djf = Interval(torch.cat([hf.lo, zpad], -1), torch.cat([hf.hi, zpad], -1))
    if structural or has_K:
        hI = Interval(*h_enclosure(system, xl, xh))
        r = yI - hI
        Hx = Interval(*jacobian_h_enclosure(system, xl, xh))
        eye = torch.eye(p, dtype=torch.float64).expand(B, p, p)
        dr = Interval(torch.cat([-Hx.hi, eye], -1), torch.cat([-Hx.lo, eye], -1))
        d2r = None
        if order >= 2:
            hh = Interval(*hessian_h_enclosure(system, xl, xh))
            zpad = torch.zeros(B, p, n, p, dtype=torch.float64)
            d2r = Interval(torch.cat([-hh.hi, zpad], -1), torch.cat([-hh.lo, zpad], -1))
    if not structural:
        k, dk, d2k = ne.value, ne.d1, ne.d2
    else:
        G = Interval(ne.value.lo.reshape(B, n, p), ne.value.hi.reshape(B, n, p))
        dG = Interval(ne.d1.lo.reshape(B, n, p, d), ne.d1.hi.reshape(B, n, p, d))
        rI = Interval(r.lo[:, None, :], r.hi[:, None, :])
        k = isum(imul(G, rI), 2)
        t1 = isum(imul(dG, Interval(r.lo[:, None, :, None], r.hi[:, None, :, None])), 2)
        t2 = isum(imul(Interval(G.lo[..., None], G.hi[..., None]),
                       Interval(dr.lo[:, None], dr.hi[:, None])), 2)
        dk = iadd(t1, t2)
        d2k = None
        if order >= 2:
            d2G = Interval(ne.d2.lo.reshape(B, n, p, n, d), ne.d2.hi.reshape(B, n, p, n, d))
            rr = Interval(r.lo[:, None, :, None, None], r.hi[:, None, :, None, None])
            a1 = imul(d2G, rr)
            drj = Interval(dr.lo[:, None, :, :n, None], dr.hi[:, None, :, :n, None])
            drm = Interval(dr.lo[:, None, :, None, :], dr.hi[:, None, :, None, :])
            dGj = Interval(dG.lo[:, :, :, :n, None], dG.hi[:, :, :, :n, None])
            dGm = Interval(dG.lo[:, :, :, None, :], dG.hi[:, :, :, None, :])
            a2 = imul(dGj, drm)
            a3 = imul(dGm, drj)
            Ge = Interval(G.lo[..., None, None], G.hi[..., None, None])
            a4 = imul(Ge, Interval(d2r.lo[:, None, :, :n, :], d2r.hi[:, None, :, :n, :]))
            d2k = isum(iadd(iadd(a1, a2), iadd(a3, a4)), 2)
    if has_K:
        k = iadd(k, isum(imul(Interval(K.expand(B, n, p), K.expand(B, n, p)),
                              Interval(r.lo[:, None, :], r.hi[:, None, :])), 2))
        Kdr = isum(imul(Interval(K[None, :, :, None].expand(B, n, p, d),
                                 K[None, :, :, None].expand(B, n, p, d)),
                        Interval(dr.lo[:, None], dr.hi[:, None])), 2)
        dk = iadd(dk, Kdr)
        if order >= 2:
            Kd2 = isum(imul(Interval(K[None, :, :, None, None].expand(B, n, p, n, d),
                                     K[None, :, :, None, None].expand(B, n, p, n, d)),
                            Interval(d2r.lo[:, None, :, :n, :], d2r.hi[:, None, :, :n, :])), 2)
            d2k = iadd(d2k, Kd2)
    return dict(k=k, dk_dx=dk[:, :, :n], dk_dy=dk[:, :, n:], d2k=d2k, jf=jf, djf=djf), ne


def _frozen_network_taylor(net, lo, hi):
    """`network_taylor` as it was before it ran through `propagate` (frozen)."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    weights = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
    act = net.act
    W0, b0 = weights[0]
    eye = torch.eye(d, dtype=torch.float64).expand(B, d, d)
    val = tm_linear(TM(zc, eye, torch.zeros_like(zc)), W0.T, b0, r)
    h0 = W0.shape[0]
    T = TM(W0.T.expand(B, d, h0), torch.zeros(B, d, h0, d, dtype=torch.float64),
           torch.zeros(B, d, h0, dtype=torch.float64))
    for W, b in weights[1:]:
        a, s = tm_activation(act, val, r)
        s_b = TM(s.c.unsqueeze(1), s.g.unsqueeze(1), s.e.unsqueeze(1))
        Tn = tm_mul(s_b, T, r)
        val = tm_linear(a, W.T, b, r)
        T = tm_linear(Tn, W.T, None, r)
    return val, TM(T.c.transpose(1, 2), T.g.transpose(1, 2), T.e.transpose(1, 2)), r


def _frozen_jcl_taylor(system, net, lo, hi, net_tms=None):
    """`jcl_taylor` as it was before it ran through `compose` (frozen)."""
    n, p = system.n, system.p
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    val, d1, r = _frozen_network_taylor(net, lo, hi) if net_tms is None else net_tms
    zc = 0.5 * (lo + hi)
    xc = zc[:, :n]
    xl, xh = lo[:, :n], hi[:, :n]

    def pad(iv):
        z = torch.zeros(*iv.lo.shape[:-1], p, dtype=torch.float64)
        return Interval(torch.cat([iv.lo, z], -1), torch.cat([iv.hi, z], -1))

    # the system's Jacobian models: `certify.enclose.system_taylor` (second-order form since
    # issue 9; tested in tests/enclose/test_system_taylor.py), not part of what is frozen here
    jf = jacobian_tm(system, "f", lo, hi, r)
    K = net.K.to(torch.float64)
    has_K = bool(torch.any(K != 0))
    structural = net.structure == "structural"
    if structural or has_K:
        Jh = jacobian_tm(system, "h", lo, hi, r)
    if not structural:
        dkdx = tm_index(d1, (slice(None), slice(None), slice(0, n)))
    else:
        hc = Interval(*h_enclosure(system, xc, xc))
        jhb = Interval(*jacobian_h_enclosure(system, xl, xh))
        eye_p = torch.eye(p, dtype=torch.float64).expand(B, p, p)
        dr_box = Interval(torch.cat([-jhb.hi, eye_p], -1), torch.cat([-jhb.lo, eye_p], -1))
        yc = Interval(zc[:, n:], zc[:, n:])
        rt = tm_from_intervals(yc - hc, dr_box, r)
        G = TM(val.c.reshape(B, n, p), val.g.reshape(B, n, p, d), val.e.reshape(B, n, p))
        dG = TM(d1.c.reshape(B, n, p, d)[..., :n], d1.g.reshape(B, n, p, d, d)[..., :n, :],
                d1.e.reshape(B, n, p, d)[..., :n])
        r_b = TM(rt.c[:, None, :, None], rt.g[:, None, :, None, :], rt.e[:, None, :, None])
        t1 = tm_sum(tm_mul(dG, r_b, r), 2, r)
        G_b = TM(G.c[..., None], G.g[:, :, :, None, :], G.e[..., None])
        Jh_b = TM(Jh.c[:, None], Jh.g[:, None], Jh.e[:, None])
        t2 = tm_sum(tm_mul(G_b, Jh_b, r), 2, r)
        dkdx = tm_add(t1, TM(-t2.c, -t2.g, t2.e), r)
    if has_K:
        KJ = TM(K @ Jh.c, torch.einsum("ip,bpjd->bijd", K, Jh.g), K.abs() @ Jh.e)
        KJ = tm_absorb(KJ.c, KJ.g, up(KJ.e * (1 + 2 * gamma(p + 1))), r, p + 2)
        dkdx = tm_add(dkdx, TM(-KJ.c, -KJ.g, KJ.e), r)
    return tm_add(jf, dkdx, r)


def _same(a: Interval | None, b: Interval | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return torch.equal(a.lo, b.lo) and torch.equal(a.hi, b.hi)


def _same_tm(a: TM, b: TM) -> bool:
    return torch.equal(a.c, b.c) and torch.equal(a.g, b.g) and torch.equal(a.e, b.e)


def _cases(act: str, structure: str):
    """(system, net, lo, hi) for three seeds: K on odd seeds, boxes from wide to thin."""
    system = System.from_text(SPEC, origin="test curved")
    for seed in range(3):
        torch.manual_seed(seed)
        K = torch.randn(3, 2) if seed % 2 else None
        net = GainNetwork(3, 2, (5, 4), structure=structure, K=K, activation=act)
        net.requires_grad_(False)  # as `certify.model.problem.Problem` freezes it for the prover
        c = 2.0 * torch.rand(6, 5, dtype=F64) - 1.0
        w = torch.rand(6, 5, dtype=F64) * 0.3 * 10.0 ** (-2 * seed)
        yield system, net, c - w, c + w


@pytest.mark.parametrize("act", activations.names())
@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_gain_enclosure_through_compose_is_the_old_one(act: str, structure: str) -> None:
    for system, net, lo, hi in _cases(act, structure):
        zc = 0.5 * (lo + hi)
        center = network_enclosure(net, zc, zc).pre
        for order, cp in ((1, None), (2, None), (2, center)):
            new, ne_new = gain_enclosure(system, net, lo, hi, order=order, center_pre=cp)
            ref, ne_ref = _frozen_gain_enclosure(system, net, lo, hi, order=order,
                                                 center_pre=cp)
            for name in ("k", "dk_dx", "d2k", "jf", "djf"):
                assert _same(getattr(new, name), ref[name]), name
            assert _same(ne_new.value, ne_ref.value) and _same(ne_new.d1, ne_ref.d1)
            # dk/dy: inside the old enclosure (equal for the direct structure without K)
            assert bool(torch.all(ref["dk_dy"].lo <= new.dk_dy.lo))
            assert bool(torch.all(new.dk_dy.hi <= ref["dk_dy"].hi))
            assert bool(torch.all(new.dk_dy.lo <= new.dk_dy.hi))
            if structure == "direct" and not net.K.any():
                assert _same(new.dk_dy, ref["dk_dy"])


@pytest.mark.parametrize("act", activations.names())
@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_taylor_models_through_propagate_and_compose_are_the_old_ones(act: str,
                                                                      structure: str) -> None:
    for system, net, lo, hi in _cases(act, structure):
        val, d1, r = network_taylor(net, lo, hi)
        rval, rd1, rr = _frozen_network_taylor(net, lo, hi)
        assert _same_tm(val, rval) and _same_tm(d1, rd1) and torch.equal(r, rr)
        assert _same_tm(jcl_taylor(system, net, lo, hi), _frozen_jcl_taylor(system, net, lo, hi))
        # Taylor models handed in from elsewhere (as the linear bound propagation does)
        shrunk = (val, TM(d1.c, d1.g, 0.5 * d1.e), r)
        assert _same_tm(jcl_taylor(system, net, lo, hi, net_tms=shrunk),
                        _frozen_jcl_taylor(system, net, lo, hi, net_tms=shrunk))


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.slow
def test_second_order_compose_at_points_matches_autograd(structure: str) -> None:
    """`compose_second` in the point arithmetic is d2k_i / dxhat_j dz_m of k written plainly
    (an independent check of the formula the interval enclosure uses)."""
    system = System.from_text(SPEC, origin="test curved")
    torch.manual_seed(3)
    net = GainNetwork(3, 2, (6, 5), structure=structure, K=torch.randn(3, 2),
                      activation="silu").double().requires_grad_(False)
    n, p, d = 3, 2, 5
    spec = net.spec(F64, detach=True)
    z = 2.0 * torch.rand(4, d, dtype=F64) - 1.0

    def k_of(v: torch.Tensor) -> torch.Tensor:  # plain k(z) at one point
        x, y = v[None, :n], v[None, n:]
        out = net(v[None])
        r = y - system.h(x)
        k = out if structure == "direct" else (out.reshape(1, n, p) @ r[..., None])[..., 0]
        return (k + r @ net.K.T)[0]

    def r_of(v: torch.Tensor) -> torch.Tensor:
        return v[n:] - system.h(v[None, :n])[0]

    out = propagate(spec, ROWS, z, d, order=2, second_cols=n)
    r = z[:, n:] - system.h(z[:, :n])
    dr = torch.stack([torch.autograd.functional.jacobian(r_of, v) for v in z])  # [B, p, d]
    d2r = torch.stack([torch.autograd.functional.hessian(lambda u, i=i: r_of(u)[i], v)
                       for v in z for i in range(p)]).reshape(-1, p, d, d)[:, :, :n, :]
    got = compose_second(spec, ROWS, out, r, dr, d2r)
    want = torch.stack([torch.autograd.functional.jacobian(
        lambda u: torch.autograd.functional.jacobian(k_of, u, create_graph=True), v)
        for v in z])[:, :, :n, :]  # [B, n, n, d]
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("act", activations.names())
@settings(max_examples=examples(4), deadline=None)
@given(seed=st.integers(0, 10_000), structure=st.sampled_from(["direct", "structural"]),
       with_K=st.booleans(), scale=st.sampled_from([1e-6, 1e-3, 0.05, 0.3]))
def test_gain_taylor_models_contain_k_and_its_jacobians(act: str, seed: int, structure: str,
                                                        with_K: bool, scale: float) -> None:
    """k, dk/dxhat, dk/dy at sampled float64 points lie in the Taylor models `compose`
    builds in `TaylorArithmetic` (value, both Jacobians, every injection)."""
    system = System.from_text(SPEC, origin="test curved")
    torch.manual_seed(seed)
    net = GainNetwork(3, 2, (5, 4), structure=structure, K=torch.randn(3, 2) if with_K else None,
                      activation=act).requires_grad_(False)
    g = torch.Generator().manual_seed(seed)
    c = 2.0 * torch.rand(8, 5, generator=g, dtype=F64) - 1.0
    w = scale * torch.rand(8, 5, generator=g, dtype=F64)
    lo, hi = c - w, c + w
    tms = gain_taylor(system, net, lo, hi)
    u = torch.rand(8, 64, 5, generator=g, dtype=F64)
    u[:, :2] = torch.stack([torch.zeros(8, 5, dtype=F64), torch.ones(8, 5, dtype=F64)], 1)
    z = (lo[:, None] + u * (hi - lo)[:, None]).reshape(-1, 5)
    t = gain_terms(system, net, z[:, :3], z[:, 3:])
    dz = (z - c.repeat_interleave(64, 0))
    for tm, v in ((tms.k, t.k), (tms.dk_dx, t.dk_dx), (tms.dk_dy, t.dk_dy)):
        rep = lambda x: x.repeat_interleave(64, 0)  # noqa: E731
        lin = rep(tm.c) + torch.einsum("b...d,bd->b...", rep(tm.g), dz)
        assert bool(((v - lin).abs() <= rep(tm.e) + 1e-12 * (1 + v.abs())).all())
