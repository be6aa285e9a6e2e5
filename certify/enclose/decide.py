"""Certified decision of lam_max(A) <= level over a box for an affine matrix family plus a
remainder: A(v) = c + sum_m v_m G_m + E, v in [-1, 1]^d, E symmetric with |E| <= rem
entrywise (the form `certify.enclose.taylor.tm_lam_upper` reduces a box to, n >= 4).

lam_max is convex, so the affine part is largest at a vertex of the cube, and
lam_max(A(v)) <= lam_max(c + sum v_m G_m) + rho(rem). Three tests, cheapest first, each one
proves the decision on its own (`decide_affine_family`):

1. Weyl: lam_max(c) + sum_m ||G_m||_F <= t = level - rho(rem) (one eigenproblem per box);
2. the vertices: every vertex matrix minus t I negative definite by the certified Cholesky
   test (`certify.arith.eigen.lam_max_at_most`), after one test of the vertex most likely
   to fail (most boxes that fail, fail there);
3. the same two tests after a congruence by the box's own metric M = (lvl I - c)^(-1/2)
   (`room_congruence`): M (A - lvl I) M <= 0 iff A <= lvl I, and in those coordinates the
   remainder counts in proportion to the room the centre leaves in each direction, not at
   the room of the tightest one (rho(|M| rem |M|) against 1, not rho(rem) against
   lvl - lam_max(c)); on the boxes tests 1-2 leave it decides many more
   (`bench/remainder_gap.py`'s `closed_by_prover`).

Rounding: M is any float matrix (a congruence by a nonsingular M preserves the decision,
and a singular one makes the test fail, never pass); the float errors of forming M c M and
M G_m M, at most gamma_{2n+2} |M| |X| |M| entrywise (Higham, two matrix products), and those
of shifting c by lvl join the remainder, all bounds rounded up. Vertex sums are rounded as in
`tm_lam_upper` (gamma_{d+5} (|c| + sum |G_m|) in the remainder).
"""

from __future__ import annotations

import torch

from certify.arith.eigen import cube_vertices, lam_max_at_most, lam_max_upper_point, rho_upper
from certify.arith.intervals import TINY, down, gamma, up
from certify.arith.linalg import eigh


