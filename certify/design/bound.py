"""The linear observer designed for the noise-to-error bound, and the sampled bound of a gain.

Observer xhat' = f(xhat) + K (y - C xhat) with y = C x + v (linear h). With e = x - xhat,
e' = A e - K v where A = Jf - K C averages Jf along the segment from xhat to x, which lies in
X (a box, so convex). For V = e^T P e,

    V' + alpha V - mu ||v||^2 = [e; v]^T M(A) [e; v],
    M = [[A^T P + P A + alpha P, -P K], [-K^T P, -mu I]],

so M <= 0 for every A in the hull of the Jacobians gives V' <= -alpha V + mu ||v||^2 and, for
||v|| <= vbar, ||e|| -> at most vbar sqrt(mu / (alpha lam_min(P))). M is affine in Jf, so it
suffices at the vertices of interval enclosures of Jf on sub-boxes covering X (the same
vertices as the LMI observer, `certify.design.metric`). With Y = P K the block is linear in
(P, Y, mu) for fixed alpha: `certify.design.sdp.DissipationSdp` minimises mu at one alpha,
and `design_bound_observer` searches alpha (coarse geometric grid, then golden section in
log alpha around the best grid point) for the smallest mu / alpha (P >= I, and at the
optimum lam_min(P) = 1 up to the solver's tolerance; the bound divides by the actual
lam_min(P)).

In the verifier's convention D(lam) = He{P (Jf + dk/dxhat)} + 2 lam P (He{M} = (M + M^T)/2),
M <= 0 reads D(alpha/4) + P B B^T P / (2 mu) <= 0 with B = dk/dy, so the design also proves
the contraction D(lam) <= -(alpha/2 - 2 lam) P < 0 for every lam < alpha/4: a checkpoint
stores lam slightly below alpha/4 (`LAM_FRACTION`) so that the prover has room.

Nothing here is a proof. The design is re-checked in numpy at every vertex of the full
enclosures (PROVED means that re-check passed with the margin); the checkpoint's contraction
is proved by `certify run`; `sampled_bound` evaluates the same inequality at points only
(for comparing designs, never for a certificate).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.arith.golden import golden_section
from certify.design import sdp
from certify.design.metric import (
    MAX_SDP_VERTICES,
    enclosure_vertices,
    output_matrix,
    sub_boxes,
    varying_entries,
)
from certify.results import Status
from certify.spec.system import System

#: margin of the vertex LMIs (M <= -margin I), and the re-check demands M <= -margin/2 I
DEFAULT_MARGIN = 1e-3
#: the checkpoint's rate lam as a fraction of alpha/4 (room for the prover)
LAM_FRACTION = 0.98
#: the coarse grid of alpha (geometric) and the golden-section iterations after it
GRID_POINTS = 7
GOLDEN_STEPS = 8
DEFAULT_ALPHA_RANGE = (0.05, 40.0)
#: vertices enumerated before the hull pruning (sub-boxes x 2^varying entries): the SDP gets
#: only the hull's vertices, so this can be far above `MAX_SDP_VERTICES`; finer sub-boxes
#: give a smaller enclosure of Jf and so a smaller bound (bench/compare.py reports it)
MAX_DESIGN_POINTS = 2**16


@dataclass
class BoundDesign:
    """A linear observer K (y - C xhat) with metric P proved (at vertices, in numpy) to satisfy
    V' <= -alpha V + mu ||v||^2 on X.

    `per_unit_noise` = sqrt(mu / (alpha lam_min(P))): the ultimate bound on ||e|| is
    vbar * per_unit_noise; `per_component[i]` = sqrt(mu (P^-1)_ii / alpha) per unit noise
    (|e_i| <= sqrt(V (P^-1)_ii)). `tried` records (alpha, mu, per_unit_noise or None) of
    every SDP solved, in order. P, K are None unless status is PROVED."""

    status: Status
    message: str
    alpha: float | None = None
    mu: float | None = None
    P: np.ndarray | None = None
    K: np.ndarray | None = None
    lam_min_P: float | None = None
    per_unit_noise: float | None = None
    per_component: list[float] | None = None
    min_alpha: float | None = None
    vertices: int = 0  # vertices of the full enclosures (the re-check)
    sdp_vertices: int = 0  # hull vertices given to the SDP
    sub_boxes: int = 0
    check_max: float | None = None  # max over all vertices of lam_max(M)
    tried: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    def bound(self, vbar: float) -> float | None:
        """The designed ultimate bound on ||e|| at noise level vbar."""
        return None if self.per_unit_noise is None else float(vbar) * self.per_unit_noise

    def lam(self, fraction: float = LAM_FRACTION) -> float | None:
        """The contraction rate a checkpoint states (fraction * alpha / 4)."""
        return None if self.alpha is None else fraction * self.alpha / 4.0

    def record(self) -> dict[str, Any]:
        """Plain data for checkpoints and benchmarks."""
        return {"status": self.status.value, "message": self.message, "alpha": self.alpha,
                "mu": self.mu, "lam_min_P": self.lam_min_P,
                "per_unit_noise": self.per_unit_noise, "per_component": self.per_component,
                "min_alpha": self.min_alpha, "vertices": self.vertices,
                "sdp_vertices": self.sdp_vertices, "sub_boxes": self.sub_boxes,
                "check_max": self.check_max, "tried": self.tried,
                "P": None if self.P is None else self.P.tolist(),
                "K": None if self.K is None else self.K.tolist(), "seconds": self.seconds}


def joint_matrix(J: np.ndarray, P: np.ndarray, B: np.ndarray, alpha: float, mu: float
                 ) -> np.ndarray:
    """M = [[A^T P + P A + alpha P, -P B], [-B^T P, -mu I]] for A [V, n, n], B [n, p] or
    [V, n, p] -> [V, n + p, n + p] (A is the closed loop Jf - K C for a linear observer)."""
    V, n, _ = J.shape
    B = np.broadcast_to(B, (V,) + B.shape[-2:])
    p = B.shape[-1]
    PA = P[None] @ J
    top = PA + np.swapaxes(PA, -1, -2) + alpha * P[None]
    PB = P[None] @ B
    M = np.empty((V, n + p, n + p))
    M[:, :n, :n] = top
    M[:, :n, n:] = -PB
    M[:, n:, :n] = -np.swapaxes(PB, -1, -2)
    M[:, n:, n:] = -mu * np.eye(p)[None]
    return M


def joint_values(J: np.ndarray, P: np.ndarray, K: np.ndarray, C: np.ndarray, alpha: float,
                 mu: float) -> np.ndarray:
    """lam_max(M) at the Jacobians J [V, n, n] for the linear observer K [n, p] -> [V]."""
    M = joint_matrix(J - (K @ C)[None], P, K, alpha, mu)
    return np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))[:, -1]


def per_unit_noise(mu: float, alpha: float, P: np.ndarray) -> float:
    """sqrt(mu / (alpha lam_min(P))): the ultimate bound on ||e|| per unit of noise."""
    lam_min = float(np.linalg.eigvalsh(0.5 * (P + P.T))[0])
    if not (lam_min > 0 and alpha > 0 and mu >= 0):
        return math.inf
    return math.sqrt(mu / (alpha * lam_min))


def design_vertices(system: System, subdivisions: int | None = None
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """(hull vertices for the SDP [V', n, n], all vertices for the re-check [V, n, n], number
    of sub-boxes) of the Jf enclosures over X: only entries wider than rounding are
    enumerated for the SDP, X is cut into the most sub-boxes per side that keep at most
    MAX_DESIGN_POINTS vertices before the hull pruning, and the SDP gets the hull's vertices
    (those of every sub-box, unpruned, for the re-check). Raises ValueError when the hull
    still has more than MAX_SDP_VERTICES vertices."""
    varies, _ = varying_entries(system)
    per_box = 2 ** int(varies.sum())
    per = subdivisions or max(1, int((MAX_DESIGN_POINTS / per_box) ** (1.0 / system.n)
                                     + 1e-9))
    lo, hi = sub_boxes(system, per, manifold=False)
    verts = enclosure_vertices(system, lo, hi, relevant=varies)
    if len(verts.pruned) > MAX_SDP_VERTICES:
        raise ValueError(f"{len(verts.pruned)} hull vertices of the Jf enclosures: more than "
                         f"{MAX_SDP_VERTICES} LMIs; give fewer subdivisions")
    full = enclosure_vertices(system, lo, hi).all
    return verts.pruned, full, verts.boxes


def design_bound_observer(system: System, *, min_alpha: float | None = None,
                          alpha: float | None = None,
                          alpha_range: tuple[float, float] = DEFAULT_ALPHA_RANGE,
                          margin: float = DEFAULT_MARGIN, gain_max: float | None = None,
                          subdivisions: int | None = None, grid_points: int = GRID_POINTS,
                          golden_steps: int = GOLDEN_STEPS) -> BoundDesign:
    """The linear observer (P, K) and rate alpha with the smallest sqrt(mu / (alpha lam_min(P)))
    such that V' <= -alpha V + mu ||v||^2 at every vertex of the Jf enclosures over X.

    `alpha`: design at this rate only. Otherwise alpha is searched over `alpha_range`, raised
    to `min_alpha` (the floor the user asked for) where that is larger. Linear h only
    (UNKNOWN otherwise). PROVED when the best answer passes the numpy re-check
    lam_max(M) <= -margin/2 at every vertex of the full enclosures; UNKNOWN when no alpha
    gave a solved SDP or the re-check failed (the message says which)."""
    t0 = time.perf_counter()
    if not system.h_is_linear:
        return BoundDesign(Status.UNKNOWN, "the bound design needs a linear output map h "
                           "(constant C = dh/dx)", seconds=time.perf_counter() - t0)
    for name, v in (("alpha", alpha), ("min_alpha", min_alpha)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0; got {v!r}")
    C = output_matrix(system)
    try:
        pruned, full, boxes = design_vertices(system, subdivisions)
    except ValueError as exc:
        return BoundDesign(Status.UNKNOWN, f"bound design: {exc}",
                           seconds=time.perf_counter() - t0)
    tried: list[dict[str, Any]] = []
    answers: dict[float, sdp.SdpResult] = {}
    problem = sdp.DissipationSdp(pruned, C, margin=margin, gain_max=gain_max)

    def value(a: float) -> float:
        res = problem.solve(a)
        answers[a] = res
        b = None
        if res.status is Status.PROVED:
            b = per_unit_noise(res.variables["mu"], a, res.variables["P"])
        tried.append({"alpha": a, "mu": res.value, "per_unit_noise": b,
                      "status": res.status.value})
        return math.inf if b is None or not math.isfinite(b) else b

    if alpha is not None:
        value(float(alpha))
    else:
        lo, hi = (float(v) for v in alpha_range)
        if min_alpha is not None:
            lo = max(lo, float(min_alpha))
            hi = max(hi, 8.0 * lo)
        grid = np.geomspace(lo, hi, max(2, grid_points))
        vals = [value(float(a)) for a in grid]
        i = int(np.argmin(vals))
        if math.isfinite(vals[i]) and golden_steps > 0:
            a = grid[max(0, i - 1)]
            b = grid[min(len(grid) - 1, i + 1)]
            golden_section(lambda s: value(float(math.exp(s))), math.log(a), math.log(b),
                           golden_steps)
    ok = [t for t in tried if t["per_unit_noise"] is not None
          and math.isfinite(t["per_unit_noise"])]
    base = dict(min_alpha=min_alpha, vertices=len(full), sdp_vertices=len(pruned),
                sub_boxes=boxes, tried=tried)
    if not ok:
        last = answers[tried[-1]["alpha"]].message if tried else "no rate tried"
        return BoundDesign(Status.UNKNOWN, f"bound design: no rate gave a solved SDP ({last})",
                           seconds=time.perf_counter() - t0, **base)
    best = min(ok, key=lambda t: t["per_unit_noise"])
    res = answers[best["alpha"]]
    a = float(best["alpha"])
    P, K, mu = res.variables["P"], res.variables["K"], float(res.variables["mu"])
    top = float(joint_values(full, P, K, C, a, mu).max())
    lam_min = float(np.linalg.eigvalsh(P)[0])
    b = per_unit_noise(mu, a, P)
    Pinv = np.linalg.inv(P)
    comp = [math.sqrt(mu * float(Pinv[i, i]) / a) for i in range(system.n)]
    out = BoundDesign(Status.PROVED, "", alpha=a, mu=mu, P=P, K=K, lam_min_P=lam_min,
                      per_unit_noise=b, per_component=comp, check_max=top,
                      seconds=time.perf_counter() - t0, **base)
    if not (top <= -0.5 * margin and lam_min > 0):
        out.status = Status.UNKNOWN
        out.message = (f"the bound design failed the re-check (max vertex value {top:.3g} > "
                       f"{-0.5 * margin:g})")
        return out
    out.message = (f"linear observer designed for the bound: alpha = {a:.4g} (lam = alpha/4 = "
                   f"{a / 4:.4g}), mu = {mu:.4g}, lam_min(P) = {lam_min:.4g}, ||e|| -> <= "
                   f"{b:.4g} vbar; V' <= -alpha V + mu ||v||^2 re-checked at all {len(full)} "
                   f"vertices of the Jf enclosures on {boxes} sub-boxes (max lam_max {top:.3g})")
    return out


# ----------------------------------------------------------------------------------------
# the same inequality at sampled points (any gain network; for comparisons only)
# ----------------------------------------------------------------------------------------

def sample_points(system: System, count: int, seed: int = 0
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Seeded uniform points of X x Y with the corners of X x Y added: xhat [N, n], y [N, p]."""
    box = np.concatenate([np.asarray(system.X, float), np.asarray(system.Y, float)], 0)
    lo = torch.as_tensor(box[:, 0], dtype=torch.float64)
    hi = torch.as_tensor(box[:, 1], dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed))
    z = lo + (hi - lo) * torch.rand(count, len(box), generator=gen, dtype=torch.float64)
    d = len(box)
    if d <= 12:
        bits = torch.cartesian_prod(*[torch.tensor([0.0, 1.0], dtype=torch.float64)] * d)
        z = torch.cat([z, lo + (hi - lo) * bits.reshape(-1, d)])
    return z[:, : system.n], z[:, system.n:]


