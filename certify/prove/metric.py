"""The Riemannian path certificate with a metric that follows the state, and its two stages.

**The inequality.** With a metric M(x) (`certify.model.metric.PolyMetric`), F(x, w) = f(x) +
k(x, w), J_F = Jf + dk/dx and B = dk/dw, prove at every point (x, w) of a domain D

    [[dM/dt + 2 He{M J_F} + alpha M,  M B ],
     [B^T M,                          -mu I]]  <=  0,     dM/dt = sum_i dM/dx_i F_i(x, w)   (*)

(`certify.enclose.metric` bounds half of it over boxes). **Why it bounds the error.** Let
d(x, xhat) be the Riemannian distance of M among paths in the box Omega (D's states). At a time
t take a path gamma from x to xhat in Omega, of M-length within eps of d and of constant
M-speed (energy E = length^2), with the output path w(s) = y + s v. Let each point flow under
its own system z' = F(z, w(s)): the end s = 0 is the plant (x' = F(x, h(x)): the gain meets
the boundary condition exactly, as a structural or linear gain does; a residual is not
supported here), the end s = 1 is the observer (xhat' = F(xhat, y + v)). For
delta = dz/ds, delta' = J_F delta + B v, so by (*) at every point of the path

    d/dt (delta^T M delta) <= -alpha delta^T M delta + mu |v|^2,

and the flowed path, which joins x(t + h) to xhat(t + h), has energy at most
E + h (-alpha E + mu |v|^2) + o(h). Hence D+ d^2 <= -alpha d^2 + mu |v|^2 (eps -> 0): d^2
decays to mu vbar^2 / alpha, and ||e|| <= d / sqrt(m_min) with M >= m_min I on Omega (a path's
Euclidean length is at most its M-length / sqrt(m_min)). This needs the paths' points in D:

- in the states: a path of M-length <= d from x keeps |z_i - x_i| <= gamma_i d with
  gamma_i^2 M >= e_i e_i^T on Omega (its length along e_i is at most gamma_i times its
  M-length), so the plant must stay in Omega shrunk by gamma_i sqrt(c) per coordinate while
  d^2 <= c;
- in the outputs: w - h(z) = (h(x) - h(z)) + s v, and ||h(x) - h(z)|| <= gamma_h d with
  gamma_h^2 M >= H^T H on Omega (H = dh/dx), so D needs the tube ||w - h(x)|| <= tau with
  tau = gamma_h sqrt(c) + vbar. On the tube, far from the output manifold's off-axis
  values, the gain's value (which enters dM/dt) stays small: that is what makes a
  state-dependent metric pay.

M may depend on the state, never on the measured output (v has no bounded derivative).

**Two stages.** The tube needs d^2 <= c, which a global certificate provides: the constant-
metric dissipation inequality V' <= -alpha1 V + mu1 |v|^2 (V = e^T P e, over X x Y,
`certify.prove.dissipation`) brings V below (1.1)^2 V1_inf after some time T1; if M <= a P on
Omega, then d^2 <= e^T M e <= a V (straight segment) there, so c = a (1.1)^2 V1_inf (at least
V2_inf = mu vbar^2 / alpha, so that d^2 <= c is invariant: D+ d^2 <= 0 on d^2 = c). From T1 on,
d^2 <= e^(-alpha (t - T1)) c + (1 - e^(-alpha (t - T1))) V2_inf.

Everything is proved by the branch and bound (`certify.search.bnb`) in outward-rounded
Taylor-model arithmetic: (*) on D (boxes of Omega x W, those outside the tube closed without a
bound), and on Omega the constants m_min (M >= m_min I), a (M <= a P), gamma_h and gamma_i.
Budgets count boxes. Whatever is not proved leaves the certificate UNKNOWN; no number here is
sampled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from certify.arith.intervals import up
from certify.arith.taylor import TM, tm_add
from certify.enclose.metric import (
    lam_max_upper,
    metric_congruence,
    metric_tm,
    path_metric_tm,
    point_matrix,
    tm_congruent,
    tm_matmul,
    tm_scale,
    tm_transpose,
    tube_box_outside,
    tube_point,
)
from certify.enclose.system_taylor import jacobian_tm
from certify.model.kernels import lam_max
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.results import Status
from certify.search.bnb import Budget, ClosingRule, Output, branch_and_bound
from certify.search.evaluation import BoxEval
from certify.settings import DEFAULTS
from certify.spec.system import System

_F64 = torch.float64
#: the box budget of the stages (`metric_boxes`), and of each constant of the metric
DEFAULT_BOXES = DEFAULTS.metric_boxes
SIDE_BOXES = 20_000
#: the growth of the sampled noise gain the prover is asked to prove, in turn (the samples
#: cover the tube's edges and the faces of X, where (*) is tightest, so the first is small)
GROWTH = (1.005, 1.02, 1.1)
#: the rate proved is the slowest whose sampled bound is within ROOM of the best: near the
#: optimum the bound is flat in alpha, and a slower rate leaves (*) a margin where the
#: samples did not look
ROOM = 1.005
#: the entry level of the second stage: the first stage's ultimate V times this squared
ENTRY = 1.1
#: rates scanned (geometric, up to the fastest sampled rate), golden-section steps after
ALPHA_GRID = 20
ALPHA_REFINE = 12


@dataclass(frozen=True)
class MetricDomain:
    """Where (*) is proved: states in the box `X` [n, 2] (Omega), outputs in the box `W`
    [p, 2], and (when `tau` is a number) only the tube ||w - h(x)||_2 <= tau, which the
    prover covers in tube coordinates u = (x, t), w = h(x) + t (`certify.enclose.metric`):
    the box X x [-tau, tau]^p, its points with ||t|| > tau closed without a bound."""

    X: np.ndarray
    W: np.ndarray
    tau: float | None = None

    @property
    def tube(self) -> bool:
        return self.tau is not None

    def root(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The prover's root box: of z = (x, w), or of u = (x, t) on a tube."""
        if self.tube:
            p = len(self.W)
            T = np.tile([[-self.tau, self.tau]], (p, 1))
            box = torch.as_tensor(np.concatenate([self.X, T], 0), dtype=_F64)
        else:
            box = torch.as_tensor(np.concatenate([self.X, self.W], 0), dtype=_F64)
        return box[:, 0].clone(), box[:, 1].clone()

    def point(self, system: System, v: torch.Tensor) -> torch.Tensor:
        """Points z [B, n + p] of the prover's coordinates v (u on a tube, else z)."""
        return tube_point(system, v) if self.tube else v

    def coordinates(self, system: System, z: torch.Tensor) -> torch.Tensor:
        """The prover's coordinates of points z (u = (x, w - h(x)) on a tube, else z)."""
        if not self.tube:
            return z
        n = system.n
        return torch.cat([z[:, :n], z[:, n:] - system.h(z[:, :n])], 1)

    def holds(self, system: System, v: torch.Tensor) -> torch.Tensor:
        """Which points v (prover's coordinates) are in the domain [B] (bool)."""
        if not self.tube:
            return torch.ones(len(v), dtype=torch.bool)
        return v[:, system.n:].norm(dim=1) <= self.tau


