"""How a box that did not close is split: a score per dimension, by one of three rules, and
the rule chosen per problem by probing (issue 9).

No rule wins everywhere (measured against the best of all d bisections, children closed per
split, boxes of radius 1/16 of the root): on the 2x10 4-state chain "sensitivity" 1.02,
"taylor" 0.93, "widest" 0.81 (best 1.08); on the 2x10 Van der Pol instance "widest" 1.61,
"taylor" 0.75, "sensitivity" 0.65 (best 1.66). So `choose_split_rule` tries the rules on a
few deterministic boxes that do not close and keeps the one whose chosen splits close the
most children. Only the choice of split depends on it, never soundness.
"""

from __future__ import annotations

import torch

SPLIT_RULES = ("sensitivity", "taylor", "widest")


def split_score(rule: str, taylor_score: torch.Tensor, r: torch.Tensor,
                root_width: torch.Tensor | None, net) -> torch.Tensor:
    """Score [B, d] (the largest is split) from the Taylor score (first-order variation plus
    remainder share, `certify.bounds.taylor.tm_lam_upper`) and the radii r [B, d]:

    - "taylor": the Taylor score;
    - "widest": r_m / root width_m;
    - "sensitivity": r_m sum_i |W_0[i, m]| (how much z_m widens the first layer's
      pre-activations, where the network's remainders come from) plus half the Taylor
      score, each scaled to a maximum of 1.
    """
    if rule == "taylor":
        return taylor_score
    if rule == "widest":
        return r / root_width if root_width is not None else r
    W0 = net.weights()[0][0].to(torch.float64)
    sens = r * W0.abs().sum(0)
    sens = sens / sens.amax(-1, keepdim=True).clamp_min(1e-300)
    sc = torch.nan_to_num(taylor_score, nan=0.0, posinf=0.0)
    sc = sc / sc.amax(-1, keepdim=True).clamp_min(1e-300)
    return sens + 0.5 * sc


def choose_split_rule(bounds, root_lo: torch.Tensor, root_hi: torch.Tensor,
                      probes: int = 64, scales: tuple[float, ...] = (1 / 8, 1 / 16)) -> str:
    """The rule of `SPLIT_RULES` whose splits close the most children on deterministic probe
    boxes that do not close (ties: the earlier rule). `bounds(lo, hi, rule)` -> (upper [B],
    score [B, d]) is the box bound (only its sign and score are used)."""
    d = root_lo.shape[0]
    w = (root_hi - root_lo).to(torch.float64)
    g = torch.Generator().manual_seed(2468)
    u = torch.rand(probes, d, generator=g, dtype=torch.float64)
    los, his = [], []
    for sc in scales:
        c = root_lo + w * (sc + (1 - 2 * sc) * u)
        los.append(c - w * sc)
        his.append(c + w * sc)
    lo, hi = torch.cat(los), torch.cat(his)
    ub, _ = bounds(lo, hi, SPLIT_RULES[0])
    keep = ub > 0
    if int(keep.sum()) < 4:
        return SPLIT_RULES[0]
    lo, hi = lo[keep], hi[keep]
    B = len(lo)
    closed = torch.empty(B, d, dtype=torch.float64)
    for m in range(d):
        mid = 0.5 * (lo[:, m] + hi[:, m])
        h1, l2 = hi.clone(), lo.clone()
        h1[:, m] = mid
        l2[:, m] = mid
        u1, _ = bounds(torch.cat([lo, l2]), torch.cat([h1, hi]), SPLIT_RULES[0])
        closed[:, m] = (u1[:B] <= 0).double() + (u1[B:] <= 0).double()
    best, best_val = SPLIT_RULES[0], -1.0
    ar = torch.arange(B)
    for rule in SPLIT_RULES:
        _, score = bounds(lo, hi, rule)
        s = torch.nan_to_num(score, nan=0.0) + 1e-3 * (hi - lo) / w  # as the B&B breaks ties
        val = float(closed[ar, s.argmax(-1)].mean())
        if val > best_val:
            best, best_val = rule, val
    return best
