"""`IntervalArithmetic`: `certify.model.gain.propagate` over `certify.arith.intervals.Interval`
values.

The prover's forward pass (`certify.enclose.network_interval.network_enclosure`) is this
arithmetic run through `propagate`. Layout: rows [B, rows, width] as in `RowArithmetic`:
the value [B, h], first-derivative rows T [B, m, h], second-derivative rows S [B, J m, h].
Rounding: products of point weight matrices with intervals in midpoint-radius form with
Higham's gamma_k bound added (`certify.arith.intervals.matmul_point_right`), interval products and
sums outward by one ulp (`imul`, `iadd`), the activation and its derivatives by the
activation's own sound enclosures (`enclose_f`, `enclose_d1`, `enclose_d2`). The input box
enters as centre and outward-rounded radius (zc, zr).

The composition with the injection (`compose`, `compose_second`) contracts by elementwise
interval products summed with `isum` (its gamma_k sum|x| term covers the summation error);
constants (K, the identity blocks of dk/dy) enter as point intervals, exactly.
"""

from __future__ import annotations

import torch

from certify.arith.interval_ops import iadd, isum, point
from certify.arith.intervals import Interval, imul, matmul_point_right, midrad_to_interval
from certify.model.activations import Activation
from certify.model.gain.propagate import NetOutput


def _view(x: Interval, *shape: int) -> Interval:
    return Interval(x.lo.reshape(*shape), x.hi.reshape(*shape))


def _neg(x: Interval) -> Interval:
    return Interval(-x.hi, -x.lo)


class IntervalArithmetic:
    """Interval value, Jacobian and second-derivative enclosures over the box zc +- zr."""

    def __init__(self, zc: torch.Tensor, zr: torch.Tensor) -> None:
        self.zc = zc
        self.zr = zr

    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[Interval, Interval | None]:
        """pre = W [zc +- zr] + b; T = W[:, :m] as point intervals [B, m, h]."""
        c, r = matmul_point_right(self.zc, self.zr, W.T)
        pre = midrad_to_interval(c, r) + point(b.expand_as(c))
        T = point(W[:, :m].T.unsqueeze(0).expand(c.shape[0], m, W.shape[0])) if m else None
        return pre, T

    def zero_second(self, pre: Interval, J: int, m: int) -> Interval:
        zero = torch.zeros(pre.lo.shape[0], J * m, pre.lo.shape[1], dtype=pre.lo.dtype,
                           device=pre.lo.device)
        return Interval(zero, zero)

    def activate(self, act: Activation, pre: Interval, layer: int, order: int
                 ) -> tuple[Interval, Interval, Interval | None]:
        return (act.enclose_f(pre), act.enclose_d1(pre),
                act.enclose_d2(pre) if order >= 2 else None)

    def scale(self, s: Interval, T: Interval, layer: int) -> Interval:
        return imul(Interval(s.lo.unsqueeze(1), s.hi.unsqueeze(1)), T)

    def second(self, s2: Interval, T: Interval, s: Interval, S: Interval, J: int,
               layer: int) -> Interval:
        B, m, h = T.lo.shape
        Tj = Interval(T.lo[:, :J].unsqueeze(2), T.hi[:, :J].unsqueeze(2))  # [B, J, 1, h]
        Tm = Interval(T.lo.unsqueeze(1), T.hi.unsqueeze(1))  # [B, 1, m, h]
        s2e = Interval(s2.lo[:, None, None, :], s2.hi[:, None, None, :])
        s1f = Interval(s.lo[:, None, None, :], s.hi[:, None, None, :])
        out = iadd(imul(s2e, imul(Tj, Tm)), imul(s1f, _view(S, B, J, m, h)))
        return _view(out, B, J * m, h)

    def affine(self, a: Interval, T: Interval | None, S: Interval | None, W: torch.Tensor,
               b: torch.Tensor, layer: int
               ) -> tuple[Interval, Interval | None, Interval | None]:
        """All rows through one midpoint-radius product with W; the bias on the value row."""
        parts = [a] + [x for x in (T, S) if x is not None]
        rows = Interval(torch.cat([a.lo.unsqueeze(1)] + [x.lo for x in parts[1:]], 1),
                        torch.cat([a.hi.unsqueeze(1)] + [x.hi for x in parts[1:]], 1))
        rc, rr = rows.midrad()
        oc, orr = matmul_point_right(rc, rr, W.T)
        out = midrad_to_interval(oc, orr)
        val = out[:, 0] + point(b.expand_as(oc[:, 0]))
        m = 0 if T is None else T.lo.shape[1]
        Tn = out[:, 1:1 + m] if T is not None else None
        Sn = out[:, 1 + m:] if S is not None else None
        return val, Tn, Sn

    def output(self, pre: Interval, T: Interval | None, S: Interval | None) -> NetOutput:
        jac = None if T is None else Interval(T.lo.transpose(1, 2), T.hi.transpose(1, 2))
        hess = None
        if S is not None:
            B, out = pre.lo.shape
            m = T.lo.shape[1]
            J = S.lo.shape[1] // m
            hess = Interval(S.lo.reshape(B, J, m, out).permute(0, 3, 1, 2),
                            S.hi.reshape(B, J, m, out).permute(0, 3, 1, 2))
        return NetOutput(pre, jac, hess)

    # --- compose primitives: products of intervals summed with `isum` ---
    def cols(self, x: Interval, start: int, stop: int) -> Interval:
        return x[..., start:stop]

    def reshape_out(self, out: Interval, n: int, p: int) -> Interval:
        return _view(out, out.lo.shape[0], n, p)

    def reshape_jac(self, jac: Interval, n: int, p: int) -> Interval:
        return _view(jac, jac.lo.shape[0], n, p, jac.lo.shape[-1])

    def matvec(self, A: Interval, v: Interval) -> Interval:
        """sum_l A_il v_l: A [B, n, p], v [B, p]."""
        return isum(imul(A, v[:, None, :]), 2)

    def contract(self, dA: Interval, v: Interval) -> Interval:
        """sum_l dA_ilm v_l: dA [B, n, p, m], v [B, p]."""
        return isum(imul(dA, v[:, None, :, None]), 2)

    def matmul(self, A: Interval, B: Interval) -> Interval:
        """sum_l A_il B_lm: A [B, n, p], B [B, p, m]."""
        return isum(imul(A[..., None], B[:, None]), 2)

    def add(self, a: Interval, b: Interval) -> Interval:
        return iadd(a, b)

    def sub(self, a: Interval, b: Interval) -> Interval:
        return iadd(a, _neg(b))

    def const_matvec(self, K: torch.Tensor, v: Interval) -> Interval:
        return isum(imul(point(K[None]), v[:, None, :]), 2)

    def const_matmul(self, K: torch.Tensor, A: Interval) -> Interval:
        return isum(imul(point(K[None, :, :, None]), A[:, None]), 2)

    def add_const(self, a: Interval, K: torch.Tensor) -> Interval:
        return iadd(a, point(K[None]))

    def reshape(self, x: Interval, shape: tuple[int, ...]) -> Interval:
        return _view(x, x.lo.shape[0], *shape)

    def index(self, x: Interval, idx: tuple) -> Interval:
        return x[idx]

    def mul(self, a: Interval, b: Interval) -> Interval:
        return imul(a, b)

    def sum(self, x: Interval, dim: int) -> Interval:
        return isum(x, dim)