def domain_for(system: System, tau: float | None, X: np.ndarray | None = None) -> MetricDomain:
    """The domain of a tube of half-width `tau` around the output manifold over the states'
    box `X` (default the system's): outputs W = the hull of h over X widened by tau (a sound
    interval enclosure of h), or the system's Y without a tube."""
    from certify.spec.enclosures import h_enclosure

    X = np.asarray(system.X if X is None else X, dtype=np.float64)
    if tau is None:
        return MetricDomain(X, np.asarray(system.Y, dtype=np.float64), None)
    t = torch.as_tensor(X, dtype=_F64)
    hl, hh = h_enclosure(system, t[None, :, 0], t[None, :, 1])
    W = np.stack([hl[0].numpy() - tau, hh[0].numpy() + tau], 1)
    return MetricDomain(X, W, float(tau))


def sample_domain(system: System, domain: MetricDomain, count: int, seed: int
                  ) -> torch.Tensor:
    """Points z = (x, w) [S, n + p] of the domain. Without a tube: x uniform in X (and its
    corners), w uniform in W. On a tube, where (*) is tightest at its edges and at the
    faces of X: a third with t = w - h(x) uniform in the tube, a third on its edge
    ||t|| = tau, a third on the edge with one state on a face of X, and the corners of X
    with t on the edge."""
    n, p = system.n, system.p
    gen = torch.Generator().manual_seed(seed)
    X = torch.as_tensor(domain.X, dtype=_F64)
    x = X[:, 0] + torch.rand(count, n, generator=gen, dtype=_F64) * (X[:, 1] - X[:, 0])
    corners = torch.as_tensor(np.array(np.meshgrid(*domain.X, indexing="ij")).reshape(n, -1).T,
                              dtype=_F64)
    if not domain.tube:
        x = torch.cat([x, corners.repeat(3, 1)])
        W = torch.as_tensor(domain.W, dtype=_F64)
        w = W[:, 0] + torch.rand(len(x), p, generator=gen, dtype=_F64) * (W[:, 1] - W[:, 0])
        return torch.cat([x, w], 1)
    third = count // 3
    face = torch.randint(0, n, (third,), generator=gen)
    side = torch.randint(0, 2, (third,), generator=gen)
    x[-third:][torch.arange(third), face] = X[face, side]
    x = torch.cat([x, corners.repeat(2, 1)])
    d = torch.randn(len(x), p, generator=gen, dtype=_F64)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-300)
    if p == 1:
        d = torch.sign(d)
    radius = torch.ones(len(x), 1, dtype=_F64)
    radius[:count - 2 * third] = torch.rand(count - 2 * third, 1, generator=gen,
                                            dtype=_F64) ** (1.0 / p)
    d[-2 * len(corners):-len(corners)] = 1.0 / math.sqrt(p)
    d[-len(corners):] = -1.0 / math.sqrt(p)
    u = torch.cat([x, domain.tau * radius * d], 1)
    return tube_point(system, u)


