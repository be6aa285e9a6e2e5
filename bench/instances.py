"""Seeded prover benchmark instances (random-network families), built without tuning for the prover.

An instance is a `Problem` on [-1, 1]^n x Y with y = x1 and

    k(xhat, y) = K (y - xhat1) + N(xhat, y),

N a tanh MLP whose hidden weights are N(0, g^2 / fan_in), biases N(0, 0.3^2), output layer
N(0, 1 / fan_in) scaled by 0.05 (output bias 0). f is Van der Pol (n = 2) or a linear chain
(x_i' = -0.5 x_i + x_{i+1}, x_n' = -x_1 - 0.5 x_n). P and K come from an LMI observer design
(cvxpy + Clarabel, imposed at the vertices of an interval enclosure of Jf over X):
He{P Jf - Y C} + 2 lam0 P <= -I, I <= P <= kappa I with kappa minimal, K = P^-1 Y. The rate
lam is then set so that the sampled maximum of lam_max(D) (grid or random points plus projected
gradient ascent) is -margin. Everything is seeded: `make_instance(spec)` is deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.model.kernels import closed_loop_jacobian, generalized_lam_max, mpdi_lam_max, sym
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.search.falsify import projected_ascent
from certify.spec.system import System


@dataclass(frozen=True)
class InstanceSpec:
    """One benchmark instance: family (architecture, g, system, n), margin and seed."""

    depth: int  # hidden layers
    width: int  # neurons per hidden layer
    g: float  # hidden-weight gain
    n: int  # states (p = 1, y = x1)
    margin: float
    seed: int
    system: str = "auto"  # "vdp" (n = 2 only), "chain", or "auto" (vdp for n = 2)

    @property
    def name(self) -> str:
        sysname = self.system_name
        return (f"{sysname}-n{self.n}-{self.depth}x{self.width}-g{self.g:g}"
                f"-m{self.margin:g}-s{self.seed}")

    @property
    def system_name(self) -> str:
        if self.system != "auto":
            return self.system
        return "vdp" if self.n == 2 else "chain"


def _spec_text(name: str, n: int) -> str:
    states = [f"x{i + 1}" for i in range(n)]
    if name == "vdp":
        if n != 2:
            raise ValueError("vdp has n = 2")
        f = ["x2", "-x1 + x2*(1 - x1**2)"]
    else:
        f = [f"-0.5*x{i + 1} + x{i + 2}" for i in range(n - 1)] + [f"-x1 - 0.5*x{n}"]
    q = '"'
    return "\n".join([
        f'name = "{name}{n}"',
        "states = [" + ", ".join(q + s + q for s in states) + "]",
        'outputs = ["y1"]',
        "f = [" + ", ".join(q + e + q for e in f) + "]",
        'h = ["x1"]',
        "[box]",
        "X = " + str([[-1.0, 1.0]] * n),
        "Y = [[-1.0, 1.0]]",
        "[design]",
        "lam = 0.1",
    ])


def make_system(name: str, n: int) -> System:
    return System.from_text(_spec_text(name, n), origin=f"bench instance {name}{n}")


def _jf_vertices(system: System) -> list[np.ndarray]:
    """Vertices of an interval enclosure of Jf over X (grid of 3^n sub-boxes)."""
    from certify.spec.enclosures import jacobian_f_enclosure

    n = system.n
    X = torch.as_tensor(system.X, dtype=torch.float64)
    axes = [torch.linspace(float(a), float(b), 4, dtype=torch.float64) for a, b in X]
    los = torch.cartesian_prod(*[a[:-1] for a in axes]).reshape(-1, n)
    his = torch.cartesian_prod(*[a[1:] for a in axes]).reshape(-1, n)
    lo, hi = jacobian_f_enclosure(system, los, his)
    verts = []
    for b in range(lo.shape[0]):
        free = [(i, j) for i in range(n) for j in range(n) if float(hi[b, i, j] - lo[b, i, j]) > 0]
        for bits in range(2 ** len(free)):
            M = lo[b].clone()
            for k, (i, j) in enumerate(free):
                if (bits >> k) & 1:
                    M[i, j] = hi[b, i, j]
            verts.append(M.numpy())
    uniq = {tuple(np.round(v, 12).ravel()): v for v in verts}
    return list(uniq.values())


def lmi_design(system: System, lam0: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """P, K with He{P (Jf - K C)} + 2 lam0 P <= -I at the Jf vertices and I <= P <= kappa I,
    kappa minimal (the best-conditioned metric; cvxpy + Clarabel)."""
    import cvxpy as cp

    n = system.n
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    P = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((n, 1))
    kappa = cp.Variable()
    cons = [P >> np.eye(n), P << kappa * np.eye(n)]
    for A in _jf_vertices(system):
        M = P @ A - Y @ C
        cons.append(0.5 * (M + M.T) + 2 * lam0 * P << -np.eye(n))
    cp.Problem(cp.Minimize(kappa + 1e-3 * cp.norm(Y, "fro")), cons).solve(solver=cp.CLARABEL)
    if P.value is None:
        raise RuntimeError(f"LMI design infeasible for {system.name} at lam0={lam0}")
    Pv = 0.5 * (P.value + P.value.T)
    K = np.linalg.solve(Pv, Y.value)
    return Pv, K


def make_network(spec: InstanceSpec, K: np.ndarray) -> GainNetwork:
    gen = torch.Generator().manual_seed(spec.seed)
    net = GainNetwork(spec.n, 1, (spec.width,) * spec.depth, K=torch.as_tensor(K))
    with torch.no_grad():
        for li, layer in enumerate(net.layers):
            fan_in = layer.weight.shape[1]
            if li < len(net.layers) - 1:
                layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen)
                                   * spec.g / math.sqrt(fan_in))
                layer.bias.copy_(0.3 * torch.randn(layer.bias.shape, generator=gen))
            else:
                layer.weight.copy_(0.05 * torch.randn(layer.weight.shape, generator=gen)
                                   / math.sqrt(fan_in))
                layer.bias.zero_()
    return net.double()


def _candidate_points(problem: Problem, seed: int, count: int) -> torch.Tensor:
    """Grid points (d <= 4) or seeded uniform points over X x Y, plus the box corners."""
    s = problem.system
    box = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=torch.float64)
    d = box.shape[0]
    per = int(round(count ** (1.0 / d)))
    if d <= 4:
        axes = [torch.linspace(float(a), float(b), per, dtype=torch.float64) for a, b in box]
        pts = torch.cartesian_prod(*axes).reshape(-1, d)
    else:
        gen = torch.Generator().manual_seed(seed + 7)
        t = torch.rand(count, d, generator=gen, dtype=torch.float64)
        pts = box[:, 0] + t * (box[:, 1] - box[:, 0])
    corners = torch.cartesian_prod(*[b for b in box]).reshape(-1, d)
    return torch.cat([pts, corners])


def _rate_fn(problem: Problem, margin: float):
    """z -> lam_max(He{P J_cl(z)} + margin I, P): the rate at which D(z) = -margin is 2 lam =
    -(this value), so min over z of -value/2 is the tuned lam (one evaluation per point)."""
    s = problem.system
    n = problem.n
    P = problem.P_t
    eye = torch.eye(n, dtype=torch.float64)

    def fn(z: torch.Tensor) -> torch.Tensor:
        J = closed_loop_jacobian(s, problem.network, z[:, :n], z[:, n:])
        return generalized_lam_max(sym(P @ J) + margin * eye, P)

    return fn


def sampled_max(problem: Problem, lam: float, pts: torch.Tensor) -> float:
    """max of lam_max(D) at rate lam over the points pts."""
    n = problem.n
    with torch.no_grad():
        return max(float(mpdi_lam_max(problem.system, problem.network, problem.P_t, lam,
                                      c[:, :n], c[:, n:]).max()) for c in pts.split(65536))


def tune_lam(problem: Problem, margin: float, seed: int, count: int = 40_000,
             starts: int = 32, steps: int = 150) -> tuple[float, float]:
    """lam with sampled max lam_max(D) = -margin.

    Per point, D(z) <= -margin I holds exactly for 2 lam <= -lam_max(He{P J} + margin I, P);
    lam is the minimum of that over grid/random points, refined by projected ascent from the
    `starts` worst ones. Returns (lam, sampled max of lam_max(D) at lam, ~ -margin)."""
    s = problem.system
    box = torch.as_tensor(np.concatenate([s.X, s.Y], 0), dtype=torch.float64)
    pts = _candidate_points(problem, seed, count)
    fn = _rate_fn(problem, margin)
    with torch.no_grad():
        v = torch.cat([fn(c) for c in pts.split(65536)])
    top = torch.topk(v, min(starts, len(v))).indices
    bx, bv = projected_ascent(fn, pts[top], box[:, 0], box[:, 1], steps)
    worst = max(float(v.max()), float(bv.max()))
    lam = -0.5 * worst
    allp = torch.cat([pts[top], bx])
    return lam, sampled_max(problem, lam, allp)


_DESIGNS: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}


def make_instance(spec: InstanceSpec) -> tuple[Problem, dict]:
    """The Problem for `spec` and a dict describing it (lam, sampled max, design)."""
    system = make_system(spec.system_name, spec.n)
    key = (spec.system_name, spec.n)
    if key not in _DESIGNS:
        _DESIGNS[key] = lmi_design(system)
    P, K = _DESIGNS[key]
    net = make_network(spec, K)
    prob = Problem(system, net, 0.0, P)
    lam, smax = tune_lam(prob, spec.margin, spec.seed)
    prob = Problem(system, net, lam, P)
    info = {"instance": spec.name, "lam": lam, "sampled_max": smax,
            "cond_P": float(np.linalg.cond(P)), "d": spec.n + 1}
    return prob, info


__all__ = ["InstanceSpec", "make_instance", "make_system", "lmi_design", "make_network",
           "tune_lam", "sampled_max"]
