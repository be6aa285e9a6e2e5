"""The open boxes of branch and bound, kept so that a round costs O(its own boxes).

Every round takes a batch out of the open boxes and later adds the batch's children; with
plain tensors both are a copy of the whole frontier (hundreds of thousands of boxes late in
a long proof, all of it on the driver). `Frontier` keeps the boxes in
slots of preallocated buffers: adding writes behind the last slot (capacity doubles when
full), taking or closing clears a slot's `alive` flag, and the buffers are compacted (live
slots moved to the front, in slot order) only when more than half the used slots are dead:
amortised O(1) per box.

Choosing the batch is a `topk`, not a sort, and on a large frontier not over all of it: two
candidate pools (`_Pools`) hold the slots whose upper bound is at least tau_top (every such
live slot: the worst boxes) and at most tau_bot (the nearest to closing), each about
sqrt(count * k) slots when built. A take selects within the pools (O(pool)); `add` puts new
slots past a threshold into its pool; a pool is rebuilt from the whole frontier (O(count))
only when it runs short of a batch, grows past 4x its built size, or a compaction moves the
slots. The worst k of the frontier are the worst k of the top pool whenever that pool holds
at least k live slots (every slot outside it is below tau_top, every slot inside at or
above), and the same for the nearest, so the pools change the cost, not the boxes taken
(up to the order among equal bounds). `bench/frontier.py` compares the cost of a take from
the pools with a full scan by frontier size.

Everything is a function of the frontier's contents and the order of the calls only, so two
runs that add and take the same boxes in the same order take the same batches (branch and
bound's deterministic rounds, `certify.search.bnb`).
"""

from __future__ import annotations

import math

import torch


class Frontier:
    """Open boxes: lo, hi [slot, d] (float64), depth [slot], upper bound [slot] and split
    score [slot, d] (None once any box came without one)."""

    #: compact only past this many used slots (and more than half of them dead)
    COMPACT_MIN = 4096
    #: take from candidate pools only past this many live boxes (and 8 batches)
    POOL_MIN = 65536

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
        self._pools: _Pools | None = None
        self._unpooled = 0  # takes left before pooling is tried again

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
        if self._pools is not None:
            self._pools.admit(torch.arange(self.used, self.used + m, device=self.alive.device),
                              _key(ub))
        self.used += m
        self.count += m

    def live(self) -> torch.Tensor:
        """Slot indices of the live boxes, in slot order."""
        return torch.nonzero(self.alive[:self.used]).squeeze(1)

    def take(self, k: int, nearest_half: bool, with_upper: bool = False
             ) -> tuple[torch.Tensor, ...]:
        """Remove and return (lo, hi, depth, score) of the `k` boxes to refine: the largest
        upper bounds (NaN counts as +inf), worst first; with `nearest_half`, only the first
        (k+1)//2 of them, then the k//2 smallest (nearest to closing). All when k >= count.
        `with_upper`: their upper bounds too, as a fifth item. On a frontier of more than
        POOL_MIN boxes the choice is made in the candidate pools (module docstring)."""
        if self.count > max(self.POOL_MIN, 8 * k) and self._unpooled <= 0:
            pick = self._take_pooled(k, nearest_half)
            if pick is not None:
                return self._remove(pick, with_upper)
            self._unpooled = 16  # the pools could not be separated: scan for a while
        self._unpooled -= 1
        live = self.live()
        key = _key(self.ub[live])
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
        return self._remove(pick, with_upper)

    def _remove(self, pick: torch.Tensor, with_upper: bool = False
                ) -> tuple[torch.Tensor, ...]:
        out = (self.lo[pick], self.hi[pick], self.depth[pick],
               self.score[pick] if self.score is not None else None)
        if with_upper:
            out = (*out, self.ub[pick])
        self._drop(pick)
        return out

    def _take_pooled(self, k: int, nearest_half: bool) -> torch.Tensor | None:
        """The slots `take` picks, chosen within the pools (rebuilt when short); None when
        the pools cannot be kept apart (the whole frontier within one bound): scan all."""
        kw = (k + 1) // 2 if nearest_half else k
        pools = self._pools
        for _ in range(2):
            if pools is None or pools.nearest != nearest_half:
                pools = self._pools = _Pools.build(self, k, nearest_half)
                if pools is None:
                    return None
            top = pools.top_live(self.alive)
            bot = pools.bottom_live(self.alive) if nearest_half else None
            if len(top) >= kw and (bot is None or len(bot) >= k - kw) and not pools.bloated():
                worst = top[torch.topk(_key(self.ub[top]), kw).indices]
                if bot is None:
                    return worst
                near = bot[torch.topk(_key(self.ub[bot]), k - kw, largest=False).indices]
                return torch.cat([worst, near])
            pools = None
        return None

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
        self._pools = None  # the slots move
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


def _key(ub: torch.Tensor) -> torch.Tensor:
    """The order of refinement: the upper bound, NaN as +inf (an unbounded box is worst)."""
    return torch.nan_to_num(ub, nan=math.inf)


class _Pools:
    """Candidate slots for `Frontier.take` (module docstring): `top` holds every live slot
    with key >= tau_top, `bottom` (nearest_half) every live slot with key <= tau_bot <
    tau_top; both may hold dead slots, dropped when read."""

    def __init__(self, top: torch.Tensor, tau_top: float, bottom: torch.Tensor | None,
                 tau_bot: float, nearest: bool, built: int) -> None:
        self.top, self.tau_top = top, tau_top
        self.bottom, self.tau_bot = bottom, tau_bot
        self.nearest = nearest
        self.built = built  # the larger pool's size when built

    @staticmethod
    def build(fr: Frontier, k: int, nearest: bool) -> _Pools | None:
        """Pools of about sqrt(count * k) slots each (at least 4 batches) from the whole
        frontier; None when their thresholds would not separate them."""
        live = fr.live()
        key = _key(fr.ub[live])
        m = min(len(live), max(4 * k, int(math.sqrt(len(live) * k))))
        tau_top = float(torch.topk(key, m).values.min())
        tau_bot = -math.inf
        bottom = None
        if nearest:
            tau_bot = float(torch.topk(key, m, largest=False).values.max())
            if not tau_bot < tau_top:
                return None
            bottom = live[key <= tau_bot]
        return _Pools(live[key >= tau_top], tau_top, bottom, tau_bot, nearest, m)

    def admit(self, slots: torch.Tensor, key: torch.Tensor) -> None:
        """New slots with their keys: those past a threshold join its pool."""
        self.top = torch.cat([self.top, slots[key >= self.tau_top]])
        if self.bottom is not None:
            self.bottom = torch.cat([self.bottom, slots[key <= self.tau_bot]])

    def top_live(self, alive: torch.Tensor) -> torch.Tensor:
        self.top = self.top[alive[self.top]]
        return self.top

    def bottom_live(self, alive: torch.Tensor) -> torch.Tensor:
        if self.bottom is None:
            raise ValueError("pools built without nearest_half have no bottom pool")
        self.bottom = self.bottom[alive[self.bottom]]
        return self.bottom

    def bloated(self) -> bool:
        """A pool grew past 4x its built size: rebuild it (a take costs O(pool))."""
        big = max(len(self.top), 0 if self.bottom is None else len(self.bottom))
        return big > 4 * self.built
