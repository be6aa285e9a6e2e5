"""How a box that did not close is split: a score per dimension, by one of three rules
(issue 9). Only the choice of split depends on it, never soundness.

Measured against the best of all d bisections (children closed per split, boxes of radius
1/16 of the root): on the 2x10 4-state chain "sensitivity" 1.02, "taylor" 0.93, "widest" 0.81
(best 1.08); on the 2x10 Van der Pol instance, on boxes with some sides already halved,
"widest" 1.61, "taylor" 0.75, "sensitivity" 0.65 (best 1.66). In whole proofs the rule
changed the box count by under 3% on both (n=4: 402k "sensitivity" vs 400k "taylor"; n=2:
1828 "widest" vs 1870), and probing for the rule per problem cost more than it saved, so
the prover uses the default; the others stay selectable (`mpdi_box_bounds(split_rule=...)`).
"""

from __future__ import annotations

import torch

SPLIT_RULES = ("sensitivity", "taylor", "widest")


def split_score(rule: str, taylor_score: torch.Tensor, r: torch.Tensor,
                root_width: torch.Tensor | None, net) -> torch.Tensor:
    """Score [B, d] (the largest is split) from the Taylor score (first-order variation plus
    remainder share, `certify.enclose.taylor.tm_lam_upper`) and the radii r [B, d]:

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
