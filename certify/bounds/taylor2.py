"""Second-order Taylor models over boxes: q(z) in c + g . dz + dz^T H dz / 2 + [-e, e],
dz = z - zc, |dz| <= r, and a sound bound of lam_max over a box for matrix-valued ones.

Used by the MPDI prover where the first-order bound fails (issue 9, the 2x10 4-6-state
chains): the network's Jacobian is propagated with its exact Hessian at the box centre
(`certify.gain.taylor2.Taylor2Arithmetic` over `certify.gain.propagate`) and a third-order
remainder. Only tanh networks (the activation's third and fourth derivatives are bounded
on the range of each pre-activation: |tanh'''| <= min(2, 4 sech^2(a)), |tanh''''| <=
min(4.9, 16 sech^2(a)), a the distance of the range from 0; sup |tanh''''| = 4.8895).

Rounding: every operation computes c, g and H in floating point and adds Higham's gamma_k
times the magnitude of the exact terms (|c| + sum |g| r + r^T |H| r / 2, each factor's
magnitude) to e, rounded up; the centre values tanh(c), tanh'(c), tanh''(c) are the midpoints of
the activation's point enclosures (their radii go into e), tanh'''(c) = -2 s (1 - 3 t^2) is
computed from them with an absolute error bound 2^-44 (at most 132 ulps of 1). Truncated
terms (products of the polynomial parts beyond degree 2, the Lagrange remainders) are
bounded with the same magnitudes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from certify.bounds.eigen import (
    MAX_VERTEX_DIM,
    _vertices,
    lam_max_upper_point,
    rho_upper,
    vertex_max_upper,
)
from certify.intervals import TINY, Interval, down, gamma, up

U = 2.0**-53
D3_TANH = 2.0  # sup |tanh'''|
D4_TANH = 4.9  # sup |tanh''''| = 4.88945... (at tanh x = 0.4769)
F3_ERR = 2.0**-44  # absolute error of the float tanh'''(c) from the enclosed t, s


@dataclass
class TM2:
    """Second-order Taylor model over boxes: value c [...], gradient g [..., d], Hessian
    H [..., d, d] (point), remainder e [...] >= 0, valid for |z - zc| <= r."""

    c: torch.Tensor
    g: torch.Tensor
    H: torch.Tensor
    e: torch.Tensor


def _r(r: torch.Tensor, ndim: int) -> torch.Tensor:
    """Radii [B, d] shaped to broadcast against a value tensor with `ndim` dims (+ d)."""
    return r.reshape(r.shape[0], *([1] * (ndim - 1)), r.shape[1])


def mags(t: TM2, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum |g| r, r^T |H| r / 2), rounded up: bounds of the linear and quadratic parts."""
    d = r.shape[-1]
    rr = _r(r, t.c.ndim)
    m1 = up((t.g.abs() * rr).sum(-1) * (1.0 + 2.0 * gamma(d + 1)))
    m2 = (t.H.abs() * rr.unsqueeze(-1)).sum(-2)
    m2 = up(0.5 * (m2 * rr).sum(-1) * (1.0 + 2.0 * gamma(2 * d + 2)))
    return m1, m2


def tm2_absorb(c: torch.Tensor, g: torch.Tensor, H: torch.Tensor, e: torch.Tensor,
               r: torch.Tensor, k: int) -> TM2:
    """Add gamma_k (|c| + sum |g| r + r^T |H| r / 2) to e (the float errors of c, g, H)."""
    gk = gamma(k)
    m1, m2 = mags(TM2(c, g, H, e), r)
    e = up((e + gk * (c.abs() + m1 + m2)) * (1.0 + 2.0 * gk) + k * TINY)
    return TM2(c, g, H, e)


def tm2_lift(c: torch.Tensor, g: torch.Tensor, e: torch.Tensor) -> TM2:
    """A first-order model as a second-order one (H = 0)."""
    d = g.shape[-1]
    return TM2(c, g, torch.zeros(*g.shape, d, dtype=g.dtype), e)


def tm2_linear(t: TM2, W: torch.Tensor, b: torch.Tensor | None, r: torch.Tensor) -> TM2:
    """x -> x @ W (+ b) on the last value dim: t.c [..., k]; W [k, m]."""
    k = W.shape[0]
    gk = gamma(k + 2)
    c = t.c @ W
    if b is not None:
        c = c + b
    g = torch.einsum("...kd,km->...md", t.g, W)
    H = torch.einsum("...kde,km->...mde", t.H, W)
    m1, m2 = mags(t, r)
    e = (t.e + gk * (t.c.abs() + m1 + m2)) @ W.abs()
    if b is not None:
        e = e + gk * (b.abs() + c.abs())
    return TM2(c, g, H, up(e * (1.0 + 2.0 * gk) + k * TINY))


