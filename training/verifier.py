"""Training for the verifier: penalise the box bound the prover would compute, not only points.

Why: the prover closes a sub-box when a sound upper bound of lam_max(D) over the whole box
is <= 0, and its bound is a first-order Taylor model of D over the box (centre value,
first-order coefficients, remainder; `certify.enclose.taylor`) turned into an eigenvalue
bound. Two networks with the same point loss can need trees of very different sizes: what
the proof pays for is how far that box bound sits above the point values at the box sizes
the tree reaches. This term trains that bound directly.

The term. Boxes Z_b = zc_b +- rho_b side are drawn in X x Y (seeded, per round: `sample_boxes`)
at a few relative half-widths `radii` (shrinking sizes: the large ones are where a proof
would like to close, the small ones where it must). For each box a first-order Taylor model
D(z) in Dc + sum_m G_m (z_m - zc_m) / r_m + [-E, E] over the box is measured in the room the
centre leaves below the level -margin (`room_terms`): the centre's height
h_b = lam_max(sym(Dc_b)) + margin and the variation in the room's metric,
s_b = sum_m ||L^-1 G_bm L^-T||_F + ||L^-1 E_b L^-T||_F with L L^T = -margin I - sym(Dc_b).
Where h_b < 0 and s_b < 1 the box's family is below the level (Weyl in the room's metric: the
prover's congruence test, `certify.enclose.decide`), so the term is

    V = mean_b [relu(h_b) + relu(s_b - ratio)]

(ratio < 1 leaves the prover's rounding and the surrogate's gap some room), and the
objective adds `weight * V`. Where the centre is not below the level, the room's smallest
eigenvalue is raised to `floor` to measure s_b and h_b carries the penalty.

The Taylor model is a *surrogate* of the prover's, differentiable in the weights:
`SurrogateTaylor` runs the one propagation of the gain (`certify.model.gain.propagate`,
`compose`) over first-order Taylor models with the prover's formulas (`certify.model.gain.
taylor.TaylorArithmetic`) but in the training dtype and without outward rounding (its
remainders are real-number bounds: |f''| and |f'''| of the activation bounded by constants
measured once on a dense grid, `activation_bounds`). Jf and dh/dxhat over the boxes are the
prover's own sound Taylor models (`certify.enclose.system_taylor.jacobian_tm`, weight-free,
made once per set of boxes). Nothing here is trusted by the verifier: it only shapes
training, and `certify run` proves the result from scratch.

Cost per evaluation: one Taylor-model propagation over `boxes` boxes (the tangent rows carry
d + 1 numbers per neuron and input column), one eigenvalue problem, one Cholesky
factorisation and d + 1 congruences per box,
with autograd through both: comparable to the curvature term (`training.curvature`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.model.activations import Activation
from certify.model.gain import GainSpec, NetOutput, compose, propagate
from certify.model.kernels import sym
from certify.spec.system import System


@dataclass(frozen=True)
class VerifierSettings:
    """The term's weight, the margin its boxes are held to, the relative half-widths of
    the boxes (fractions of each side of X x Y; one group of `boxes` boxes per radius)."""

    weight: float = 0.0
    margin: float = 0.05
    radii: tuple[float, ...] = (1 / 8, 1 / 16, 1 / 32)
    boxes: int = 64
    ratio: float = 0.5  # the variation s held below this share of the room (< 1)
    floor: float = 0.05  # smallest room eigenvalue used to measure s (where the centre is
    # not below the level its height is penalised instead)

    def __post_init__(self) -> None:
        for name in ("weight", "margin", "ratio", "floor"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"verifier: {name} must be a finite number >= 0; got {v!r}")
        if (not isinstance(self.radii, tuple) or not self.radii
                or any(not (isinstance(r, (int, float)) and 0 < r < 0.5) for r in self.radii)):
            raise ValueError(f"verifier: radii must be a non-empty tuple of numbers in (0, 0.5);"
                             f" got {self.radii!r}")
        if not isinstance(self.boxes, int) or isinstance(self.boxes, bool) or self.boxes < 1:
            raise ValueError(f"verifier: boxes must be an int >= 1; got {self.boxes!r}")


def sample_boxes(system: System, radii: tuple[float, ...], per_radius: int, seed: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Boxes inside X x Y: centres uniform in the box shrunk by rho * side, half-widths
    rho * side, `per_radius` boxes per rho in `radii` -> (zc, r) float64 [B, n + p] each."""
    box = np.concatenate([system.X, system.Y], 0)
    lo = torch.as_tensor(box[:, 0], dtype=torch.float64)
    side = torch.as_tensor(box[:, 1] - box[:, 0], dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed))
    zcs, rs = [], []
    for rho in radii:
        u = torch.rand(per_radius, lo.numel(), generator=gen, dtype=torch.float64)
        zcs.append(lo + rho * side + (1.0 - 2.0 * rho) * side * u)
        rs.append((rho * side).expand(per_radius, -1))
    return torch.cat(zcs), torch.cat(rs)


