"""The Jacobian a proof's matrix is made of: J_cl = Jf + dk/dxhat, or the path certificate's J~.

For a problem without a noise input the prover bounds D = He{P J_cl} + 2 lam P (+ Q). With
one (`certify.model.problem.NoiseInput`) it bounds D~ = He{P~ J~} + 2 lam P~ + Q~ with

    J~ = [[J_cl, dk/dy], [0, 0]]   [m, m], m = n + p,

J_cl and dk/dy at the *same* point (xhat, y) of the box. Both enclosures below are built from
the enclosures the MPDI already uses (`certify.enclose.network_interval.gain_enclosure`,
`certify.enclose.taylor.gain_taylor`, whose dk/dy is enclosed with dk/dxhat in one pass) by
placing exact zeros: every member of J~'s enclosure is J~ at some point of the box when the
two blocks' enclosures hold there, so the stages' arguments (congruence, lam_max bounds) carry
over unchanged to the larger matrix.
"""

from __future__ import annotations

import torch

from certify.arith.interval_ops import iadd
from certify.arith.intervals import Interval
from certify.arith.taylor import TM, tm_add
from certify.enclose.network_interval import GainEnclosure
from certify.enclose.system_taylor import jacobian_tm
from certify.enclose.taylor import gain_taylor, jcl_taylor, network_taylor
from certify.model.problem import Problem


def jacobian_columns(problem: Problem) -> list[int]:
    """The network's input columns the matrix reads: xhat's, and y's with a noise input."""
    return list(range(problem.m))


def _pad(top_left: torch.Tensor, top_right: torch.Tensor, p: int) -> torch.Tensor:
    """[[A, B], [0, 0]] over the dims (1, 2) of A [N, n, n, ...] and B [N, n, p, ...]."""
    top = torch.cat([top_left, top_right], 2)
    shape = list(top.shape)
    shape[1] = p
    return torch.cat([top, torch.zeros(shape, dtype=top.dtype, device=top.device)], 1)


def closed_loop_box(problem: Problem, g: GainEnclosure) -> Interval:
    """Interval enclosure of the proof's Jacobian over boxes from their `gain_enclosure`:
    J_cl = Jf + dk/dxhat [N, n, n], or J~ [N, m, m] with a noise input."""
    J = iadd(g.jf, g.dk_dx)
    if problem.noise is None:
        return J
    p = problem.p
    return Interval(_pad(J.lo, g.dk_dy.lo, p), _pad(J.hi, g.dk_dy.hi, p))


def closed_loop_tm(problem: Problem, lo: torch.Tensor, hi: torch.Tensor,
                   net_tms: tuple[TM, TM, torch.Tensor] | None = None) -> TM:
    """First-order Taylor model of the proof's Jacobian over z-boxes [N, d]: `jcl_taylor`, or
    J~ [N, m, m] with a noise input (dk/dy from the same `gain_taylor` pass; the network's
    models `net_tms` as there, needing every column of `jacobian_columns`)."""
    system, net = problem.system, problem.network
    if problem.noise is None:
        return jcl_taylor(system, net, lo, hi, net_tms=net_tms)
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    net_tms = network_taylor(net, lo, hi) if net_tms is None else net_tms
    r = net_tms[2]
    gv = gain_taylor(system, net, lo, hi, net_tms, with_k=False, with_dy=True)
    J = tm_add(jacobian_tm(system, "f", lo, hi, r), gv.dk_dx, r)
    B, p = gv.dk_dy, problem.p
    return TM(_pad(J.c, B.c, p), _pad(J.g, B.g, p), _pad(J.e, B.e, p))
