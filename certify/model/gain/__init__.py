"""The gain written once: its description (`GainSpec`) and one propagation (`propagate`).

- `GainSpec` (spec.py): layers (W, b), the activation (`certify.model.activations`), the injection
  structure (direct / structural) and the linear term K. `GainNetwork.spec()` gives it.
- `propagate` (propagate.py): N(z) and its input derivatives (first order, optionally second)
  layer by layer against an arithmetic; `compose` adds the injection (G r, K r) and returns
  k, dk/dxhat, dk/dy; `compose_second` the second derivatives d2k / dxhat dz.
- Arithmetics, each implementing the `Arithmetic` protocol (arithmetic.py) over its own
  number kind:
  * points, float32/float64: `RowArithmetic` (points in rows, autograd-safe),
    `ColumnArithmetic` (feature-major, dense grids), `ChunkArithmetic` (buffered.py,
    training buffers, with its hand-written adjoint `reverse` and the chunk-layout `compose`
    primitives `ChunkCompose`); `gain_at_points` / `gain_value` (point.py) are the point
    entry points;
  * intervals: `IntervalArithmetic` (interval.py), outward-rounded;
  * first-order Taylor models: `TaylorArithmetic` (taylor.py), over
    `certify.enclose.taylor.TM`, whose `tm_activation` is its `activate`;
  * a Taylor model and an interval per value: `PairedArithmetic` (paired.py; `propagate`
    only, no compose primitives), which delegates to the two above (the interval step's
    products with W kept per value) and intersects the interval with the model's range when
    asked (`intersect`).

Adding an activation touches one file in `certify/activations/`. Through `propagate` and
`compose` run: the point kernels (`certify.model.kernels`, `certify.search.grid`,
`certify.simulate.integrate`), training's forward passes and loss heads (`training.objective`,
CEGIS' `training.cegis_objective`, the curvature term), and the prover's enclosures:
`network_enclosure` and `gain_enclosure`
(`certify.enclose.network_interval`: `propagate`, `compose`, `compose_second` in
`IntervalArithmetic`), `network_taylor`, `gain_taylor` and `jcl_taylor`
(`certify.enclose.taylor`, in `TaylorArithmetic`), and the CROWN prover's forward ranges
`certify.enclose.crown.forward_bounds` (`propagate` in `PairedArithmetic`; its `layer_hook`
intersects, adds the composed first layer's slack at layer 0, runs the backward CROWN
queries that tighten pre_l and the tangent columns, and records each layer's relaxations).
Their values are frozen bit for bit by the gain, compose, crown-forward and training-head
tests; dk/dy of the interval gain is formed as dN/dy r + G + K with exact constants (no
product rounding on G_il * 1 and K_il * 1).

Not (yet) written once:
- The linear-relaxation arithmetic: CROWN's backward pass (`certify.enclose.crown_backward`),
  the adjoint of the chain rule with `act.relax` / `act.relax_d1` lines, is separate by
  nature (backward mode; `propagate` is forward mode). `certify.enclose.side.
  dk_dy_box_upper_crown` adds K to crown's dN/dy model by hand (`TaylorArithmetic.add_const`).
- The reverse pass of training (`ChunkArithmetic.reverse`, the weight gradient) is the
  hand-written adjoint of `propagate` over the chunk buffers, not derived from it:
  `propagate` is forward mode and records nothing to reverse; autograd through it costs
  several times more (see `training.objective`). The training heads call `compose` (with
  `with_K_dx=False`: they fold -K Hx into their float64 constant) and autograd maps the
  head's gradient back through it.
- tanh keeps its own tighter rules beside the generic ones (`tm_tanh_and_dtanh`,
  `certify.enclose.relax`).
"""

from __future__ import annotations

from certify.model.gain.arithmetic import COLUMNS, ROWS, Arithmetic, ColumnArithmetic, RowArithmetic
from certify.model.gain.point import gain_at_points, gain_value
from certify.model.gain.propagate import (
    GainValues,
    NetOutput,
    columns_needed,
    compose,
    compose_second,
    propagate,
)
from certify.model.gain.spec import STRUCTURES, GainSpec

__all__ = ["Arithmetic", "COLUMNS", "ColumnArithmetic", "GainSpec", "GainValues", "NetOutput",
           "ROWS", "RowArithmetic", "STRUCTURES", "columns_needed", "compose", "compose_second",
           "gain_at_points", "gain_value", "propagate"]