_BOUNDS: dict[str, tuple[float, float]] = {}


def activation_bounds(act: Activation) -> tuple[float, float]:
    """(sup |f''|, sup |f'''| or inf) of the activation, the first measured on a dense grid
    of [-40, 40] with 5% room (a surrogate's constant: nothing sound rests on it), the second
    the activation's own `d3_bound`."""
    if act.name not in _BOUNDS:
        x = torch.linspace(-40.0, 40.0, 400_001, dtype=torch.float64)
        m2 = float(act.d2(x).abs().max()) * 1.05
        _BOUNDS[act.name] = (m2, float(act.d3_bound))
    return _BOUNDS[act.name]


@dataclass
class STM:
    """A surrogate first-order Taylor model: value c [...] + sum_m g[..., m] u_m + [-e, e]
    for every u in [-1, 1]^d (coefficients already scaled by the box radii)."""

    c: torch.Tensor
    g: torch.Tensor
    e: torch.Tensor

    def reach(self) -> torch.Tensor:
        """sum_m |g_m|: the radius of the affine part's range."""
        return self.g.abs().sum(-1)


def _mul(a: STM, b: STM) -> STM:
    """Elementwise product (broadcasting): the affine parts multiplied out to first order,
    the rest (cross term and remainders) bounded by (|g_a| + e_a)(|g_b| + e_b)."""
    c = a.c * b.c
    g = a.c.unsqueeze(-1) * b.g + b.c.unsqueeze(-1) * a.g
    e = a.c.abs() * b.e + b.c.abs() * a.e + (a.reach() + a.e) * (b.reach() + b.e)
    return STM(c, g, e)


def _add(a: STM, b: STM) -> STM:
    return STM(a.c + b.c, a.g + b.g, a.e + b.e)


def _neg(a: STM) -> STM:
    return STM(-a.c, -a.g, a.e)


def _index(a: STM, idx: tuple) -> STM:
    if Ellipsis in idx:
        return STM(a.c[idx], a.g[idx + (slice(None),)], a.e[idx])
    return STM(a.c[idx], a.g[idx], a.e[idx])


def _sum(a: STM, dim: int) -> STM:
    return STM(a.c.sum(dim), a.g.sum(dim), a.e.sum(dim))


