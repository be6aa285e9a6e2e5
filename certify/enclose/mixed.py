"""Linear bound propagation for mixed Jacobian rows R dN/dz and the contraction matrix built
from them: with the congruence M = I (`certify.enclose.preconditioner`), A = He{P J} + 2 lam
P (+ Q), and bounding P dN/dx directly keeps the cancellations between the outputs that P
mixes (a smaller remainder than |P| times the entrywise remainders of dN/dx;
`bench/remainder_gap.py` measures the remainders).

Rounding: R W_H is a float product whose error is bounded with gamma_k |.| and added outward
(`mixed_jacobian_crown` says how); the rest is
`certify.enclose.crown`'s and `certify.enclose.taylor`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.arith.intervals import TINY, Interval, U, down, gamma, up
from certify.arith.taylor import TM, tm_absorb, tm_add
from certify.enclose.crown import (
    ForwardBounds,
    LinearEnclosure,
    backward_pass,
    forward_bounds,
    queries,
    to_tm,
)
from certify.enclose.preconditioner import constant_term
from certify.enclose.taylor import jcl_taylor, tm_congruence
from certify.enclose.top_rank import TopRank, lower_apart_applies, top_rank
from certify.model.network import GainNetwork


@dataclass
class TopLayerRemainder:
    """The relaxation errors of the last hidden layer's products kept as a product: the exact
    R dN/dz lies within the linear enclosure plus C eps, C = R W_H [m, h] (the float product
    the backward pass used), eps [B, h, J] one matrix for all rows with |eps[b, k, j]| <=
    w[b, j, k] (`BackwardLayer.col_consts`' WQ). Bounding C eps entrywise (sum_k |C_ik| w_jk) loses
    the signs of C; `certify.enclose.structured` keeps them."""

    C: torch.Tensor  # [m, h]
    w: torch.Tensor  # [B, J, h]
    #: the errors' rank structure (one or two hidden layers; `certify.enclose.top_rank`)
    rank: TopRank | None = None


def mixed_jacobian_crown(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
                         cols: list[int], rows: torch.Tensor, fb: ForwardBounds,
                         top_apart: bool = False
                         ) -> tuple[LinearEnclosure, TopLayerRemainder | None]:
    """Linear lower/upper bounds of (R dN/dz)_{ij} over each box, R = `rows` [m, out] a point
    matrix, j in cols -> [B, m, J]: the backward passes start from the rows of R W_H, so
    the cancellations between the outputs that R mixes are kept (bounding dN/dz and then
    multiplying by |R| loses them). R W_H is a float product: its error, at most
    gamma_{out+2} |R| |W_H| entrywise, times |Q_{H-1}^j| (forward magnitudes), widens both
    lines, rounded up. top_apart: the last hidden layer's relaxation errors are left out of
    the lines and returned as a `TopLayerRemainder` (else None); with two hidden layers
    (`top_rank.lower_apart_applies`) so are the first layer's f' errors, returned in its
    `rank.lower`."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    B, d = lo.shape
    WH = net.weights()[-1][0].to(torch.float64)
    R = rows.to(torch.float64)
    m, out = R.shape
    RW = R @ WH
    delta = up(gamma(out + 2) * (R.abs() @ WH.abs()) * (1.0 + 4 * U))  # [m, h]
    colt = torch.as_tensor(cols, dtype=torch.long, device=lo.device)
    J = len(cols)
    LQ = queries(RW, J, B)
    lower = top_apart and lower_apart_applies(fb.layers)
    Lz, cl, cu = backward_pass(fb.layers, len(fb.layers), None, LQ,
                           torch.zeros(B, m, J, dtype=torch.float64, device=lo.device), colt,
                           lo, hi, top_apart=top_apart, lower_apart=lower)
    qm = fb.layers[-1].qmag(colt)  # [B, h, J]
    h = qm.shape[1]
    slack = up(torch.einsum("mh,bhj->bmj", delta, qm) * (1.0 + gamma(h + 2)) + TINY)
    le = LinearEnclosure(gl=Lz, cl=down(cl - slack), gu=Lz, cu=up(cu + slack))
    if not top_apart:
        return le, None
    WQ = fb.layers[-1].col_consts(colt)[4][:, 0]  # [B, J, h]
    return le, TopLayerRemainder(RW, WQ, top_rank(fb.layers, colt, RW, lower=lower))


def network_crown_mixed_jacobian(net: GainNetwork, lo: torch.Tensor, hi: torch.Tensor,
                                 cols: list[int], rows: torch.Tensor, top_apart: bool = False
                                 ) -> tuple[TM, TopLayerRemainder | None]:
    """TM of R dN/dz[:, cols] over each box [B, m, J] (R = `rows` [m, out]) from the linear
    bounds with the mixed rows (`mixed_jacobian_crown`) on forward ranges without Taylor
    models (`forward_bounds(taylor=False)`), and (top_apart) the last hidden layer's
    relaxation errors apart, as there. R times the forward Taylor model (entry by entry
    where tighter) is not taken: in whole proofs of the benchmark families it was never the
    tighter one, and propagating it was the forward pass's largest cost
    (`bench/prove_suite.py`)."""
    fb = forward_bounds(net, lo, hi, cols=cols, crown=True, taylor=False)
    le, top = mixed_jacobian_crown(net, lo, hi, cols, rows, fb, top_apart=top_apart)
    return to_tm(le, fb.r), top


def contraction_tm_mixed(problem, pc, lo: torch.Tensor, hi: torch.Tensor, r: torch.Tensor,
                         lam: float, top_apart: bool = False, constant: Interval | None = None
                         ) -> tuple[TM, TopLayerRemainder | None]:
    """TM of A = He{P J} + 2 lam P over each box for the congruence M = I (pc.kind "none")
    and a direct network: He{P (Jf - K dh/dx)} + 2 lam P from the Taylor models
    (`jcl_taylor` with the network's Jacobian left out, then `tm_congruence`, whose Q = I P
    encloses P), plus He{P dN/dx} from `network_crown_mixed_jacobian` with R = P exactly.
    top_apart: the last hidden layer's relaxation errors are not in the TM's remainder; A
    lies within the TM plus He{C eps} (the returned `TopLayerRemainder`; else None).
    `constant`: M (2 lam P + Q) M^T when the caller has it (`constant_term(pc, lam)`)."""
    n = problem.n
    rest = contraction_rest(problem, pc, lo, hi, r, lam, constant)
    Nt, top = network_crown_mixed_jacobian(problem.network, lo, hi, list(range(n)),
                                           problem.P_t, top_apart=top_apart)  # [B, n, n]
    c = 0.5 * (Nt.c + Nt.c.transpose(1, 2))
    g = 0.5 * (Nt.g + Nt.g.transpose(1, 2))
    e = 0.5 * up(Nt.e + Nt.e.transpose(1, 2))
    return tm_add(rest, tm_absorb(c, g, up(e), r, 2), r), top


def contraction_rest(problem, pc, lo: torch.Tensor, hi: torch.Tensor, r: torch.Tensor,
                     lam: float, constant: Interval | None = None) -> TM:
    """TM of He{P (Jf - K dh/dx)} + 2 lam P (+ Q) over boxes (a direct network's Jacobian
    left out): `jcl_taylor` with zero network models, then `tm_congruence` (`constant`: M (2
    lam P + Q) M^T when the caller has it, else `constant_term(pc, lam)`).

    When Jf and dh/dx are constant (a linear plant and output: the chain families) so is
    this matrix: its model is made on the first box only, and its centre and remainder
    serve every box with no first-order part (the model holds at that box's centre, where
    the constant is the function's value, so c +- e contains it everywhere); on the chain
    families this function had been a large share of the proof's time
    (`bench/prove_suite.py`)."""
    if problem.system.jacobians_constant and lo.shape[0] > 1:
        one = contraction_rest(problem, pc, lo[:1], hi[:1], r[:1], lam, constant)
        B, d = lo.shape
        n = one.c.shape[-1]
        return TM(one.c.expand(B, n, n), torch.zeros(B, n, n, d, dtype=one.c.dtype,
                                                     device=one.c.device),
                  one.e.expand(B, n, n))
    system, net = problem.system, problem.network
    n = problem.n
    B, d = lo.shape
    f64 = dict(dtype=torch.float64, device=lo.device)
    z = torch.zeros(B, n, **f64)
    val = TM(z, torch.zeros(B, n, d, **f64), z)
    jac0 = TM(torch.zeros(B, n, d, **f64), torch.zeros(B, n, d, d, **f64),
              torch.zeros(B, n, d, **f64))
    if constant is None:
        constant = constant_term(pc, lam)
    return tm_congruence(pc, jcl_taylor(system, net, lo, hi, net_tms=(val, jac0, r)), constant,
                         r)
