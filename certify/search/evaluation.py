"""What an evaluation of boxes returns to branch and bound, and joining evaluated pieces.

`BoxEval` is the contract between the branch-and-bound driver (`certify.search.bnb`), the
rounds in flight (`certify.search.rounds`) and every bound that evaluates boxes (the MPDI and
side proofs in `certify.prove`): per box a sound upper bound, a float value at the centre,
an optional split score, which boxes were evaluated at all and the statistics of the
bound's stages.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["BoxEval", "add_counts", "join"]


@dataclass
class BoxEval:
    """What `evaluate` returns for N boxes."""

    upper: torch.Tensor  # [N] sound upper bound over the box (NaN: unknown)
    centre_value: torch.Tensor  # [N] value at the centre in float64 (a lower bound of the max)
    score: torch.Tensor | None = None  # [N, d] split score (None: widest scaled dimension)
    #: [N] bool: which boxes were evaluated (None: all). A box not evaluated (its round ran
    #: out of time, `RoundClock`) has upper and centre_value NaN and score 0
    done: torch.Tensor | None = None
    #: statistics of the bound's stages over these boxes, name -> {count name -> int}
    #: (`certify.enclose.mpdi.BoxBounds.counts`; None: the bound has no stages)
    counts: dict[str, dict[str, int]] | None = None


def add_counts(total: dict[str, dict[str, int]], more: dict[str, dict[str, int]] | None
               ) -> dict[str, dict[str, int]]:
    """`total` with `more`'s counts added, name by name (in place; also returned)."""
    for name, cs in (more or {}).items():
        into = total.setdefault(name, {})
        for k, v in cs.items():
            into[k] = into.get(k, 0) + int(v)
    return total


def join(parts: list[BoxEval]) -> BoxEval:
    """The `BoxEval`s of consecutive pieces of a round as one, in order (a score only when
    every piece evaluated has one; `done` only where some box was not evaluated)."""
    if len(parts) == 1:
        return parts[0]
    done = None
    if any(p.done is not None for p in parts):
        done = torch.cat([p.done if p.done is not None
                          else torch.ones(len(p.upper), dtype=torch.bool,
                                          device=p.upper.device) for p in parts])
    score = None
    if all(p.score is not None for p in parts if p.done is None or bool(p.done.any())):
        d = next((p.score.shape[1] for p in parts if p.score is not None), 0)
        score = torch.cat([p.score if p.score is not None
                           else torch.zeros(len(p.upper), d, dtype=torch.float64,
                                            device=p.upper.device) for p in parts])
    counts = None
    if any(p.counts is not None for p in parts):
        counts = {}
        for p in parts:
            add_counts(counts, p.counts)
    return BoxEval(upper=torch.cat([p.upper for p in parts]),
                   centre_value=torch.cat([p.centre_value for p in parts]), score=score,
                   done=done, counts=counts)
