"""The `bound` preset with a metric that follows the state (docs/error-bounds.md, section 7).

1. **A linear gain with M(x)** (`design_linear_metric`). `certify.design.metric_poly.
   design_metric` designs a polynomial metric M(x) and a linear gain K for the Riemannian path
   certificate on the tube ||w - h(x)|| <= tau, at grid points; the first stage's constant
   metric P for that gain over X x Y is a degree-0 design (`design_constant_metric`), and the
   checkpoint's rate is LAM_FRACTION alpha1 / 4 of that design. The certificate is what
   `certify.verify` proves; the chain of stages it proves ends on a tube of its own, and
   when that tube differs from the design's by more than `tau_tolerance` the metric is
   designed again at the chain's tube (at most `tau_rounds` designs). Degree 2 first; the
   next degrees at the best tube, kept only where their certificate is better.
2. **A learned gain against the same certificate** (`learn_metric_gain`). The structural
   network k = (G(x, y) + K) (y - h(x)): a gain schedule K(x) (polynomial, with its own metric,
   `design_metric(schedule_degree=...)`) is designed on the tube; G is fitted to K(x) - K on
   the tube, values and x-derivatives, with dG/dy kept small (distillation); then trained
   against the certificate: the contraction loss of the paper's recipe (lam_max(D) with the
   first stage's P and rate over X x Y, with a margin) plus a penalty on lam_max of the
   metric certificate's matrix (`certify.enclose.metric.point_matrix`) at points of the tube
   for the fixed metric, rate and a target noise gain; after each round the prover decides
   the inequality on the tube (`certify.prove.metric.prove_inequality`) and a refuting point
   joins the training points. Returned only when its proved certificate beats the linear
   gain's with M(x).

Nothing here is trusted: the candidates are compared by the bounds `certify.verify` proves,
and `certify run` proves the written checkpoint again.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from certify.arith.text import upper_text
from certify.design.bound import LAM_FRACTION, pointwise_terms
from certify.design.metric_poly import MetricDesign, design_constant_metric, design_metric
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.spec.system import System


@dataclass(frozen=True)
class MetricSettings:
    """The metric designs and the learned gain against their certificate (module doc)."""

    degrees: tuple[int, ...] = (2, 4)
    tau_noise: float = 4.0  # the first design's tube: tau_noise * the report's noise level
    tau_rounds: int = 3
    tau_tolerance: float = 0.05
    # the learned gain
    learn: bool = True
    schedule_degree: int = 2
    hidden: tuple[int, ...] = (16, 16)
    points: int = 4000
    distill_steps: int = 2000
    distill_lr: float = 3e-3
    dy_weight: float = 1.0  # weight of |dG/dy|^2 in the distillation
    rounds: int = 4
    steps: int = 150  # Adam steps per round against the certificate
    lr: float = 1e-3
    mu_ratio: float = 1.02  # target mu: the schedule design's mu times this
    mpdi_margin: float = 0.05  # lam_max(D) <= -margin over X x Y
    metric_margin: float = 0.01  # lam_max of the normalised metric matrix <= -margin
    tube_widen: float = 1.1  # train on a tube this much wider than the chain's last
    prove_boxes: int = 30_000  # the prover's boxes per round (a refuting point or not)
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.degrees or any(d not in (1, 2, 3, 4) for d in self.degrees):
            raise ValueError(f"metric degrees must be in 1..4; got {self.degrees!r}")
        for name in ("tau_rounds", "points", "distill_steps", "rounds", "steps",
                     "prove_boxes", "seed", "schedule_degree"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"metric settings: {name} must be an int >= 0; got {v!r}")
        for name in ("tau_noise", "tau_tolerance", "distill_lr", "lr", "mu_ratio",
                     "tube_widen"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"metric settings: {name} must be a finite number > 0; "
                                 f"got {v!r}")


@dataclass
class MetricCandidate:
    """A gain with a metric M(x), its first stage (P, lam) and what `certify.verify` proved
    (`certified`: `training.proved.certified_bound`'s dict)."""

    kind: str  # "linear" or "learned"
    degree: int
    tau: float  # the tube of the design
    design: MetricDesign
    network: GainNetwork
    P: np.ndarray
    lam: float
    certified: dict[str, Any]
    seconds: float = 0.0

    @property
    def metric(self) -> PolyMetric:
        return self.design.metric

    @property
    def ultimate(self) -> float:
        """The certificate's best proved ultimate bound (inf when none)."""
        v = self.certified.get("ultimate")
        return math.inf if v is None else float(v)

    @property
    def chain_tau(self) -> float | None:
        """The tube of the last stage the chain proved (None: no stage)."""
        return self.certified.get("metric_tau")

    def record(self) -> dict[str, Any]:
        d = self.design
        return {"kind": self.kind, "degree": self.degree, "design_tau": self.tau,
                "design_alpha": d.alpha, "design_mu": d.mu,
                "design_per_unit_noise": d.per_unit_noise,
                "schedule": d.schedule.tolist(), "K": d.K.tolist(),
                "metric": d.metric.to_dict(), "P": self.P.tolist(), "lam": self.lam,
                "certified": self.certified, "seconds": self.seconds}


def _say(log: Any):
    return log or (lambda _m: None)


def _linear_network(system: System, K: np.ndarray, hidden: tuple[int, ...], seed: int,
                    activation: str) -> GainNetwork:
    from training.cegis import warm_start_network

    net = warm_start_network(system, hidden, K=np.asarray(K).reshape(system.n, system.p),
                             structure="structural", seed=seed, activation=activation)
    return net.eval().requires_grad_(False)


def first_stage(system: System, K: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The first stage's constant metric P and the checkpoint's rate lam for the linear gain
    K over X x Y (`design_constant_metric`; lam = LAM_FRACTION alpha / 4): None when none."""
    out = design_constant_metric(system, np.asarray(K).reshape(system.n, system.p))
    if out is None:
        return None
    P, alpha, _ = out
    return P, LAM_FRACTION * alpha / 4.0


def design_linear_metric(system: System, K0: np.ndarray, *, vbar: float, hidden: tuple[int, ...],
                         settings: MetricSettings | None = None, seed: int = 0,
                         activation: str = "tanh", log: Any = None,
                         tried: list[dict[str, Any]] | None = None) -> MetricCandidate | None:
    """The linear gain with M(x) whose certificate proves the smallest bound (module doc,
    item 1), starting from the linear gain K0 [n, p]; None when no design gave a proved
    bound. `tried` collects every candidate's record."""
    from training.proved import certified_bound

    ms = settings or MetricSettings()
    say = _say(log)
    tried = [] if tried is None else tried
    best: MetricCandidate | None = None

    def attempt(degree: int, tau: float, K: np.ndarray) -> MetricCandidate | None:
        t0 = time.perf_counter()
        d = design_metric(system, K, degree=degree, tau=tau)
        if d is None:
            say(f"metric degree {degree} on the tube {tau:.3g}: no design (infeasible)")
            return None
        stage = first_stage(system, d.K[0])
        if stage is None:
            say(f"metric degree {degree} on the tube {tau:.3g}: no constant metric for the "
                "first stage")
            return None
        P, lam = stage
        net = _linear_network(system, d.K[0], hidden, seed, activation)
        cert = certified_bound(system, net, lam, P, metric=d.metric, vbar=vbar)
        cand = MetricCandidate("linear", degree, tau, d, net, P, lam, cert,
                               time.perf_counter() - t0)
        tried.append(cand.record())
        say(f"metric degree {degree} designed on the tube {tau:.3g}: designed bound "
            f"{vbar * d.per_unit_noise:.4g}; proved {_text(cert)}")
        return cand

    K = np.asarray(K0, dtype=np.float64).reshape(system.n, system.p)
    tau = ms.tau_noise * vbar
    for degree in ms.degrees:
        rounds = ms.tau_rounds if best is None else 1
        if best is not None:
            tau = best.chain_tau or tau
        for _ in range(rounds):
            cand = attempt(degree, tau, K if best is None else best.design.K[0])
            if cand is None:
                break
            if cand.ultimate < (best.ultimate if best is not None else math.inf):
                best = cand
            chain = cand.chain_tau
            if chain is None or abs(chain - tau) <= ms.tau_tolerance * tau:
                break
            tau = chain
    return best if best is not None and math.isfinite(best.ultimate) else None


def _text(cert: dict[str, Any]) -> str:
    u = cert.get("ultimate")
    if u is None:
        return f"no bound ({cert.get('verdict')})"
    m = cert.get("metric_ultimate")
    tube = cert.get("metric_tau")
    return (f"{upper_text(u, 4)} ({cert.get('best')}; the metric's stages "
            + (f"{upper_text(m, 4)} on the tube {tube:.3g})" if m is not None
               else "not proved)"))


# ----------------------------------------------------------------------------------------
# the learned gain against the metric certificate
# ----------------------------------------------------------------------------------------

@dataclass
class LearnedMetricAttempt:
    """What the learned gain against the metric certificate reached (module doc, item 2):
    `final` the trained gain with its certificate (None when no schedule was designed),
    `beat` whether its proved bound beats the linear gain's with M(x)."""

    final: MetricCandidate | None
    beat: bool
    message: str
    rounds: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def candidate(self) -> MetricCandidate | None:
        """The learned gain when it is to be returned (proved, and better), else None."""
        return self.final if self.beat else None

    def record(self) -> dict[str, Any]:
        return {"message": self.message, "rounds": self.rounds, "returned": self.beat,
                "certified": None if self.final is None else self.final.certified,
                "seconds": self.seconds}


def candidate_record(cand: MetricCandidate, returned: bool = True) -> dict[str, Any]:
    """The checkpoint's training record of a candidate written on its own (the preset's
    record shape: preset, returned, lam, and the metric design under "metric")."""
    what = f"{cand.kind} with M(x)" + ("" if returned else " (not returned by the preset)")
    return {"preset": "bound", "returned": what, "lam": cand.lam, "report_vbar": None,
            "metric": {"returned": cand.record()}}


def save_candidate(path: Any, system: System, cand: MetricCandidate, *, returned: bool = True,
                   record: dict[str, Any] | None = None) -> str:
    """Write the candidate's checkpoint (network, lam, P, M(x) and `record` or
    `candidate_record`); returns its sha256."""
    from certify.model import checkpoint

    return checkpoint.save(path, system=system, network=cand.network, lam=cand.lam, P=cand.P,
                           metric=cand.metric,
                           training=record or candidate_record(cand, returned))


def schedule_targets(schedule: np.ndarray, coeffs: np.ndarray, x: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """K(x) - K(0)'s constant part removed: (values [N, n, p], x-derivatives [N, n, p, n])
    of sum_j x^(b_j) K_j over the non-constant monomials, at states x [N, n]."""
    from certify.design.metric_poly import monomial_features

    psi, dpsi = monomial_features(np.asarray(schedule), x.detach().numpy())
    keep = np.asarray(schedule).sum(1) > 0
    val = np.einsum("Nj,jab->Nab", psi[:, keep], coeffs[keep])
    der = np.einsum("Nji,jab->Nabi", dpsi[:, keep], coeffs[keep])
    return torch.as_tensor(val), torch.as_tensor(der)


def distill(net: GainNetwork, system: System, z: torch.Tensor, target: torch.Tensor,
            target_dx: torch.Tensor, *, steps: int, lr: float, dy_weight: float) -> float:
    """Fit the structural network's G(x, y) (its MLP output as n x p) to `target` [N, n, p]
    with dG/dx to `target_dx` [N, n, p, n] at the points z = (x, y) [N, n + p], and
    dy_weight |dG/dy|^2 (k's dependence on y beyond the schedule); returns the last loss."""
    n, p = system.n, system.p
    params = [q for layer in net.layers for q in (layer.weight, layer.bias)]
    for q in params:
        q.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    loss_v = math.nan
    for _ in range(steps):
        val, jac = net.forward_with_jacobian(z)
        G = val.reshape(-1, n, p)
        dG = jac.reshape(-1, n, p, n + p)
        loss = (((G - target) ** 2).mean() + ((dG[..., :n] - target_dx) ** 2).mean()
                + dy_weight * (dG[..., n:] ** 2).mean())
        opt.zero_grad()
        loss.backward()
        opt.step()
        loss_v = float(loss.detach())
    return loss_v


def learn_metric_gain(system: System, base: MetricCandidate, *, vbar: float,
                      settings: MetricSettings | None = None, activation: str = "tanh",
                      log: Any = None) -> LearnedMetricAttempt:
    """The learned gain against the metric certificate of `base` (a proved linear gain with
    M(x)), module doc item 2; its `candidate` is set only when its proved bound beats
    base's by more than `training.proved.BEAT_TOLERANCE`."""
    from certify.enclose.metric import metric_congruence, point_matrix
    from certify.prove import metric as pm
    from certify.results import Status
    from training.collocation import collocation_points
    from training.proved import BEAT_TOLERANCE, certified_bound

    t0 = time.perf_counter()
    ms = settings or MetricSettings()
    say = _say(log)
    n, p = system.n, system.p
    tau = base.chain_tau or base.tau
    wide = ms.tube_widen * tau
    sched = design_metric(system, base.design.K[0], degree=base.degree, tau=tau,
                          schedule_degree=ms.schedule_degree)
    if sched is None:
        return LearnedMetricAttempt(None, False, "no gain schedule was designed on the tube",
                                    seconds=time.perf_counter() - t0)
    say(f"gain schedule of degree {ms.schedule_degree} with a metric of degree {base.degree} "
        f"on the tube {tau:.3g}: designed bound {vbar * sched.per_unit_noise:.4g} (the linear "
        f"gain's {vbar * base.design.per_unit_noise:.4g})")
    K = sched.K[0]
    stage = first_stage(system, K)
    if stage is None:
        return LearnedMetricAttempt(None, False, "no constant metric for the first stage of "
                                    "the schedule's constant gain",
                                    seconds=time.perf_counter() - t0)
    P, lam = stage
    metric, alpha = sched.metric, float(sched.alpha)
    mu_t = ms.mu_ratio * float(sched.mu)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(ms.seed)
        net = GainNetwork(n, p, ms.hidden, structure="structural",
                          K=torch.as_tensor(K.reshape(n, p)), activation=activation).double()
    with torch.no_grad():
        net.layers[-1].weight.mul_(0.01)
        net.layers[-1].bias.zero_()
    domain = pm.domain_for(system, wide)
    z = pm.sample_domain(system, domain, ms.points, ms.seed + 1)
    target, target_dx = schedule_targets(sched.schedule, sched.K, z[:, :n])
    loss = distill(net, system, z, target, target_dx, steps=ms.distill_steps, lr=ms.distill_lr,
                   dy_weight=ms.dy_weight)
    say(f"distilled G(x, y) to the schedule on the tube {wide:.3g}: loss {loss:.3g}")
    xhat, y = collocation_points(system, ms.points, ms.seed + 2)
    T = metric_congruence(metric, np.zeros(n + p), mu_t, p)
    params = [q for layer in net.layers for q in (layer.weight, layer.bias)]
    opt = torch.optim.Adam(params, lr=ms.lr)
    prove_domain = pm.domain_for(system, tau)
    rounds: list[dict[str, Any]] = []
    gen = torch.Generator().manual_seed(ms.seed + 3)

    def losses(xh, yy, zz):
        D, _ = pointwise_terms(system, net, P, 4.0 * lam, xh, yy)
        lD = torch.linalg.eigvalsh(D)[:, -1]
        N = T @ point_matrix(system, net, metric, alpha, mu_t, zz) @ T.T
        lN = torch.linalg.eigvalsh(0.5 * (N + N.transpose(1, 2)))[:, -1]
        return lD, lN

    for rnd in range(1, ms.rounds + 1):
        for _ in range(ms.steps):
            lD, lN = losses(xhat, y, z)
            loss = (torch.relu(lD + ms.mpdi_margin).mean()
                    + torch.relu(lN + ms.metric_margin).mean())
            opt.zero_grad()
            loss.backward()
            opt.step()
        frozen = _frozen(net)
        with torch.no_grad():
            out = pm.prove_inequality(system, frozen, metric, alpha, mu_t, prove_domain,
                                      max_boxes=ms.prove_boxes)
            zs = pm.sample_domain(system, domain, 2 * ms.points, ms.seed + 100 + rnd)
            xs, ys = collocation_points(system, 2 * ms.points, ms.seed + 200 + rnd)
            lD, lN = losses(xs, ys, zs)
        add = max(1, ms.points // 16)
        z = torch.cat([z, zs[torch.argsort(lN, descending=True)[:add]]])
        worst = torch.argsort(lD, descending=True)[:add]
        xhat, y = torch.cat([xhat, xs[worst]]), torch.cat([y, ys[worst]])
        if out.status == Status.VIOLATED and out.point is not None:
            jitter = out.point + 0.01 * tau * torch.randn(add, n + p, generator=gen,
                                                          dtype=torch.float64)
            z = torch.cat([z, out.point.repeat(add, 1), jitter])
        rec = {"round": rnd, "loss": float(loss.detach()), "max_mpdi": float(lD.max()),
               "max_metric": float(lN.max()), "prover": out.status.value,
               "prover_boxes": out.boxes, "points": int(len(z))}
        rounds.append(rec)
        say(f"metric round {rnd}: loss {rec['loss']:.3g}, sampled max lam_max(D) "
            f"{rec['max_mpdi']:.3g}, of the metric matrix {rec['max_metric']:.3g}; the "
            f"inequality at mu {mu_t:.4g} on the tube {tau:.3g}: {out.status.value} "
            f"({out.boxes} boxes)")
    final = _frozen(net)
    cert = certified_bound(system, final, lam, P, metric=metric, vbar=vbar)
    design = MetricDesign(metric=metric, schedule=sched.schedule, K=sched.K, alpha=alpha,
                          mu=mu_t)
    cand = MetricCandidate("learned", base.degree, tau, design, final, P, lam, cert,
                           time.perf_counter() - t0)
    beat = cand.ultimate < base.ultimate * (1.0 - BEAT_TOLERANCE)
    msg = (f"the learned gain with M(x): proved {_text(cert)}; the linear gain with M(x): "
           f"{_text(base.certified)}; "
           + ("returning the learned gain" if beat else "returning the linear gain"))
    return LearnedMetricAttempt(cand, beat, msg, rounds, time.perf_counter() - t0)


def _frozen(net: GainNetwork) -> GainNetwork:
    from training.proved import copy_network

    return copy_network(net).eval().requires_grad_(False)