class SurrogateTaylor:
    """`certify.model.gain.propagate` / `compose` over `STM`s on the boxes zc +- r (module
    docstring): the prover's first-order Taylor-model formulas without outward rounding,
    differentiable in the spec's weights. First derivatives only (order 1)."""

    def __init__(self, zc: torch.Tensor, r: torch.Tensor, act: Activation) -> None:
        self.zc, self.r = zc, r
        self.m2, self.m3 = activation_bounds(act)

    def input_layer(self, z: None, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[STM, STM | None]:
        B, d = self.zc.shape
        pre = STM(self.zc @ W.T + b, W[None] * self.r[:, None, :],
                  torch.zeros(B, W.shape[0], dtype=W.dtype, device=W.device))
        if not m:
            return pre, None
        h = W.shape[0]
        T = STM(W[:, :m].T.expand(B, m, h), torch.zeros(B, m, h, d, dtype=W.dtype),
                torch.zeros(B, m, h, dtype=W.dtype))
        return pre, T

    def activate(self, act: Activation, pre: STM, layer: int, order: int
                 ) -> tuple[STM, STM, None]:
        """f(q) = f(c) + f'(c) (q - c) + f''(xi) (q - c)^2 / 2 and f'(q) likewise with f'''
        (a first-order remainder 2 sup|f''| |q - c| without a third derivative)."""
        if order >= 2:
            raise ValueError("the surrogate propagates first derivatives only")
        rho = pre.reach() + pre.e
        t0, s0, s2 = act.f(pre.c), act.d1(pre.c), act.d2(pre.c)
        a = STM(t0, pre.g * s0.unsqueeze(-1), s0.abs() * pre.e + 0.5 * self.m2 * rho * rho)
        rem = (0.5 * self.m3 * rho * rho if math.isfinite(self.m3) else 2.0 * self.m2 * rho)
        s = STM(s0, pre.g * s2.unsqueeze(-1), s2.abs() * pre.e + rem)
        return a, s, None

    def scale(self, s: STM, T: STM, layer: int) -> STM:
        return _mul(STM(s.c.unsqueeze(1), s.g.unsqueeze(1), s.e.unsqueeze(1)), T)

    def affine(self, a: STM, T: STM | None, S: None, W: torch.Tensor, b: torch.Tensor,
               layer: int) -> tuple[STM, STM | None, None]:
        def lin(x: STM, bias: torch.Tensor | None) -> STM:
            c = x.c @ W.T
            return STM(c if bias is None else c + bias,
                       torch.einsum("...kd,jk->...jd", x.g, W), x.e @ W.abs().T)

        return lin(a, b), (None if T is None else lin(T, None)), None

    def output(self, pre: STM, T: STM | None, S: None) -> NetOutput:
        jac = None if T is None else STM(T.c.transpose(1, 2), T.g.transpose(1, 2),
                                         T.e.transpose(1, 2))
        return NetOutput(pre, jac)

    # --- compose ---
    def cols(self, x: STM, start: int, stop: int) -> STM:
        return _index(x, (Ellipsis, slice(start, stop)))

    def reshape_out(self, out: STM, n: int, p: int) -> STM:
        B, d = out.c.shape[0], out.g.shape[-1]
        return STM(out.c.reshape(B, n, p), out.g.reshape(B, n, p, d), out.e.reshape(B, n, p))

    def reshape_jac(self, jac: STM, n: int, p: int) -> STM:
        B, m, d = jac.c.shape[0], jac.c.shape[-1], jac.g.shape[-1]
        return STM(jac.c.reshape(B, n, p, m), jac.g.reshape(B, n, p, m, d),
                   jac.e.reshape(B, n, p, m))

    def matvec(self, A: STM, v: STM) -> STM:
        return _sum(_mul(A, _index(v, (slice(None), None, slice(None)))), 2)

    def contract(self, dA: STM, v: STM) -> STM:
        return _sum(_mul(dA, _index(v, (slice(None), None, slice(None), None))), 2)

    def matmul(self, A: STM, B: STM) -> STM:
        return _sum(_mul(_index(A, (Ellipsis, None)), _index(B, (slice(None), None))), 2)

    def add(self, a: STM, b: STM) -> STM:
        return _add(a, b)

    def sub(self, a: STM, b: STM) -> STM:
        return _add(a, _neg(b))

    def const_matvec(self, K: torch.Tensor, v: STM) -> STM:
        return _index(self.const_matmul(K, _index(v, (Ellipsis, None))), (Ellipsis, 0))

    def const_matmul(self, K: torch.Tensor, A: STM) -> STM:
        return STM(K @ A.c, torch.einsum("ip,bpjd->bijd", K, A.g), K.abs() @ A.e)

    def add_const(self, a: STM, K: torch.Tensor) -> STM:
        return STM(a.c + K, a.g, a.e)


def room_terms(D: STM, level: float, floor: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(lam_max(sym(c)) - level, s) per box [B] for D [B, n, n]: the centre's height above
    the level and the variation measured in the room R = level I - sym(c) (its eigenvalues
    raised to at least `floor`, so that s stays finite where the centre is not below):
    s = sum_m ||L^-1 sym(g_m) L^-T||_F + ||L^-1 E L^-T||_F, R = L L^T, E = |L^-1| sym(e) |L^-T|
    entrywise. Where the centre is below the level and s < 1 the family is below it
    (Weyl in the room's metric, the prover's congruence test); differentiable (Cholesky,
    triangular solves, one eigenvalue problem per box)."""
    c = sym(D.c)
    n = c.shape[-1]
    eye = torch.eye(n, dtype=c.dtype, device=c.device)
    top = torch.linalg.eigvalsh(c)[..., -1]
    lift = torch.relu(floor - (level - top))  # raise R's smallest eigenvalue to >= floor
    L = torch.linalg.cholesky((level + lift)[:, None, None] * eye - c)
    Li = torch.linalg.solve_triangular(L, eye.expand_as(c), upper=False)
    g = sym(D.g.permute(0, 3, 1, 2))  # [B, d, n, n]
    Lg = Li[:, None] @ g @ Li[:, None].transpose(-1, -2)
    E = Li.abs() @ sym(D.e) @ Li.abs().transpose(-1, -2)
    s = torch.linalg.matrix_norm(Lg).sum(-1) + torch.linalg.matrix_norm(E)
    return top - level, s


class VerifierPenalty:
    """The term of the module docstring at fixed boxes (drawn once, seeded), for the network
    whose spec is given at each call (its weights change between calls), at rate `lam` in
    metric `P`. `K_in_spec`: whether the spec's K is part of the gain (False for the training
    objectives, whose trunk spec carries K but whose weight-free -K dh/dxhat is folded in
    elsewhere: here it is always included, from `K`)."""

    def __init__(self, system: System, settings: VerifierSettings, seed: int, *, lam: float,
                 P: torch.Tensor, K: torch.Tensor | None = None,
                 dtype: torch.dtype = torch.float32) -> None:
        from certify.arith.intervals import up
        from certify.enclose.system_taylor import jacobian_tm

        self.settings = settings
        self.system = system
        n, p = system.n, system.p
        zc, r = sample_boxes(system, settings.radii, settings.boxes, seed)
        lo, hi = zc - r, zc + r
        ru = up(r)
        with torch.no_grad():
            jf = jacobian_tm(system, "f", lo, hi, ru)  # [B, n, n], g per unit (z - zc)
            jh = jacobian_tm(system, "h", lo, hi, ru)  # [B, p, n]
            hc = system.h(zc[:, :n])
        self.dtype = dtype
        self.zc, self.r = zc.to(dtype), r.to(dtype)
        P64 = torch.as_tensor(P, dtype=torch.float64)
        self.P = P64.to(dtype)
        d = n + p
        # r = y - h(xhat) by the mean-value form: centre value, coefficients (-dh/dxhat | I)
        # at the centre, the range of dh/dxhat - its centre value over the box times |xhat -
        # xhat_c| in the remainder (0 for a linear h)
        eye = torch.eye(p, dtype=torch.float64).expand(zc.shape[0], p, p)
        rg = torch.cat([-jh.c, eye], -1) * r[:, None, :]
        spread = (jh.g.abs() * r[:, None, None, :]).sum(-1) + jh.e  # [B, p, n]
        re = (spread @ r[:, :n, None])[..., 0]
        self.rt = STM((zc[:, n:] - hc).to(dtype), rg.to(dtype), re.to(dtype))
        self.hx = STM(jh.c.to(dtype), (jh.g * r[:, None, None, :]).to(dtype), jh.e.to(dtype))
        # the weight-free part: He{P (Jf - K dh/dxhat)} + 2 lam P, as a model over the boxes
        Kt = (torch.zeros(n, p, dtype=torch.float64) if K is None
              else torch.as_tensor(K, dtype=torch.float64))
        A = STM(jf.c - Kt @ jh.c, (jf.g - torch.einsum("ip,bpjd->bijd", Kt, jh.g))
                * r[:, None, None, :], jf.e + Kt.abs() @ jh.e)
        self.base = STM((P64 @ A.c + 2.0 * float(lam) * P64).to(dtype),
                        torch.einsum("ik,bkjd->bijd", P64, A.g).to(dtype),
                        (P64.abs() @ A.e).to(dtype))
        self.d = d

    def model(self, spec: GainSpec) -> STM:
        """The surrogate Taylor model of D over every box [B, n, n], differentiable in the
        spec's weights."""
        arith = SurrogateTaylor(self.zc, self.r, spec.activation)
        m = spec.n + spec.p if spec.structural else spec.n
        out = propagate(spec, arith, None, m)
        gain = compose(spec, arith, out, self.rt, self.hx, with_dy=False, with_k=False,
                       with_K_dx=False)
        M = gain.dk_dx  # [B, n, n], the network's part (K's is in `base`)
        PM = STM(self.P @ M.c, torch.einsum("ik,bkjd->bijd", self.P, M.g),
                 self.P.abs() @ M.e)
        return _add(self.base, PM)

    def terms(self, spec: GainSpec) -> tuple[torch.Tensor, torch.Tensor]:
        """(height, s) per box: `room_terms` at the level -margin."""
        st = self.settings
        return room_terms(self.model(spec), -st.margin, st.floor)

    def value(self, spec: GainSpec) -> torch.Tensor:
        """mean_b [relu(height_b) + relu(s_b - ratio)] as a 0-d tensor (module docstring),
        differentiable in the spec's weights."""
        height, s = self.terms(spec)
        return (torch.relu(height) + torch.relu(s - self.settings.ratio)).mean()


__all__ = ["VerifierSettings", "VerifierPenalty", "SurrogateTaylor", "sample_boxes",
           "room_terms", "activation_bounds"]