@dataclass
class PointTerms:
    """At points: X0 = dM/dt / 2 + He{M J_F} [S, n, n], M [S, n, n], M B [S, n, p]."""

    z: torch.Tensor
    X0: np.ndarray
    M: np.ndarray
    MB: np.ndarray

    @classmethod
    def at(cls, system: System, net: GainNetwork, metric: PolyMetric, z: torch.Tensor
           ) -> PointTerms:
        with torch.no_grad():
            N = point_matrix(system, net, metric, 0.0, 1.0, z)
            M = metric.value(z[:, :system.n])
        n = system.n
        return cls(z, N[:, :n, :n].numpy(), M.numpy(), 2.0 * N[:, :n, n:].numpy())

    def add(self, other: PointTerms) -> PointTerms:
        return PointTerms(torch.cat([self.z, other.z]), np.concatenate([self.X0, other.X0]),
                          np.concatenate([self.M, other.M]), np.concatenate([self.MB, other.MB]))


def needed_mu(terms: PointTerms, alpha: float) -> float:
    """max over the points of lam_max(B^T M (-X)^-1 M B) / 2 with X = X0 + (alpha/2) M: the
    smallest mu for which (*) holds at them (inf where X is not negative definite)."""
    X = terms.X0 + 0.5 * alpha * terms.M
    try:
        L = np.linalg.cholesky(-X)
    except np.linalg.LinAlgError:
        return math.inf
    Z = np.linalg.solve(L, terms.MB)
    G = np.einsum("sij,sik->sjk", Z, Z)
    return float(np.linalg.eigvalsh(G)[:, -1].max()) / 2.0


def fastest_rate(terms: PointTerms) -> float:
    """The largest alpha with X0 + (alpha/2) M negative definite at every point (the pencil's
    eigenvalues; 0 where none is, or M is not positive definite there)."""
    try:
        L = np.linalg.cholesky(terms.M)
    except np.linalg.LinAlgError:
        return 0.0
    Li = np.linalg.inv(L)
    ev = np.linalg.eigvalsh(Li @ terms.X0 @ Li.transpose(0, 2, 1))[:, -1].max()
    return max(0.0, -2.0 * float(ev))


