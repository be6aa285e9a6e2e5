"""The gain written once: its description (`GainSpec`) and one propagation (`propagate`).

- `GainSpec` (spec.py): layers (W, b), the activation (`certify.activations`), the injection
  structure (direct / structural) and the linear term K. `GainNetwork.spec()` gives it.
- `propagate` (propagate.py): N(z) and its input derivatives (first order, optionally second)
  layer by layer against an arithmetic; `compose` adds the injection (G r, K r) and returns
  k, dk/dxhat, dk/dy.
- Arithmetics (arithmetic.py, buffered.py): `RowArithmetic` (points in rows, autograd-safe),
  `ColumnArithmetic` (feature-major, dense grids), `ChunkArithmetic` (training buffers); all
  point float32/float64. `gain_at_points` / `gain_value` (point.py) are the point entry points.

Adding an activation touches one file in `certify/activations/`; every evaluation of the gain
(kernels, grid kernel, simulation, training, CEGIS) goes through `propagate`.

How `certify/enclosures.py` ports to this interface (the prover's interval, Taylor-model and
relaxation arithmetics implement the `Arithmetic` protocol of arithmetic.py):

1. `IntervalArithmetic(zc, zr)` over `certify.intervals.Interval` values in the row layout
   [B, rows, width]: `input_layer` = `matmul_point_right(zc, zr, W.T)` + b, T = point(W[:, :m]);
   `zero_second` = a zero Interval [B, J m, h]; `activate(act, pre, i, order)` =
   (act.enclose_f(pre), act.enclose_d1(pre), act.enclose_d2(pre) if order 2); `scale` =
   imul(s[:, None], T); `second` = iadd(imul(s2, imul(T_j, T_m)), imul(s, S)) (the block now in
   `network_enclosure`); `affine` = rows.midrad() -> `matmul_point_right(rc, rr, W.T)`, + b on
   row 0; `output` = the transposes `network_enclosure` ends with. The mean-value tightening
   with `center_pre` becomes `pre_hook(i, pre, T)`: intersect(pre, center_pre[i] +
   isum(imul(T, z - c), 1)), recording `pre` for `NetEnclosure.pre`. Then
   `network_enclosure(net, lo, hi, order, second_cols, center_pre)` =
   `propagate(net.spec(torch.float64, detach=True), IntervalArithmetic(zc, zr), None, d,
   order, second_cols, hook)`.
2. Its compose primitives: cols = Interval slicing, matvec/contract = imul + `isum`, matmul =
   `imatmul`, add/sub = `iadd` / negation, const_matvec/const_matmul = `matmul_point_right`
   with zero radius handling of K, add_const = + point(K). `gain_enclosure` is then
   `compose(spec, IA, net, r=Interval(y) - h_enclosure(x), Hx=jacobian_h_enclosure(x))`
   plus its Jf / djf terms (which are about f, not the gain).
3. The Taylor models (`network_taylor`): `activate` returns the TMs of f(q) and f'(q) that
   `tm_tanh_and_dtanh` builds, with `torch.tanh` -> `act.f`, 1 - t^2 -> `act.d1`,
   `d2tanh_enclosure` -> `act.enclose_d2` and the constant max|tanh'''| = 2 ->
   `act.d3_bound` (math.inf for ELU, whose f'' jumps: use the first-order remainder with
   `act.enclose_d2` there); `scale` = `tm_mul`; `affine` = `tm_linear`.
4. Linear relaxations: `act.relax(lo, hi)` and `act.relax_d1(lo, hi)` give sound lines for
   f and f' on each neuron's pre-activation interval.
Item 1 is done: `IntervalArithmetic` (interval.py) and `network_enclosure` is a call to
`propagate` (bit-identical to the old layer walk, tests/test_gain_interval.py). The prover
reads the activation (`net.act`) at the sites of items 3 and 4
(`certify.bounds.taylor.tm_activation`, `certify.bounds.relax.relax_value` / `relax_slope`;
tanh keeps its own tighter rules). Item 2, `gain_enclosure` through `compose`, is not done.
"""

from __future__ import annotations

from certify.gain.arithmetic import COLUMNS, ROWS, Arithmetic, ColumnArithmetic, RowArithmetic
from certify.gain.point import gain_at_points, gain_value
from certify.gain.propagate import (
    GainValues,
    NetOutput,
    columns_needed,
    compose,
    compose_second,
    propagate,
)
from certify.gain.spec import STRUCTURES, GainSpec

__all__ = ["Arithmetic", "COLUMNS", "ColumnArithmetic", "GainSpec", "GainValues", "NetOutput",
           "ROWS", "RowArithmetic", "STRUCTURES", "columns_needed", "compose", "compose_second",
           "gain_at_points", "gain_value", "propagate"]
