"""Linear bounds of the second hidden layer's pre-activations and tangents through the first
layer, in closed form (the forward pass's cost on two-layer networks).

The backward pass (`certify.enclose.crown_backward.backward_pass`) is general: any depth, value and
derivative paths, products relaxed by McCormick planes. Through the first layer alone its
queries have a closed form. With pre_0 = W0 z + b0 exact (real arithmetic), the first
layer's parallel-line relaxations f(pre_0l) = A_l pre_0l + mu_l and f'(pre_0l) = a_l pre_0l +
nu_l (|mu_l - m_al| <= w_al, |nu_l - m_sl| <= w_sl, `BackwardLayer`'s lines) and the Jacobian
column Q_0^j = f'(pre_0) * W0[:, j] (t_0 = W0 is a point: no product relaxation), over the
box z = zc + dz, |dz| <= r:

    pre_1k = sum_l W1_kl (A_l p_l + m_al) + b1_k + G_k . dz + sum_l W1_kl (mu_l - m_al),
    t_1kj  = sum_l W1_kl W0_lj (a_l p_l + m_sl) + H_kj . dz + sum_l W1_kl W0_lj (nu_l - m_sl),

p = W0 zc + b0, G = W1 diag(A) W0, H_kj = sum_l W1_kl W0_lj a_l W0_l: the same linear functions
the general pass composes (equal up to rounding), from a few batched products instead of a
pass with McCormick planes of the point tangent and per-layer slack constants (through the
general pass, the second layer's queries had been most of the forward pass's time on
two-layer networks: `bench/prove_suite.py`; `certify.enclose.crown.forward_bounds`'s
`closed_form` compares the two).

Rounding (each bound for the real-number quantity, the float values as computed): p is a
float product, |p - (W0 zc + b0)| <= gamma_{d+1} (|W0| |zc| + |b0|) = e_p; the centre terms
v = A p + m_a (and a p + m_s) carry |A| e_p + gamma_2 (|A p| + |m_a|); each sum of products
of k float factors over l carries gamma_{h1+k+1} times the same sum of magnitudes; the
radius collects all of these, the relaxation radii and |G| r (|H| r), and is rounded up
with a factor (1 + gamma_{h1+d+4}) for its own sums; the ends are rounded outward.
"""

from __future__ import annotations

import torch

from certify.arith.intervals import TINY, down, gamma, up


def second_layer_ranges(first, W1: torch.Tensor, b1: torch.Tensor, cols: torch.Tensor,
                        zc: torch.Tensor, r: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(pre_lo, pre_hi [B, h], t_lo, t_hi [B, h, J]): sound ranges of pre_1 and of the tangent
    columns t_1[:, :, cols] over the boxes zc +- r, from the first layer `first` (a
    `certify.enclose.crown_backward.BackwardLayer` with no composed-layer slack) and the second
    layer's weights W1 [h, h1], b1 [h] (module docstring)."""
    W0, b0 = first.W.to(torch.float64), first.b.to(torch.float64)
    W1, b1 = W1.to(torch.float64), b1.to(torch.float64)
    h1, d = W0.shape
    e = lambda x: x[:, 0, 0, :]  # noqa: E731  [B, 1, 1, h1] -> [B, h1]
    A, m_a, w_a = e(first.a_a), e(first.m_a), e(first.w_a)
    a_s, m_s, w_s = (e(x) for x in first.slope_lines())
    W0a, W1a = W0.abs(), W1.abs()
    rr = r.to(torch.float64)
    p = zc @ W0.T + b0  # [B, h1]
    e_p = up(gamma(d + 1) * (zc.abs() @ W0a.T + b0.abs()) * (1.0 + 4 * gamma(1)) + TINY)
    widen = 1.0 + gamma(h1 + d + 4)

    def centre_term(slope: torch.Tensor, mid: torch.Tensor) -> tuple[torch.Tensor,
                                                                     torch.Tensor]:
        v = slope * p + mid
        ev = up(slope.abs() * e_p + gamma(2) * (slope.abs() * p.abs() + mid.abs()) + TINY)
        return v, ev

    # the value: pre_1 = W1 v + b1 + G dz + W1 (mu - m_a)
    v, ev = centre_term(A, m_a)
    c = v @ W1.T + b1
    G = (W1[None] * A[:, None, :]) @ W0  # [B, h, d]
    G_abs = (W1a[None] * A.abs()[:, None, :]) @ W0a
    g1 = gamma(h1 + 3)
    rad = (up(w_a + ev) @ W1a.T + g1 * (v.abs() @ W1a.T + b1.abs())
           + ((G.abs() + g1 * G_abs) * rr[:, None, :]).sum(-1))
    rad = up(rad * widen + TINY)
    pre_lo, pre_hi = down(c - rad), up(c + rad)
    # the tangent columns: t_1[:, :, j] = (W1 * W0[:, j]) u + H_j dz + (W1 * W0[:, j]) (nu - m_s)
    u, eu = centre_term(a_s, m_s)
    W0c = W0[:, cols]  # [h1, J]
    ct = torch.einsum("kl,lj,bl->bkj", W1, W0c, u)
    H = torch.einsum("kl,lj,bl,lm->bkjm", W1, W0c, a_s, W0)  # [B, h, J, d]
    H_abs = torch.einsum("kl,lj,bl,lm->bkjm", W1a, W0c.abs(), a_s.abs(), W0a)
    g2 = gamma(h1 + 4)
    rad_t = (torch.einsum("kl,lj,bl->bkj", W1a, W0c.abs(), up(w_s + eu) + g2 * u.abs())
             + ((H.abs() + g2 * H_abs) * rr[:, None, None, :]).sum(-1))
    rad_t = up(rad_t * widen + TINY)
    return pre_lo, pre_hi, down(ct - rad_t), up(ct + rad_t)