def plan(terms: PointTerms, vbar: float) -> list[dict]:
    """Candidates (alpha, mu) ranked by sqrt(mu / alpha) (the bound per unit noise and unit
    m_min), smallest first, from the points of `terms`."""
    from certify.arith.golden import golden_section

    top = fastest_rate(terms)
    if not top > 0:
        return []
    out: list[dict] = []

    def value(alpha: float) -> float:
        mu = needed_mu(terms, alpha)
        if not (math.isfinite(mu) and mu > 0):
            return math.inf
        out.append(dict(alpha=float(alpha), mu=mu, bound=math.sqrt(mu / alpha) * vbar))
        return out[-1]["bound"]

    grid = top * np.geomspace(0.02, 0.98, ALPHA_GRID)
    vals = [value(float(a)) for a in grid]
    if any(math.isfinite(v) for v in vals):
        k = int(np.argmin(vals))
        lo, hi = math.log(grid[max(k - 1, 0)]), math.log(grid[min(k + 1, len(grid) - 1)])
        golden_section(lambda u: value(math.exp(u)), lo, hi, ALPHA_REFINE)
    return sorted(out, key=lambda c: (c["bound"], c["alpha"]))


def _needed(system: System, net: GainNetwork, metric: PolyMetric, alpha: float, fn: str):
    """At points z [N, d] (differentiable): the mu (*) needs there at rate alpha (NaN where
    X = X0 + (alpha/2) M is not negative definite), or (fn "margin") lam_max(X)."""
    n = system.n

    def value(z: torch.Tensor) -> torch.Tensor:
        N = point_matrix(system, net, metric, alpha, 1.0, z)
        X, MB = N[:, :n, :n], 2.0 * N[:, :n, n:]
        if fn == "margin":
            return torch.linalg.eigvalsh(X)[:, -1]
        L, info = torch.linalg.cholesky_ex(-X)
        ok = info == 0
        L = torch.where(ok[:, None, None], L, torch.eye(n, dtype=_F64).expand_as(L))
        Z = torch.linalg.solve_triangular(L, MB, upper=False)
        mu = torch.linalg.eigvalsh(Z.transpose(1, 2) @ Z)[:, -1] / 2.0
        return torch.where(ok, mu, torch.full_like(mu, float("nan")))

    return value


def sharpen(system: System, net: GainNetwork, metric: PolyMetric, terms: PointTerms,
            domain: MetricDomain, alpha: float, starts: int = 12, steps: int = 40
            ) -> PointTerms:
    """`terms` with the points projected ascent reaches, inside the domain, from the worst
    samples for rate alpha (where (*) needs the most mu, and where X is least negative): a
    plan that misses them is refuted by the prover at the price of a proof. The ascent runs
    in the prover's coordinates, so on a tube it slides along the tube's edge."""
    from certify.search.falsify import projected_ascent

    lo, hi = domain.root()
    feasible = (None if not domain.tube or system.p == 1
                else (lambda v: domain.holds(system, v)))
    found = []
    for fn in ("mu", "margin"):
        f = _needed(system, net, metric, alpha, fn)
        with torch.no_grad():
            v = torch.nan_to_num(f(terms.z), nan=math.inf)
        top = domain.coordinates(system, terms.z[torch.argsort(v, descending=True)[:starts]])
        best, _ = projected_ascent(lambda u, f=f: f(domain.point(system, u)),
                                   top.clamp(lo, hi), lo, hi, steps, feasible=feasible)
        found.append(best)
    return terms.add(PointTerms.at(system, net, metric,
                                   domain.point(system, torch.cat(found))))


