"""Collocation points: N points drawn uniformly from the box X x Y, seeded.

The source method trains on uniform samples of X x Y (no trajectories, no labels). Points are
drawn in float64 from a private `torch.Generator`, so the global RNG is untouched and the same
seed gives the same points whatever the training dtype.
"""

from __future__ import annotations

import numpy as np
import torch

from certify.spec.system import System


def uniform_in_box(box: np.ndarray, count: int, generator: torch.Generator) -> torch.Tensor:
    """`count` points uniform in the box `[[lo, hi], ...]` (shape [d, 2]) -> [count, d] float64."""
    b = torch.as_tensor(np.asarray(box, dtype=np.float64))
    lo, hi = b[:, 0], b[:, 1]
    u = torch.rand(count, b.shape[0], generator=generator, dtype=torch.float64)
    return lo + (hi - lo) * u


def collocation_points(system: System, count: int, seed: int
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(xhat [count, n], y [count, p]) uniform in X x Y, float64, reproducible from `seed`."""
    if count < 1:
        raise ValueError(f"need at least one collocation point; got {count}")
    gen = torch.Generator().manual_seed(int(seed))
    xhat = uniform_in_box(system.X, count, gen)
    y = uniform_in_box(system.Y, count, gen)
    return xhat, y
