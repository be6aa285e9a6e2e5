"""Verification-aware training: penalise how fast the gain's Jacobian dk/dxhat varies.

Why: the prover encloses D = He{P (Jf + dk/dxhat)} + 2 lam P on a sub-box by its value near
the centre plus a remainder that grows with the variation of dk/dxhat over the box (the
curvature its Taylor and linear bounds must absorb). Two networks with the same training loss
can need very different numbers of sub-boxes; this term prefers the one whose Jacobian is
nearly constant at the prover's scale.

The term is a finite-difference estimate of the Jacobian's Lipschitz constant at a small
radius r: pairs (z1, z2) of X x Y at distance r in normalised coordinates (each coordinate
divided by its side of the box), both inside the box, and

    C = mean_j relu(||J(z1_j) - J(z2_j)||_F^2 / r^2 - tol),    J = dk/dxhat,

added to the loss as `weight * C`. C is zero when dk/dxhat is constant (a linear gain: the
zero network with K and a linear h), positive for a curved one, and differentiable in the
weights almost everywhere. The pairs are drawn once per objective (seeded, so training stays
deterministic); J comes from the one propagation of the gain (`certify.model.gain.propagate`, row
layout, autograd through it for the weight gradient). Cost: 2 x `pairs` forward-mode
evaluations and one reverse pass per step, small beside the collocation trunk.

Nothing here is trusted by the verifier; it only shapes training.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.model.gain import ROWS, GainSpec, compose, propagate
from certify.spec.system import System


@dataclass(frozen=True)
class CurvatureSettings:
    """The penalty's weight, pair radius (fraction of each box side), pair count, tolerance."""

    weight: float = 0.0
    radius: float = 0.02
    pairs: int = 256
    tol: float = 0.0

    def __post_init__(self) -> None:
        for name in ("weight", "radius", "tol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"curvature: {name} must be a finite number >= 0; got {v!r}")
        if not 0 < self.radius < 0.5:
            raise ValueError(f"curvature: radius must be in (0, 0.5); got {self.radius!r}")
        if not isinstance(self.pairs, int) or isinstance(self.pairs, bool) or self.pairs < 1:
            raise ValueError(f"curvature: pairs must be an int >= 1; got {self.pairs!r}")


def sample_pairs(system: System, pairs: int, radius: float, seed: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """`pairs` point pairs of X x Y, float64 [pairs, n + p] each, at normalised distance
    `radius`: z1 uniform in the box shrunk by radius * side, z2 = z1 + radius * side * u
    with u a uniform unit vector, so both lie in the box."""
    box = np.concatenate([system.X, system.Y], 0)
    lo = torch.as_tensor(box[:, 0], dtype=torch.float64)
    hi = torch.as_tensor(box[:, 1], dtype=torch.float64)
    side = hi - lo
    gen = torch.Generator().manual_seed(int(seed))
    d = lo.numel()
    z1 = lo + radius * side + (1 - 2 * radius) * side * torch.rand(
        pairs, d, generator=gen, dtype=torch.float64)
    u = torch.randn(pairs, d, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True).clamp_min(1e-300)
    return z1, z1 + radius * side * u


class CurvaturePenalty:
    """C (see the module docstring) at fixed pairs, for the network whose spec is given at
    each call (its weights may change between calls: optimisers update them in place)."""

    def __init__(self, system: System, settings: CurvatureSettings, seed: int,
                 dtype: torch.dtype = torch.float32) -> None:
        self.settings = settings
        n = system.n
        z1, z2 = sample_pairs(system, settings.pairs, settings.radius, seed)
        z = torch.cat([z1, z2])  # one propagation for both ends
        self.z = z.to(dtype)
        self.r = self.Hx = None
        xhat, y = z[:, :n], z[:, n:]
        self.r = (y - system.h(xhat)).to(dtype)
        self.Hx = system.jac_h(xhat).to(dtype)

    def value(self, spec: GainSpec) -> torch.Tensor:
        """C as a 0-d tensor, differentiable in the spec's weights."""
        s = self.settings
        net = propagate(spec, ROWS, self.z, spec.n)  # dk/dxhat needs the xhat columns only
        r = self.r if spec.needs_h else None
        Hx = self.Hx if spec.needs_h else None
        J = compose(spec, ROWS, net, r, Hx, with_dy=False, with_k=False).dk_dx
        m = J.shape[0] // 2
        diff = J[:m] - J[m:]
        v = (diff * diff).sum(dim=(1, 2)) / (s.radius * s.radius)
        return torch.relu(v - s.tol).mean()