def _evaluator(system: System, net: GainNetwork, metric: PolyMetric, alpha: float, mu: float,
               domain: MetricDomain):
    """The branch and bound's box evaluation of (*) on `domain` (module docstring), over
    boxes of the prover's coordinates (`MetricDomain.root`)."""
    lo0, hi0 = domain.root()
    centre0 = domain.point(system, (0.5 * (lo0 + hi0))[None])[0]
    T = metric_congruence(metric, centre0.numpy(), mu, system.p)
    p = system.p

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        if domain.tube:
            outside = (tube_box_outside(system, lo, hi, domain.tau) if p > 1
                       else torch.zeros(len(lo), dtype=torch.bool))
        else:
            outside = torch.zeros(len(lo), dtype=torch.bool)
        upper = torch.full((len(lo),), -math.inf, dtype=_F64)
        score = torch.zeros(len(lo), lo.shape[1], dtype=_F64)
        inside = ~outside
        if bool(inside.any()):
            A = path_metric_tm(system, net, metric, alpha, mu, lo[inside], hi[inside],
                               congruence=T, tube=domain.tube)
            ub, sc = lam_max_upper(A, lo[inside], hi[inside])
            upper[inside] = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, math.nan))
            score[inside] = torch.nan_to_num(sc, nan=0.0, posinf=0.0)
        c = 0.5 * (lo + hi)
        with torch.no_grad():
            val = lam_max(T @ point_matrix(system, net, metric, alpha, mu,
                                           domain.point(system, c)) @ T.T)
        val = torch.where(domain.holds(system, c), val, torch.full_like(val, -math.inf))
        return BoxEval(upper=upper, centre_value=val, score=score)

    return evaluate


@dataclass
class InequalityOutcome:
    """One decision of (*): PROVED, refuted at `point` (a float value > 0 there: not proved,
    the planner's next sample) or UNKNOWN (budget), with the boxes it evaluated."""

    status: Status
    boxes: int
    point: torch.Tensor | None = None
    upper: float = math.inf


def prove_inequality(system: System, net: GainNetwork, metric: PolyMetric, alpha: float,
                     mu: float, domain: MetricDomain, *, max_boxes: int = DEFAULT_BOXES,
                     deadline: float | None = None) -> InequalityOutcome:
    """Decide (*) on `domain` for (alpha, mu) by branch and bound (module docstring). A
    refuting `point` is a point z = (x, w) of the domain."""
    lo, hi = domain.root()
    out = branch_and_bound(lo, hi, _evaluator(system, net, metric, alpha, mu, domain),
                           ClosingRule(threshold=0.0), Budget(max_boxes, deadline),
                           output=Output(task="metric proof", keep_leaves=0))
    if out.complete and out.upper <= 0 and math.isfinite(out.upper):
        return InequalityOutcome(Status.PROVED, out.stats.boxes_processed, upper=out.upper)
    if out.violated and out.best_point is not None:
        return InequalityOutcome(Status.VIOLATED, out.stats.boxes_processed,
                                 point=domain.point(system, out.best_point[None].clone()))
    return InequalityOutcome(Status.UNKNOWN, out.stats.boxes_processed,
                             upper=out.upper if math.isfinite(out.upper) else math.inf)


def _maximum(evaluate, lo: torch.Tensor, hi: torch.Tensor, boxes: int) -> float | None:
    """A sound upper bound of max over [lo, hi] of the evaluated quantity (None: none)."""
    out = branch_and_bound(lo, hi, evaluate, ClosingRule(rel_tol=1e-3, tol=1e-9),
                           Budget(boxes), output=Output(task="metric constant", keep_leaves=0))
    return float(out.upper) if math.isfinite(out.upper) else None