def pointwise_terms(system: System, network: Any, P: np.ndarray, alpha: float,
                    xhat: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(D(alpha/4) = He{P (Jf + dk/dxhat)} + (alpha/2) P [N, n, n], B = dk/dy [N, n, p]) at
    the points; differentiable in the network's parameters."""
    from certify.model.kernels import contraction_matrix, gain_terms

    g = gain_terms(system, network, xhat, y, with_dy=True)
    Jf = system.jac_f(xhat)
    P_t = torch.as_tensor(P, dtype=Jf.dtype)
    return contraction_matrix(Jf, g.dk_dx, P_t, alpha / 4.0), g.dk_dy


def required_mu(D: torch.Tensor, B: torch.Tensor, P: np.ndarray, *, chunk: int = 256
                ) -> float:
    """The smallest mu with D_i + P B_j B_j^T P / (2 mu) <= 0 for every pair (i, j): the joint
    inequality with A and B ranging independently over the sampled values (the mean-value
    argument evaluates them at different points). inf when some D_i is not negative definite.
    D [N, n, n], B [M, n, p]."""
    D = D.detach().to(torch.float64)
    B = B.detach().to(torch.float64)
    S = -0.5 * (D + D.transpose(-1, -2))
    ev = torch.linalg.eigvalsh(S)
    if not bool(torch.isfinite(ev).all()) or float(ev[:, 0].min()) <= 0:
        return math.inf
    P_t = torch.as_tensor(P, dtype=torch.float64)
    G = P_t @ torch.linalg.solve(S, P_t.expand_as(S))  # P S^-1 P [N, n, n]
    G = 0.5 * (G + G.transpose(-1, -2))
    top = 0.0
    for s in range(0, G.shape[0], chunk):
        Q = torch.einsum("jka,ikl,jlb->ijab", B, G[s:s + chunk], B)  # B^T G B [c, M, p, p]
        Q = 0.5 * (Q + Q.transpose(-1, -2))
        lm = torch.linalg.eigvalsh(Q)[..., -1] if Q.shape[-1] > 1 else Q[..., 0, 0]
        top = max(top, float(lm.max()))
    return 0.5 * top


def distinct_gains(B: torch.Tensor, limit: int = 512) -> torch.Tensor:
    """At most `limit` of the values B [N, n, p]: the largest in norm and an even spread."""
    if B.shape[0] <= limit:
        return B
    norms = B.reshape(B.shape[0], -1).norm(dim=1)
    big = torch.argsort(norms, descending=True)[: limit // 2]
    spread = torch.linspace(0, B.shape[0] - 1, limit - big.numel()).long()
    return B[torch.unique(torch.cat([big, spread]))]


def sampled_bound(system: System, network: Any, P: np.ndarray, alpha: float, *,
                  points: int = 4000, seed: int = 0) -> dict[str, float]:
    """The joint inequality at sampled points of X x Y (`required_mu`): {"mu", "per_unit_noise"}
    with per_unit_noise = sqrt(mu / (alpha lam_min(P))). A sample, not a bound: it is a lower
    estimate of what a proof over the box could give for this (P, alpha)."""
    xhat, y = sample_points(system, points, seed)
    with torch.no_grad():
        D, B = pointwise_terms(system, network, P, alpha, xhat, y)
    mu = required_mu(D, distinct_gains(B), P)
    return {"mu": mu, "per_unit_noise": per_unit_noise(mu, alpha, np.asarray(P))
            if math.isfinite(mu) else math.inf}
