"""The open boxes of branch and bound, kept so that a round costs O(its own boxes).

Every round takes a batch out of the open boxes and later adds the batch's children; with
plain tensors both are a copy of the whole frontier (hundreds of thousands of boxes late in
a long proof: tens of ms a round, all of it on the driver). `Frontier` keeps the boxes in
slots of preallocated buffers: adding writes behind the last slot (capacity doubles when
full), taking or closing clears a slot's `alive` flag, and the buffers are compacted (live
slots moved to the front, in slot order) only when more than half the used slots are dead:
amortised O(1) per box. Choosing the batch is two `topk`s over the live upper bounds, not a
sort. Everything is a function of the frontier's contents and slot order only, so two runs
that add and take the same boxes in the same order take the same batches (branch and
bound's deterministic rounds, `certify.bnb`).
"""

from __future__ import annotations

import math

import torch


class Frontier:
    """Open boxes: lo, hi [slot, d] (float64), depth [slot], upper bound [slot] and split
    score [slot, d] (None once any box came without one)."""

    #: compact only past this many used slots (and more than half of them dead)
    COMPACT_MIN = 4096

    def __init__(self, d: int, capacity: int = 4096, with_score: bool = True,
                 device: torch.device | str = "cpu") -> None:
        self.d = d
        self.used = 0  # slots written since the last compaction
        self.count = 0  # live boxes
        f64 = dict(dtype=torch.float64, device=device)
        self.lo = torch.empty(capacity, d, **f64)
        self.hi = torch.empty(capacity, d, **f64)
        self.depth = torch.empty(capacity, dtype=torch.long, device=device)
        self.ub = torch.empty(capacity, **f64)
        self.alive = torch.zeros(capacity, dtype=torch.bool, device=device)
        self.score: torch.Tensor | None = (torch.empty(capacity, d, **f64)
                                           if with_score else None)

    def __len__(self) -> int:
        return self.count

    def add(self, lo: torch.Tensor, hi: torch.Tensor, depth: torch.Tensor, ub: torch.Tensor,
            score: torch.Tensor | None) -> None:
        """Append boxes (in their order) behind the last used slot."""
        m = int(lo.shape[0])
        if score is None:
            self.score = None
        if m == 0:
            return
        self._reserve(self.used + m)
        s = slice(self.used, self.used + m)
        self.lo[s], self.hi[s], self.depth[s], self.ub[s] = lo, hi, depth, ub
        if self.score is not None:
            self.score[s] = score
        self.alive[s] = True
        self.used += m
        self.count += m

    def live(self) -> torch.Tensor:
        """Slot indices of the live boxes, in slot order."""
        return torch.nonzero(self.alive[:self.used]).squeeze(1)

    def take(self, k: int, nearest_half: bool) -> tuple[torch.Tensor, ...]:
        """Remove and return (lo, hi, depth, score) of the `k` boxes to refine: the largest
        upper bounds (NaN counts as +inf), worst first; with `nearest_half`, only the first
        (k+1)//2 of them, then the k//2 smallest (nearest to closing). All when k >= count."""
        live = self.live()
        key = torch.nan_to_num(self.ub[live], nan=math.inf)
        k = min(k, len(live))
        if nearest_half and len(live) > k:
            kw = (k + 1) // 2
            worst = torch.topk(key, kw).indices
            others = torch.ones(len(live), dtype=torch.bool, device=live.device)
            others[worst] = False
            others = torch.nonzero(others).squeeze(1)
            near = others[torch.topk(key[others], k - kw, largest=False).indices]
            pick = live[torch.cat([worst, near])]
        else:
            pick = live[torch.topk(key, k).indices]
        out = (self.lo[pick], self.hi[pick], self.depth[pick],
               self.score[pick] if self.score is not None else None)
        self._drop(pick)
        return out

    def close(self, level: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Remove the live boxes with upper <= level (finite; NaN stays open); their lo, hi
        and upper bounds in slot order, or None when none closes."""
        live = self.live()
        ub = self.ub[live]
        shut = (ub <= level) & (ub < math.inf)
        if not bool(shut.any()):
            return None
        pick = live[shut]
        out = (self.lo[pick], self.hi[pick], ub[shut])
        self._drop(pick)
        return out

    def open_max(self) -> float:
        """Largest live upper bound (NaN counts as +inf); -inf when empty."""
        if self.count == 0:
            return -math.inf
        return float(torch.nan_to_num(self.ub[self.live()], nan=math.inf).max())

    def boxes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """lo, hi of the live boxes in slot order."""
        live = self.live()
        return self.lo[live], self.hi[live]

    def _drop(self, slots: torch.Tensor) -> None:
        self.alive[slots] = False
        self.count -= int(slots.numel())
        if self.used > self.COMPACT_MIN and 2 * self.count < self.used:
            self._compact()

    def _compact(self) -> None:
        live = self.live()
        m = len(live)
        for name in ("lo", "hi", "depth", "ub", "score"):
            buf = getattr(self, name)
            if buf is not None:
                buf[:m] = buf[live]
        self.alive[:m] = True
        self.alive[m:self.used] = False
        self.used = m

    def _reserve(self, size: int) -> None:
        cap = self.lo.shape[0]
        if size <= cap:
            return
        new = max(size, 2 * cap)
        for name in ("lo", "hi", "depth", "ub", "score", "alive"):
            buf = getattr(self, name)
            if buf is None:
                continue
            grown = (torch.zeros if name == "alive" else torch.empty)(
                (new, *buf.shape[1:]), dtype=buf.dtype, device=buf.device)
            grown[:self.used] = buf[:self.used]
            setattr(self, name, grown)
