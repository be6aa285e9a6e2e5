"""Boxes in float64 and their exact bisection: the geometry every box search shares.

A `Box` is a batch of axis-aligned boxes lo <= z <= hi [B, d] with their bisection depth.
`initial_grid` cuts a root box into about `target` equal boxes and `split` bisects boxes
along given dimensions; both keep shared faces exact (the two halves of a bisection meet at
the same float midpoint, and the root's faces are its own), so the boxes of a search cover
the root box with no gap whatever the rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Box:
    """A batch of boxes: lo, hi [batch, d] (float64) and their bisection depth [batch]."""

    lo: torch.Tensor
    hi: torch.Tensor
    depth: torch.Tensor

    @property
    def centre(self) -> torch.Tensor:
        return 0.5 * (self.lo + self.hi)

    def volume(self) -> torch.Tensor:
        return (self.hi - self.lo).prod(-1)

    def __len__(self) -> int:
        return int(self.lo.shape[0])


def initial_grid(lo: torch.Tensor, hi: torch.Tensor, target: int) -> Box:
    """Split the root box [d] into about `target` equal boxes (more cuts on wider sides)."""
    d = lo.shape[0]
    width = (hi - lo).double()
    sides = width.cpu()  # the cut counts are chosen on the CPU
    cuts = torch.ones(d, dtype=torch.long, device="cpu")
    while int(cuts.prod()) * 2 <= max(target, 1):
        i = int(torch.argmax(sides / cuts))
        cuts[i] *= 2
    axes = [torch.linspace(0.0, 1.0, int(c) + 1, dtype=torch.float64, device=lo.device)
            for c in cuts]
    los = torch.cartesian_prod(*[a[:-1] for a in axes]).reshape(-1, d)
    his = torch.cartesian_prod(*[a[1:] for a in axes]).reshape(-1, d)
    blo = lo + los * width
    bhi = lo + his * width
    # exact shared faces and the exact root faces
    blo = torch.where(los == 0, lo.expand_as(blo), blo)
    bhi = torch.where(his == 1, hi.expand_as(bhi), bhi)
    depth = torch.full((blo.shape[0],), int(torch.log2(cuts.double()).sum()), dtype=torch.long,
                       device=lo.device)
    return Box(blo, bhi, depth)


def split(box: Box, dims: torch.Tensor) -> Box:
    """Bisect each box along dims [N]; the two halves share the (float) midpoint exactly.
    The first halves come first, then the second halves, in the order of `box`."""
    N = len(box)
    ar = torch.arange(N, device=box.lo.device)
    mid = 0.5 * (box.lo[ar, dims] + box.hi[ar, dims])
    lo1, hi1 = box.lo.clone(), box.hi.clone()
    lo2, hi2 = box.lo.clone(), box.hi.clone()
    hi1[ar, dims] = mid
    lo2[ar, dims] = mid
    depth = box.depth + 1
    return Box(torch.cat([lo1, lo2]), torch.cat([hi1, hi2]), torch.cat([depth, depth]))
