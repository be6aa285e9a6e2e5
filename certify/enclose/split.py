"""How a box that did not close is split: a score per dimension, by one of three rules.
Only the choice of split depends on it, never soundness.

Against the best of all d bisections each rule wins on some families and loses on others,
but in whole proofs the rule changed the box count only a little (`bench/prove_suite.py`),
and probing for the rule per problem cost more than it saved, so the prover uses the
default, "sensitivity"; the others stay selectable
(`certify.enclose.options.box_bound_options(split_rule=...)`).
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
