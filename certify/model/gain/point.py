"""k(xhat, y) and its Jacobians at points: `propagate` + `compose` with h from the system.

The entry points the point kernels use (`certify.model.kernels`, `certify.search.grid`,
`certify.simulate.integrate`, training's CEGIS): shapes xhat [B, n], y [B, p].
"""

from __future__ import annotations

from typing import Any

import torch

from certify.model.gain.arithmetic import ROWS
from certify.model.gain.propagate import GainValues, columns_needed, compose, propagate
from certify.model.gain.spec import GainSpec


def gain_at_points(spec: GainSpec, system: Any, xhat: torch.Tensor, y: torch.Tensor, *,
                   with_dy: bool = True, with_k: bool = True, arith: Any = ROWS
                   ) -> GainValues:
    """k [B, n], dk/dxhat [B, n, n], dk/dy [B, n, p] (with_dy) at a batch of points."""
    z = torch.cat([xhat, y], dim=1)
    net = propagate(spec, arith, z, columns_needed(spec, with_dy))
    r = Hx = None
    if spec.needs_h:
        Hx = system.jac_h(xhat)  # [B, p, n]
        if with_k or spec.structural:
            r = y - system.h(xhat)  # [B, p]
    return compose(spec, arith, net, r, Hx, with_dy=with_dy, with_k=with_k)


def gain_value(spec: GainSpec, system: Any, xhat: torch.Tensor, y: torch.Tensor,
               h_xhat: torch.Tensor | None = None, arith: Any = ROWS) -> torch.Tensor:
    """k(xhat, y) [B, n] alone (no derivatives); `h_xhat` = h(xhat) when already known."""
    net = propagate(spec, arith, arith.inputs(xhat, y), 0)
    r = None
    if spec.needs_h:
        r = y - (system.h(xhat) if h_xhat is None else h_xhat)
    return compose(spec, arith, net, r, None, with_dy=False).k
