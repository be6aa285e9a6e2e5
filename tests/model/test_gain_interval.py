"""The interval forward pass through `propagate` equals the old hand-written one, bit for bit.

`network_enclosure` now runs `certify.model.gain.propagate` with `IntervalArithmetic`; the layer
walk
it replaced is frozen below (kept only here) and every enclosure must match it exactly: same
outward-rounded operations in the same order, for every activation, both structures, order 1
and 2, with and without the mean-value tightening.
"""

from __future__ import annotations

import pytest
import torch

from certify.arith.interval_ops import iadd, intersect, isum, point
from certify.arith.intervals import Interval, imul, matmul_point_right, midrad_to_interval, up
from certify.enclose.network_interval import NetEnclosure, network_enclosure
from certify.model import activations
from certify.model.network import GainNetwork


def _frozen_network_enclosure(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor, order: int = 1,
                      second_cols: int | None = None,
                      center_pre: list[Interval] | None = None) -> NetEnclosure:
    """`network_enclosure` as it was before it ran through `propagate` (frozen)."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    J = d if second_cols is None else int(second_cols)
    weights = [(W.to(torch.float64), b.to(torch.float64)) for W, b in net.weights()]
    act = net.act
    W0, b0 = weights[0]
    zc = 0.5 * (lo + hi)
    zr = up(torch.maximum(hi - zc, zc - lo))
    zdev = Interval(-zr, zr)  # z - c
    c, r = matmul_point_right(zc, zr, W0.T)
    val = midrad_to_interval(c, r) + point(b0.expand_as(c))
    h0 = W0.shape[0]
    T = point(W0.T.unsqueeze(0).expand(B, d, h0))  # [B, d, h]
    S = None
    if order >= 2:
        zero = torch.zeros(B, J * d, h0, dtype=torch.float64)
        S = Interval(zero, zero)
    pres: list[Interval] = []
    for li, (W, b) in enumerate(weights[1:]):
        if center_pre is not None:
            mv = isum(imul(T, Interval(zdev.lo.unsqueeze(-1), zdev.hi.unsqueeze(-1))), 1)
            val = intersect(val, center_pre[li] + mv)
        pres.append(val)
        t = act.enclose_f(val)
        s1 = act.enclose_d1(val)
        s1e = Interval(s1.lo.unsqueeze(1), s1.hi.unsqueeze(1))
        Tn = imul(s1e, T)
        rows_lo = [t.lo.unsqueeze(1), Tn.lo]
        rows_hi = [t.hi.unsqueeze(1), Tn.hi]
        if S is not None:
            s2 = act.enclose_d2(val)
            hw = T.lo.shape[-1]
            Tj = Interval(T.lo[:, :J].unsqueeze(2), T.hi[:, :J].unsqueeze(2))  # [B, J, 1, h]
            Tm = Interval(T.lo.unsqueeze(1), T.hi.unsqueeze(1))  # [B, 1, d, h]
            TT = imul(Tj, Tm)  # [B, J, d, h]
            s2e = Interval(s2.lo[:, None, None, :], s2.hi[:, None, None, :])
            s1f = Interval(s1.lo[:, None, None, :], s1.hi[:, None, None, :])
            Sn = iadd(imul(s2e, TT), imul(s1f, Interval(S.lo.reshape(B, J, d, hw),
                                                        S.hi.reshape(B, J, d, hw))))
            rows_lo.append(Sn.lo.reshape(B, J * d, hw))
            rows_hi.append(Sn.hi.reshape(B, J * d, hw))
        rows = Interval(torch.cat(rows_lo, 1), torch.cat(rows_hi, 1))
        rc, rr = rows.midrad()
        oc, orr = matmul_point_right(rc, rr, W.T)
        out = midrad_to_interval(oc, orr)
        val = out[:, 0] + point(b.expand_as(oc[:, 0]))
        T = out[:, 1:1 + d]
        if S is not None:
            S = out[:, 1 + d:]
    out_dim = val.lo.shape[-1]
    d1 = Interval(T.lo.transpose(1, 2), T.hi.transpose(1, 2))  # [B, out, d]
    d2 = None
    if S is not None:
        d2 = Interval(S.lo.reshape(B, J, d, out_dim).permute(0, 3, 1, 2),
                      S.hi.reshape(B, J, d, out_dim).permute(0, 3, 1, 2))
    return NetEnclosure(value=val, d1=d1, d2=d2, pre=pres)


def _same(a: Interval, b: Interval) -> bool:
    return torch.equal(a.lo, b.lo) and torch.equal(a.hi, b.hi)


@pytest.mark.parametrize("act", activations.names())
@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_propagate_interval_pass_is_the_old_one_bit_for_bit(act: str, structure: str) -> None:
    for seed in range(3):
        torch.manual_seed(seed)
        K = torch.randn(2, 2) if seed % 2 else None
        net = GainNetwork(2, 2, (5, 4), structure=structure, K=K, activation=act)
        c = 2.0 * torch.rand(6, 4, dtype=torch.float64) - 1.0
        w = torch.rand(6, 4, dtype=torch.float64) * 10.0 ** (-3 * seed)
        lo, hi = c - w, c + w
        center = network_enclosure(net, c, c).pre
        for order, J, cp in ((1, None, None), (1, None, center), (2, 2, None), (2, 2, center)):
            new = network_enclosure(net, lo, hi, order=order, second_cols=J, center_pre=cp)
            ref = _frozen_network_enclosure(net, lo, hi, order=order, second_cols=J,
                                            center_pre=cp)
            assert _same(new.value, ref.value) and _same(new.d1, ref.d1)
            assert (new.d2 is None) == (ref.d2 is None)
            assert new.d2 is None or _same(new.d2, ref.d2)
            assert len(new.pre) == len(ref.pre)
            assert all(_same(a, b) for a, b in zip(new.pre, ref.pre, strict=True))
            assert bool(torch.all(new.value.lo <= new.value.hi))