def _state_box(system: System, X: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Omega as boxes of z = (x, w) with the outputs pinned at 0 (the constants depend on x)."""
    lo = torch.zeros(system.n + system.p, dtype=_F64)
    hi = torch.zeros_like(lo)
    lo[:system.n] = torch.as_tensor(X[:, 0])
    hi[:system.n] = torch.as_tensor(X[:, 1])
    return lo, hi


def _matrix_evaluator(system: System, model, centre_value):
    """BoxEval of lam_max of a symmetric model `model(lo, hi)` -> TM [B, m, m]."""
    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        ub, sc = lam_max_upper(model(lo, hi), lo, hi)
        ub = torch.where(torch.isfinite(ub), ub, torch.full_like(ub, math.nan))
        c = 0.5 * (lo + hi)
        with torch.no_grad():
            val = lam_max(centre_value(c[:, :system.n]))
        return BoxEval(upper=ub, centre_value=val, score=torch.nan_to_num(sc, nan=0.0))
    return evaluate


def _neg(t: TM) -> TM:
    return TM(-t.c, -t.g, t.e)


def prove_m_min(system: System, metric: PolyMetric, X: np.ndarray,
                boxes: int = SIDE_BOXES) -> float | None:
    """A sound m_min with M(x) >= m_min I on X (None when none > 0 is proved)."""
    lo, hi = _state_box(system, X)
    ev = _matrix_evaluator(system, lambda a, b: _neg(metric_tm(metric, a, b)),
                           lambda x: -metric.value(x))
    u = _maximum(ev, lo, hi, boxes)
    if u is None or not -u > 0:
        return None
    return -float(up(torch.tensor(u)))  # -u rounded down


def prove_relative_max(system: System, metric: PolyMetric, P: np.ndarray, X: np.ndarray,
                       boxes: int = SIDE_BOXES) -> float | None:
    """A sound a with M(x) <= a P on X: max lam_max(L^-1 M L^-T), P = L L^T (any invertible
    L: a congruence; bounded soundly through `tm_congruent`'s outward rounding, and
    L^-1 L^-T = P^-1 up to rounding, covered by widening a by a relative 1e-9)."""
    lo, hi = _state_box(system, X)
    Li = torch.as_tensor(np.linalg.inv(np.linalg.cholesky(np.asarray(P, dtype=np.float64))))

    def model(a: torch.Tensor, b: torch.Tensor) -> TM:
        zc = 0.5 * (a + b)
        return tm_congruent(Li, metric_tm(metric, a, b), up(torch.maximum(b - zc, zc - a)))

    ev = _matrix_evaluator(system, model, lambda x: Li @ metric.value(x) @ Li.T)
    u = _maximum(ev, lo, hi, boxes)
    # the float inverse: L^-1 M L^-T >= the exact one's up to a relative 1e-12 or so
    return None if u is None else float(up(torch.tensor(u * (1 + 1e-9) + 1e-300)))


def prove_direction_gain(system: System, metric: PolyMetric, X: np.ndarray, gamma: float,
                         direction: np.ndarray | None = None, boxes: int = SIDE_BOXES) -> bool:
    """Whether gamma^2 M(x) >= H^T H on X is proved: H = dh/dx (`direction` None) or the row
    `direction` [n] (a coordinate), i.e. ||H M^(-1/2)|| <= gamma."""
    lo, hi = _state_box(system, X)
    g2 = gamma * gamma
    if direction is not None:
        row = torch.as_tensor(np.asarray(direction, dtype=np.float64)[None])

    def HtH(a: torch.Tensor, b: torch.Tensor) -> TM:
        zc = 0.5 * (a + b)
        r = up(torch.maximum(b - zc, zc - a))
        if direction is None:
            H = jacobian_tm(system, "h", a, b, r)  # [B, p, n]
        else:
            B_ = len(a)
            H = TM(row.expand(B_, 1, system.n).clone(),
                   torch.zeros(B_, 1, system.n, a.shape[1], dtype=_F64),
                   torch.zeros(B_, 1, system.n, dtype=_F64))
        return tm_matmul(tm_transpose(H), H, r), r

    def model(a: torch.Tensor, b: torch.Tensor) -> TM:
        hh, r = HtH(a, b)
        return tm_add(hh, tm_scale(metric_tm(metric, a, b), -g2, r), r)

    def centre(x: torch.Tensor) -> torch.Tensor:
        H = (system.jac_h(x) if direction is None
             else row.expand(len(x), 1, system.n))
        return H.transpose(1, 2) @ H - g2 * metric.value(x)

    out = branch_and_bound(lo, hi, _matrix_evaluator(system, model, centre),
                           ClosingRule(threshold=0.0), Budget(boxes),
                           output=Output(task="metric constant", keep_leaves=0))
    return bool(out.complete and out.upper <= 0)


def sampled_direction_gain(system: System, metric: PolyMetric, X: np.ndarray,
                           direction: np.ndarray | None = None, count: int = 4096,
                           seed: int = 0) -> float:
    """max over sampled x of ||H M(x)^(-1/2)||_2 (a starting guess for the proof)."""
    gen = torch.Generator().manual_seed(seed)
    Xt = torch.as_tensor(X, dtype=_F64)
    x = Xt[:, 0] + torch.rand(count, system.n, generator=gen, dtype=_F64) * (Xt[:, 1] - Xt[:, 0])
    M = metric.value(x)
    H = (system.jac_h(x) if direction is None
         else torch.as_tensor(np.asarray(direction, dtype=np.float64))[None, None].expand(
             count, 1, system.n))
    G = H @ torch.linalg.solve(M, H.transpose(1, 2))
    return float(torch.linalg.eigvalsh(G)[:, -1].clamp_min(0).max().sqrt())


@dataclass
class MetricConstants:
    """The metric's constants on the states' box, each proved: M >= m_min I, M <= a P (P the
    first stage's metric), gamma_h^2 M >= H^T H and gamma_i^2 M >= e_i e_i^T."""

    m_min: float
    a: float
    gamma_h: float
    gamma: list[float]


def prove_constants(system: System, metric: PolyMetric, X: np.ndarray, P1: np.ndarray,
                    boxes: int = SIDE_BOXES) -> MetricConstants | str:
    """The `MetricConstants` on X, or why one was not proved (a sentence)."""
    m_min = prove_m_min(system, metric, X, boxes)
    if m_min is None:
        return "M(x) >= m_min I with m_min > 0 was not proved on the box"
    a = prove_relative_max(system, metric, P1, X, boxes)
    if a is None:
        return "no bound M(x) <= a P of the metric by the first stage's P was proved"
    gammas = []
    for i in range(system.n):
        e = np.eye(system.n)[i]
        g = sampled_direction_gain(system, metric, X, e) * 1.01 + 1e-12
        if not prove_direction_gain(system, metric, X, g, e, boxes):
            return f"the metric's reach along x{i + 1} was not proved"
        gammas.append(g)
    gh = sampled_direction_gain(system, metric, X) * 1.01 + 1e-12
    if not prove_direction_gain(system, metric, X, gh, None, boxes):
        return "the metric's reach along dh/dx was not proved"
    return MetricConstants(m_min=m_min, a=a, gamma_h=gh, gamma=gammas)


@dataclass
class MetricStage:
    """One stage of the chain: (*) proved on the tube of half-width `tau` with (alpha, mu);
    from its start, d^2 <= e^(-alpha t) `entry` + (1 - e^(-alpha t)) `v_inf`, and it hands
    over when d^2 <= ENTRY^2 v_inf (after `duration` seconds), the next stage's entry."""

    tau: float
    alpha: float
    mu: float
    entry: float
    v_inf: float
    boxes: int

    @property
    def duration(self) -> float:
        """Seconds from `entry` to ENTRY^2 v_inf (0 when it starts below)."""
        target = ENTRY ** 2 * self.v_inf
        if self.entry <= target:
            return 0.0
        return math.log((self.entry - self.v_inf) / (target - self.v_inf)) / self.alpha


@dataclass
class MetricOutcome:
    """The chain of stages with the metric (module docstring): its constants, the stages, the
    plant box in which the first stage's paths stay in the proved domain, and the bound
    ||e|| <= sqrt(v_inf / m_min) of the last stage."""

    status: Status
    message: str
    constants: MetricConstants | None = None
    stages: list[MetricStage] = field(default_factory=list)
    plant_box: list[list[float]] | None = None
    boxes: int = 0
    candidates: list[dict] = field(default_factory=list)

    @property
    def ultimate(self) -> float | None:
        """The last stage's sqrt(v_inf / m_min) (None unless proved)."""
        if self.status != Status.PROVED or not self.stages or self.constants is None:
            return None
        return math.sqrt(self.stages[-1].v_inf / self.constants.m_min)


#: at most this many stages with the metric; a next one only when its tube is narrower by
#: more than SHRINK
MAX_STAGES = 3
SHRINK = 0.97


def _pick(cands: list[dict]) -> dict | None:
    """The slowest candidate within ROOM of the best (None: none)."""
    if not cands:
        return None
    return min((c for c in cands if c["bound"] <= ROOM * cands[0]["bound"]),
               key=lambda c: c["alpha"])


def _prove_on_tube(system: System, net: GainNetwork, metric: PolyMetric, vbar: float,
                   tau: float, boxes: int, samples: int, seed: int, tried: list[dict]
                   ) -> tuple[float, float, int] | tuple[None, None, int]:
    """Plan and prove (*) on the tube: (alpha, mu, boxes used), or (None, None, boxes)."""
    domain = domain_for(system, tau)
    terms = PointTerms.at(system, net, metric, sample_domain(system, domain, samples, seed))
    used = 0
    for grow in GROWTH:
        for _ in range(3):
            cand = _pick(plan(terms, vbar))
            if cand is not None:
                terms = sharpen(system, net, metric, terms, domain, cand["alpha"])
                cand = _pick(plan(terms, vbar))
            if cand is None or used >= boxes:
                return None, None, used
            mu = cand["mu"] * grow
            out = prove_inequality(system, net, metric, cand["alpha"], mu, domain,
                                   max_boxes=boxes - used)
            used += out.boxes
            tried.append(dict(tau=tau, alpha=cand["alpha"], mu=mu, status=out.status.value,
                              boxes=out.boxes))
            if out.status == Status.PROVED:
                return cand["alpha"], mu, used
            if out.status != Status.VIOLATED or out.point is None:
                break
            terms = terms.add(PointTerms.at(system, net, metric, out.point))
    return None, None, used


def prove_metric_chain(system: System, net: GainNetwork, metric: PolyMetric, *, vbar: float,
                       P1: np.ndarray, V1_inf: float, max_boxes: int = DEFAULT_BOXES,
                       side_boxes: int = SIDE_BOXES, samples: int = 4096, seed: int = 0
                       ) -> MetricOutcome:
    """The chain of stages with the metric after the first, constant-metric stage whose
    V = e^T P1 e tends to `V1_inf` (module docstring): the constants, then stages on tubes
    each derived from the entry level (tau = gamma_h sqrt(entry) + vbar), while the tube
    narrows."""
    X = np.asarray(system.X, dtype=np.float64)
    consts = prove_constants(system, metric, X, P1, side_boxes)
    if isinstance(consts, str):
        return MetricOutcome(Status.UNKNOWN, consts)
    level = consts.a * ENTRY ** 2 * V1_inf
    stages: list[MetricStage] = []
    tried: list[dict] = []
    used = 0
    while len(stages) < MAX_STAGES:
        tau = (consts.gamma_h * math.sqrt(level) + vbar) * (1 + 1e-9)
        if stages and tau > SHRINK * stages[-1].tau:
            break
        share = (max_boxes - used) // (MAX_STAGES - len(stages))
        alpha, mu, spent = _prove_on_tube(system, net, metric, vbar, tau, share, samples,
                                          seed, tried)
        used += spent
        if alpha is None:
            break
        v_inf = mu * vbar * vbar / alpha
        stages.append(MetricStage(tau=tau, alpha=alpha, mu=mu, entry=max(level, v_inf),
                                  v_inf=v_inf, boxes=spent))
        level = ENTRY ** 2 * v_inf
    if not stages:
        return MetricOutcome(Status.UNKNOWN, "(*) was not proved on the tube the first stage "
                             f"leads to (half-width {tau:.4g}) within its boxes",
                             constants=consts, boxes=used, candidates=tried)
    reach = [g * math.sqrt(stages[0].entry) for g in consts.gamma]
    plant = [[float(X[i, 0] + reach[i]), float(X[i, 1] - reach[i])] for i in range(system.n)]
    if any(lo_ >= hi_ for lo_, hi_ in plant):
        return MetricOutcome(Status.UNKNOWN, "no plant state keeps the paths inside the box "
                             "(the box shrunk by the paths' reach is empty)", constants=consts,
                             stages=stages, boxes=used, candidates=tried)
    last = stages[-1]
    return MetricOutcome(
        Status.PROVED, f"{len(stages)} stage(s) with the metric, the last on the tube "
        f"||w - h(x)|| <= {last.tau:.4g}: d^2 -> {last.v_inf:.6g} (alpha {last.alpha:.6g}, "
        f"mu {last.mu:.6g}), m_min {consts.m_min:.6g}", constants=consts, stages=stages,
        plant_box=plant, boxes=used, candidates=tried)