def tm2_add(a: TM2, b: TM2, r: torch.Tensor) -> TM2:
    return tm2_absorb(a.c + b.c, a.g + b.g, a.H + b.H, up(a.e + b.e), r, 2)


def tm2_mul(a: TM2, b: TM2, r: torch.Tensor) -> TM2:
    """Elementwise product (broadcasting): degree-2 part kept, the rest in e."""
    c = a.c * b.c
    g = a.c.unsqueeze(-1) * b.g + b.c.unsqueeze(-1) * a.g
    ga, gb = torch.broadcast_tensors(a.g, b.g)
    H = (a.c[..., None, None] * b.H + b.c[..., None, None] * a.H
         + ga.unsqueeze(-1) * gb.unsqueeze(-2) + gb.unsqueeze(-1) * ga.unsqueeze(-2))
    a1, a2 = mags(a, r)
    b1, b2 = mags(b, r)
    ma, mb = up(a1 + a2), up(b1 + b2)
    trunc = a1 * b2 + a2 * b1 + a2 * b2  # degree 3 and 4 products of the polynomial parts
    rem = a.e * (b.c.abs() + mb) + b.e * (a.c.abs() + ma) + a.e * b.e
    fl = gamma(4) * (a.c.abs() + ma) * (b.c.abs() + mb)  # float errors of c, g, H
    e = up((trunc + rem + fl) * (1.0 + 8 * U) + 4 * TINY)
    return TM2(c, g, H, e)