def decide_affine_family(c: torch.Tensor, rG: torch.Tensor, rem: torch.Tensor,
                         rr: torch.Tensor, lvl: float, congruence: bool = True
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """(decided [B], Weyl's upper bound of the affine part [B]) for c [B, n, n], rG
    [B, d, n, n], rem [B, n, n] (symmetric, >= 0, already covering the rounding of the vertex
    sums c + sum v_m rG_m) and rr = rho_upper(rem): decided means lam_max(A) <= lvl is proved
    on the whole box (module docstring, tests 1-3). The Weyl bound ranks the boxes that are
    not decided (their bound in the branch and bound)."""
    t = down(lvl - rr)  # proved vertex max <= t  =>  vertex max + rr <= lvl
    weyl = weyl_upper(c, rG)
    decided = weyl <= t
    # NaN/Inf never decide, and LAPACK's eigh must not see them
    finite = torch.isfinite(weyl) & torch.isfinite(rr)
    need = torch.nonzero(~decided & finite).squeeze(-1)
    worst = None
    if len(need):
        worst = likely_worst_vertex(c[need], rG[need])
        at_worst = c[need] + torch.einsum("bd,bdij->bij", worst, rG[need])
        decided[need] = vertex_test(c[need], rG[need], t[need], worst, at_worst)
    if congruence and len(need):
        left = ~decided[need]
        if bool(left.any()):
            # a congruence preserves inertia: where the likeliest-worst vertex matrix is not
            # even proved <= lvl (the remainder aside), no M decides the box (most of the
            # boxes that reach this stage on the larger chains), so only the others go on
            left[left.clone()] = lam_max_at_most(
                at_worst[left],
                torch.full((int(left.sum()),), lvl, dtype=c.dtype, device=c.device))
        if bool(left.any()):
            idx = need[left]
            parts = room_congruence(c[idx], rG[idx], rem[idx], lvl)
            if parts is None:  # eigh failed: the boxes stay undecided (sound)
                return decided, weyl
            cc, gc, rc = parts
            d = rG.shape[1]
            gk = gamma(d + 5)
            rc = up((rc + gk * (cc.abs() + gc.abs().sum(1))) * (1.0 + 2.0 * gk) + (d + 2) * TINY)
            rc = torch.maximum(rc, rc.transpose(1, 2))
            tc = down(-rho_upper(rc))
            ok = weyl_upper(cc, gc) <= tc
            rest = torch.nonzero(~ok).squeeze(-1)
            if len(rest):
                ok[rest] = vertex_test(cc[rest], gc[rest], tc[rest], worst[left][rest])
            decided[idx] = ok
    return decided, weyl


def vertex_test(c: torch.Tensor, rG: torch.Tensor, t: torch.Tensor, worst: torch.Tensor,
                at_worst: torch.Tensor | None = None) -> torch.Tensor:
    """Whether lam_max(c + sum_m v_m rG_m) <= t is proved at every vertex v (certified
    Cholesky tests of the lower triangles), the vertex `worst` [B, d] tested first: a box
    that fails there needs no other test. `at_worst`: that vertex's matrix, when the caller
    has formed it."""
    out = torch.zeros(c.shape[0], dtype=torch.bool, device=c.device)
    if at_worst is None:
        at_worst = c + torch.einsum("bd,bdij->bij", worst, rG)
    first = lam_max_at_most(at_worst, t)
    need = torch.nonzero(first).squeeze(-1)
    if len(need):
        S = vertex_matrices(c[need], rG[need], sym=False)
        out[need] = lam_max_at_most(S, t[need, None].expand(len(need), S.shape[1])).all(-1)
    return out


def vertex_matrices(c: torch.Tensor, rG: torch.Tensor, sym: bool) -> torch.Tensor:
    """c + sum_m v_m rG_m at the 2^d vertices v of [-1, 1]^d: [B, 2^d, n, n] (float; the
    caller's remainder covers the rounding); `sym`: symmetrised, else as computed (for
    consumers of the lower triangle only)."""
    S = c[:, None] + torch.einsum("vd,bdij->bvij", cube_vertices(rG.shape[1], rG.device), rG)
    return 0.5 * (S + S.transpose(-1, -2)) if sym else S


def likely_worst_vertex(c: torch.Tensor, rG: torch.Tensor) -> torch.Tensor:
    """The vertex v in {-1, 1}^d that maximises the first-order change of lam_max(sym(c) +
    sum_m v_m rG_m) at v = 0: v_m = sign(u^T rG_m u), u the top eigenvector of sym(c)
    (float; a guess that orders the vertex tests, never part of a bound). Many boxes the
    Weyl bound leaves fail at many vertices, and those need only this test. c [B, n, n],
    rG [B, d, n, n] -> [B, d]."""
    try:
        u = eigh(0.5 * (c + c.transpose(-1, -2)))[1][..., -1]  # [B, n]
    except RuntimeError:  # LAPACK did not converge: any vertex is a valid first guess
        return torch.ones(rG.shape[:2], dtype=c.dtype, device=c.device)
    q = torch.einsum("bi,bdij,bj->bd", u, rG, u)
    return torch.where(q >= 0, 1.0, -1.0).to(c.dtype)


def weyl_upper(c: torch.Tensor, rG: torch.Tensor) -> torch.Tensor:
    """Upper bound of lam_max(sym(c) + sum_m v_m rG_m) over v in [-1, 1]^d: lam_max(sym(c))
    + sum_m ||rG_m||_F (Weyl; the spectral norm is at most the Frobenius norm), rounded up.
    c [B, n, n], rG [B, d, n, n]; the float errors of sym(c) and of the vertex sums are
    those the caller's remainder already covers."""
    d = rG.shape[1]
    lc = lam_max_upper_point(0.5 * (c + c.transpose(-1, -2)))
    fro = torch.linalg.matrix_norm(rG).sum(-1)
    return up(lc + up(fro * (1.0 + 2.0 * gamma(d * rG.shape[-1] ** 2 + 2))))


def lower_sym(X: torch.Tensor) -> torch.Tensor:
    """The symmetric matrix of X's lower triangle (what LAPACK and the vertex tests read;
    exact, no rounding)."""
    return X.tril() + X.tril(-1).transpose(-1, -2)


def room_congruence(c: torch.Tensor, rG: torch.Tensor, rem: torch.Tensor, lvl: float
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """(M (c - lvl I) M, M rG_m M, remainder) with M = (lvl I - c)^(-1/2) per box (c and rG_m
    read by their lower triangles, as the vertex tests read them; the eigenvalues of
    lvl I - c clamped away from 0; any nonsingular float M serves): the remainder bounds
    |M E M| for every |E| <= rem plus the float errors of the shift and of both congruences
    (module docstring), so that A <= lvl I on the box follows from the transformed family
    being <= 0. None where LAPACK's eigh fails."""
    n = c.shape[-1]
    eye = torch.eye(n, dtype=c.dtype, device=c.device)
    c = lower_sym(c)
    rG = lower_sym(rG)
    cs = c - lvl * eye
    shift_err = gamma(2) * (c.abs() + abs(lvl)) * eye  # one rounding on the diagonal
    try:
        ev, Q = eigh(-cs)
    except RuntimeError:
        return None
    ev = torch.maximum(ev, ev[..., -1:].abs() * 1e-12 + TINY)
    M = (Q * ev.rsqrt()[..., None, :]) @ Q.transpose(-1, -2)
    M = 0.5 * (M + M.transpose(-1, -2))
    Mc = M @ cs @ M
    MG = M[:, None] @ rG @ M[:, None]
    Ma = M.abs()
    g2 = gamma(2 * n + 2)
    inner = rem + shift_err + g2 * (cs.abs() + rG.abs().sum(1))
    rc = up((Ma @ inner @ Ma) * (1.0 + 2.0 * g2) + TINY)
    return Mc, MG, rc
