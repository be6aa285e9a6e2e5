"""`PairedArithmetic`: `certify.model.gain.propagate` over a Taylor model and an interval per value.

Each value (a pre-activation [B, h] or the tangent rows T = d pre / dz [B, m, h]) is a
`Paired`: a first-order Taylor model (`TaylorArithmetic`, which advances it unchanged) and
an interval that the next layer's interval step starts from. The interval step is
`IntervalArithmetic`'s activation enclosures and product with f', then one point-matrix
product per value (the value and the tangent rows separately, as the CROWN prover has always
done). `intersect` narrows the interval to its meet with the Taylor model's range: the
caller (the `layer_hook` of `certify.enclose.crown.forward_bounds`) decides when, since it
also tightens the ranges further (CROWN queries) before the next step.

Rounding: the Taylor side is `TaylorArithmetic`'s; on the interval side, products of point
matrices with intervals go through midpoint-radius form with Higham's gamma_k bound
(`certify.arith.intervals.matmul_point_right`), the bias sum is rounded outward by one ulp, the
products with f' outward (`imul`), and a Taylor model's range is c +- rho rounded outward
(`tm_range`). Intersecting two enclosures of the same quantity is exact.

The output layer's interval step is skipped (`depth`): only the Taylor models of N and dN/dz
leave `output`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.intervals import Interval, down, matmul_point_right, midrad_to_interval, up
from certify.arith.taylor import TM, tm_rho
from certify.model.activations import Activation
from certify.model.gain.interval import IntervalArithmetic
from certify.model.gain.propagate import NetOutput
from certify.model.gain.taylor import TaylorArithmetic


@dataclass
class Paired:
    """A Taylor model and an interval (None: not yet formed) enclosing the same values."""

    tm: TM
    iv: Interval | None


def tm_range(t: TM, r: torch.Tensor) -> Interval:
    """The range c +- rho of a Taylor model over the box radii r, rounded outward."""
    rho = tm_rho(t, r)
    return Interval(down(t.c - rho), up(t.c + rho))


def imatvec_point(x: Interval, W: torch.Tensor) -> Interval:
    """x @ W.T for x [..., k] an interval and W [m, k] a point matrix."""
    c, r = x.midrad()
    oc, orr = matmul_point_right(c, r, W.T)
    return midrad_to_interval(oc, orr)


class PairedArithmetic:
    """Taylor models and intervals of N and dN/dz over the boxes zc +- r; `depth` is the
    number of hidden layers (the output layer gets no interval step)."""

    def __init__(self, zc: torch.Tensor, r: torch.Tensor, depth: int) -> None:
        self.r = r
        self.depth = depth
        self.taylor = TaylorArithmetic(zc, r)
        self.interval = IntervalArithmetic(zc, r)

    def intersect(self, x: Paired) -> Paired:
        """x with its interval replaced by its meet with the Taylor model's range (the range
        alone where there is no interval yet)."""
        rng = tm_range(x.tm, self.r)
        if x.iv is None:
            return Paired(x.tm, rng)
        return Paired(x.tm, Interval(torch.maximum(x.iv.lo, rng.lo),
                                     torch.minimum(x.iv.hi, rng.hi)))

    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[Paired, Paired]:
        """pre_0 as a Taylor model (its interval: `intersect`, after any slack is added);
        T_0 = W[:, :m] exactly, as constant models and point intervals [B, m, h]."""
        pre, T = self.taylor.input_layer(z, W, b, m)
        Wt = W[:, :m].T.expand(pre.c.shape[0], m, W.shape[0])
        return Paired(pre, None), Paired(T, Interval(Wt, Wt))

    def activate(self, act: Activation, pre: Paired, layer: int, order: int
                 ) -> tuple[Paired, Paired, None]:
        a, s, _ = self.taylor.activate(act, pre.tm, layer, order)
        if layer >= self.depth or pre.iv is None:  # pre_{H-1}: the output needs no range
            return Paired(a, None), Paired(s, None), None
        ai, si, _ = self.interval.activate(act, pre.iv, layer, order)
        return Paired(a, ai), Paired(s, si), None

    def scale(self, s: Paired, T: Paired, layer: int) -> Paired:
        Tn = self.taylor.scale(s.tm, T.tm, layer)
        if s.iv is None or T.iv is None:
            return Paired(Tn, None)
        return Paired(Tn, self.interval.scale(s.iv, T.iv, layer))

    def affine(self, a: Paired, T: Paired, S: None, W: torch.Tensor, b: torch.Tensor,
               layer: int) -> tuple[Paired, Paired, None]:
        val, Tn, _ = self.taylor.affine(a.tm, T.tm, None, W, b, layer)
        if a.iv is None or T.iv is None:
            return Paired(val, None), Paired(Tn, None), None
        nxt = imatvec_point(a.iv, W)
        return (Paired(val, Interval(down(nxt.lo + b), up(nxt.hi + b))),
                Paired(Tn, imatvec_point(T.iv, W)), None)

    def output(self, pre: Paired, T: Paired, S: None) -> NetOutput:
        """The Taylor models of N [B, out] and dN/dz [B, out, m]."""
        return self.taylor.output(pre.tm, T.tm, None)