def _sech2_far(c: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """Upper bound of sech^2 over [c - rho, c + rho] (1 when it contains 0)."""
    a = down(c.abs() - rho).clamp_min(0.0)
    t = down(torch.tanh(a)) * (1.0 - 8 * U)
    return up(1.0 - t * t).clamp(max=1.0)


def tm2_tanh_and_dtanh(t: TM2, r: torch.Tensor) -> tuple[TM2, TM2]:
    """TM2s of tanh(q) and tanh'(q) for a TM2 q: with u = q - c (|u| <= rho),
    f(q) = f(c) + f'(c) u + f''(c) u^2 / 2 + f'''(xi) u^3 / 6, and the same for f'; u = p + eps
    (p the polynomial part), u^2 = (g . dz)^2 + [p^2 - (g . dz)^2] + 2 p eps + eps^2 with the
    bracket at most 2 m1 m2 + m2^2. Centre values: midpoints of the point enclosures."""
    from certify.activations.tanh import TANH

    m1, m2 = mags(t, r)
    m = up(m1 + m2)
    rho = up(m + t.e)
    cI = Interval(t.c, t.c)
    t0, et0 = TANH.enclose_f(cI).midrad()
    s0, es0 = TANH.enclose_d1(cI).midrad()
    s2, es2 = TANH.enclose_d2(cI).midrad()
    s3 = -2.0 * s0 * (1.0 - 3.0 * t0 * t0)
    es3 = F3_ERR
    sf = _sech2_far(t.c, rho)
    M3 = torch.clamp(4.0 * sf, max=D3_TANH)
    M4 = torch.clamp(16.0 * sf, max=D4_TANH)
    gg = t.g.unsqueeze(-1) * t.g.unsqueeze(-2)
    sq = 2.0 * m1 * m2 + m2 * m2 + 2.0 * m * t.e + t.e * t.e  # |u^2 - (g . dz)^2|
    rho3 = rho * rho * rho / 6.0

    def model(v0, ev0, v1, ev1, v2, ev2, Mx) -> TM2:
        g = v1.unsqueeze(-1) * t.g
        H = v1[..., None, None] * t.H + v2[..., None, None] * gg
        e = (ev0 + (v1.abs() + ev1) * t.e + ev1 * m + 0.5 * (v2.abs() + ev2) * sq
             + 0.5 * ev2 * m1 * m1 + Mx * rho3
             + gamma(4) * (v0.abs() + v1.abs() * m + v2.abs() * m1 * m1))
        return TM2(v0, g, H, up(e * (1.0 + 16 * U) + 8 * TINY))

    A = model(t0, et0, s0, es0, s2, es2, M3)
    S = model(s0, es0, s2, es2, s3, es3, M4)
    return A, S


def tm2_lam_upper(A: TM2, r: torch.Tensor, level: float | None = None) -> torch.Tensor:
    """Upper bound of max over each box of lam_max(A(z)) for a symmetric matrix model A
    [B, n, n]: with the quadratic part split into its pairs j < m (multilinear: exact at the
    vertices) and its diagonal H_jj dz_j^2 / 2 <= (H_jj + tau_j I) dz_j^2 / 2, tau_j >= the
    negative part of lam_min(H_jj) (so the diagonal terms are PSD, convex in dz_j), the
    upper model is convex in each coordinate separately, so its lam_max is largest at one of
    the 2^d vertices, where dz_j^2 = r_j^2. Bound: max over vertices of lam_max(vertex matrix)
    + rho(e + float error of the vertex matrices). level: as in
    `certify.bounds.taylor.tm_lam_upper` (certified Cholesky decision for n >= 4)."""
    B, n, _, d = A.g.shape
    if d > MAX_VERTEX_DIM:
        return torch.full((B,), float("inf"), dtype=torch.float64)
    H = A.H.permute(0, 3, 4, 1, 2)  # [B, d, d, n, n]
    H = 0.5 * (H + H.transpose(-1, -2))
    idx = torch.arange(d)
    Hd = H[:, idx, idx]  # [B, d, n, n]
    tau = lam_max_upper_point(-Hd).clamp_min(0.0)  # >= -lam_min(H_jj)
    r2 = r * r
    eye = torch.eye(n, dtype=torch.float64)
    K = A.c + 0.5 * ((Hd + tau[..., None, None] * eye) * r2[:, :, None, None]).sum(1)
    jj, mm = torch.triu_indices(d, d, 1)
    Hp = 0.5 * (H[:, jj, mm] + H[:, mm, jj]) * (r[:, jj] * r[:, mm])[:, :, None, None]
    rG = (A.g * r[:, None, None, :]).permute(0, 3, 1, 2)  # [B, d, n, n]
    V = _vertices(d)
    VV = V[:, jj] * V[:, mm]  # [V, pairs]
    S = (K[:, None] + torch.einsum("vd,bdij->bvij", V, rG)
         + torch.einsum("vp,bpij->bvij", VV, Hp))
    S = 0.5 * (S + S.transpose(-1, -2))
    k = 2 * d + len(jj) + 8
    gk = gamma(k)
    absum = (A.c.abs() + rG.abs().sum(1) + Hp.abs().sum(1)
             + 0.5 * ((Hd.abs() + tau[..., None, None] * eye) * r2[:, :, None, None]).sum(1))
    rem = up((A.e + gk * absum) * (1.0 + 2.0 * gk) + k * TINY)
    rem = torch.maximum(rem, rem.transpose(1, 2))
    rr = rho_upper(rem)
    if level is not None and n >= 4:
        lvl = float(level) - 1e-12 * (1.0 + abs(float(level)))
        t = down(lvl - rr)
        lv, ok = vertex_max_upper(S, t)
        return torch.where(ok, torch.full_like(rr, lvl), up(lv + rr))
    return up(lam_max_upper_point(S).amax(-1) + rr)


def network_taylor2(net, lo: torch.Tensor, hi: torch.Tensor, m: int
                    ) -> tuple[TM2, TM2, torch.Tensor]:
    """TM2s over boxes of N(z) [B, out] and dN/dz[:, :, :m] [B, out, m]; returns radii r.
    `certify.gain.propagate` in `certify.gain.taylor2.Taylor2Arithmetic` (tanh only)."""
    from certify.gain.propagate import propagate
    from certify.gain.taylor2 import Taylor2Arithmetic

    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    zc = 0.5 * (lo + hi)
    r = up(torch.maximum(hi - zc, zc - lo))
    out = propagate(net.spec(torch.float64, detach=True), Taylor2Arithmetic(zc, r), None, m)
    return out.value, out.jac, r


def contraction_tm2_mixed(problem, pc, lo: torch.Tensor, hi: torch.Tensor, lam: float
                          ) -> tuple[TM2, torch.Tensor]:
    """(TM2 of A = He{P J} + 2 lam P over boxes, radii r) for M = I and a direct tanh network: the
    first-order model of everything but the network (`certify.bounds.mixed.contraction_rest`,
    lifted) plus He{P dN/dxhat} from `network_taylor2` (P applied as a linear map)."""
    from certify.bounds.mixed import contraction_rest

    n = problem.n
    _, J, r = network_taylor2(problem.network, lo, hi, n)  # [B, n, n]
    rest = contraction_rest(problem, pc, lo, hi, r, lam)
    Jt = TM2(J.c.transpose(1, 2), J.g.transpose(1, 2), J.H.transpose(1, 2), J.e.transpose(1, 2))
    X = tm2_linear(Jt, problem.P_t.to(torch.float64).T, None, r)  # (P J)^T
    c = 0.5 * (X.c + X.c.transpose(1, 2))
    g = 0.5 * (X.g + X.g.transpose(1, 2))
    H = 0.5 * (X.H + X.H.transpose(1, 2))
    he = tm2_absorb(c, g, H, up(0.5 * up(X.e + X.e.transpose(1, 2))), r, 2)
    return tm2_add(tm2_lift(rest.c, rest.g, rest.e), he, r), r
