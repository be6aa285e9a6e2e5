"""The CEGIS refinement loop: train -> falsify -> prove -> add points -> repeat.

`cegis` trains a gain network for D <= 0 over X x Y at rate lam in metric P. Each round:
Adam on the collocation set with the objective of `training.cegis_objective`
(`CertObjective`: eigenvalue loss with margin, ||dk/dy|| penalty, optional curvature term,
fresh seeded curvature pairs each round, optional box-bound term of `training.verifier` on
fresh seeded boxes each round); then the counterexample search of
`search_round` below (falsifier, then the sound prover with a box budget), whose
counterexamples and unproved-leaf points join the collocation set (any number of states and
outputs). It stops at the first PROVED round (or after `improve_rounds` more) or when the
round/time budget is spent. This module holds the loop, its settings and its record.
A non-finite loss term, weight or gradient stops the loop at once with one line naming the
round, the step and the term (`training.objective.check_finite`); nothing is returned.
Nothing here is trusted for the certificate: `certify run` re-verifies the checkpoint.

Seeded and deterministic as long as the in-loop proofs end on their box budget
(`proof_boxes`), not on the safety time cap `proof_seconds`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from certify.checks.mpdi import falsify_mpdi
from certify.model.kernels import mpdi_lam_max
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import ProofOutcome, prove_mpdi
from certify.results import Status
from certify.search.threads import torch_threads
from certify.settings import VerifySettings
from certify.spec.system import System
from training.cegis_objective import CertObjective
from training.collocation import collocation_points
from training.curvature import CurvaturePenalty, CurvatureSettings
from training.objective import check_finite
from training.optim import Adam
from training.verifier import VerifierPenalty, VerifierSettings

Log = Callable[[str], None]


# ----- settings and results ---------------------------------------------------------------


@dataclass(frozen=True)
class CegisSettings:
    """How the counterexample-guided loop trains and checks (defaults: the certified preset)."""

    margin: float = 0.2  # train lam_max(D) <= -margin on the collocation points
    mpdi_weight: float = 10.0  # weight of the eigenvalue loss (the constraint, kept dominant)
    rate_slack: float = 0.01  # train D at lam + rate_slack, so the proved rate clears lam
    lip_weight: float = 0.05  # weight of the ||dk/dy|| penalty (0: off)
    lip_power: float = 4.0  # q in (mean ||dk/dy||_F^(2q))^(1/(2q)); 1: RMS, large: sup
    rounds: int = 8
    improve_rounds: int = 0  # rounds kept going after the first proof (lowering L); the
    # result is the last network that was PROVED
    improve_proof_seconds: float = 10.0  # stop improving once a proof takes longer than this
    # (a network that is slow to prove is slow for `certify run` too)
    iters_per_round: int = 400  # Adam steps per round
    lr: float = 1e-3
    grid_points: int = 60_000  # falsification grid over X x Y
    adversarial_starts: int = 32
    adversarial_steps: int = 60
    proof_boxes: int = 300_000  # in-loop prover budget (boxes): the deterministic budget
    proof_seconds: float = 60.0  # in-loop prover safety cap (seconds)
    budget_seconds: float = 240.0  # wall-clock budget of the whole loop
    add_per_round: int = 1024  # most new collocation points per round
    jitter: int = 4  # jittered copies per counterexample
    jitter_scale: float = 0.02  # jitter std, as a fraction of each box width
    seed: int = 0
    curv_weight: float = 0.0  # weight of the Jacobian-variation term C (0: off)
    curv_radius: float = 0.02  # its pair distance, as a fraction of each box side
    curv_pairs: int = 256  # its pairs per round
    verifier_weight: float = 0.0  # weight of the box-bound term V (`training.verifier`; 0: off)
    verifier_margin: float = 0.05  # the level -margin its boxes are held to

    def __post_init__(self) -> None:
        for name in ("margin", "mpdi_weight", "rate_slack", "lip_weight", "lr", "jitter_scale",
                     "curv_weight", "verifier_weight", "verifier_margin",
                     "proof_seconds", "budget_seconds", "improve_proof_seconds"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"cegis: {name} must be a finite number >= 0; got {v!r}")
        if not self.lip_power >= 1:
            raise ValueError(f"cegis: lip_power must be >= 1; got {self.lip_power!r}")
        for name in ("rounds", "iters_per_round", "grid_points", "proof_boxes",
                     "add_per_round", "seed", "jitter", "adversarial_starts", "curv_pairs",
                     "adversarial_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"cegis: {name} must be an int >= 0; got {v!r}")


@dataclass
class RoundRecord:
    """What one round did and found."""

    round: int
    loss: float
    mpdi: float
    lip: float  # the penalty's power mean of ||dk/dy||_F on the collocation points
    lip_max: float  # max ||dk/dy||_F on the collocation points
    max_lam_found: float  # largest float64 lam_max(D) found by the falsifier (at design lam)
    status: str  # PROVED / VIOLATED / UNKNOWN / SKIPPED-NEAR-0 (proof skipped, see below)
    proved_volume: float | None
    points: int  # collocation points trained on this round
    added: int  # points added after this round
    train_seconds: float
    falsify_seconds: float
    proof_seconds: float
    proof_upper: float | None = None
    curv: float = 0.0  # the Jacobian-variation term C at the end of the round's training
    verifier: float = 0.0  # the box-bound term V at the end of the round's training

    def line(self) -> str:
        vol = "-" if self.proved_volume is None else f"{self.proved_volume:.4f}"
        return (f"round {self.round:2d}  loss {self.loss:.4g} (mpdi {self.mpdi:.3g})  ||dk/dy|| "
                f"max {self.lip_max:.4g}  max lam_max(D) found {self.max_lam_found:+.4g}  proof "
                f"{self.status}  proved volume {vol}  points {self.points} (+{self.added})  "
                f"train {self.train_seconds:.1f} s  falsify {self.falsify_seconds:.1f} s  "
                f"prove {self.proof_seconds:.1f} s"
                + (f"  curv {self.curv:.4g}" if self.curv else "")
                + (f"  verifier {self.verifier:.4g}" if self.verifier else ""))


@dataclass
class CegisResult:
    """The trained network (float64), the metric, and the loop's record."""

    network: GainNetwork
    P: np.ndarray
    lam: float
    status: Status  # PROVED iff the last in-loop proof proved D <= 0 over X x Y at lam
    rounds: list[RoundRecord]
    proof: ProofOutcome | None
    xhat: torch.Tensor  # final collocation set
    y: torch.Tensor
    seconds: float
    settings: CegisSettings
    notes: list[str] = field(default_factory=list)

    def record(self) -> dict[str, Any]:
        """Plain data for the checkpoint's training record."""
        return {"cegis": asdict(self.settings), "status": self.status.value,
                "rounds": [asdict(r) for r in self.rounds], "seconds": self.seconds,
                "collocation_points": int(self.xhat.shape[0]), "notes": list(self.notes),
                "proof_upper": None if self.proof is None else self.proof.upper}


# ----- networks -----------------------------------------------------------------------------


def warm_start_network(system: System, hidden: tuple[int, ...], *, K: Any = None,
                       structure: str = "structural", seed: int = 0,
                       activation: str = "tanh") -> GainNetwork:
    """A float64 network whose MLP output is exactly zero (last layer zero) and whose linear
    injection buffer is K: its gain is exactly K (y - h(xhat)) (K = None: zero gain).

    The hidden layers keep a seeded random initialisation so that training can move them.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        net = GainNetwork(system.n, system.p, hidden, structure=structure,
                          activation=activation).double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        if K is not None:
            net.K.copy_(torch.as_tensor(np.asarray(K, dtype=np.float64)))
    return net


def _copy_net(net: GainNetwork, dtype: torch.dtype, K: torch.Tensor | None = None
              ) -> GainNetwork:
    out = GainNetwork.from_architecture(net.architecture())
    out.load_state_dict({k: v.detach().clone() for k, v in net.state_dict().items()})
    out = out.to(dtype)
    if K is not None:
        with torch.no_grad():
            out.K.copy_(K.to(dtype))
    return out


# ----- the loop ---------------------------------------------------------------------------


def cegis(system: System, network: GainNetwork, P: np.ndarray, lam: float, *,
          settings: CegisSettings | None = None, points: int = 4000,
          log: Log | None = None) -> CegisResult:
    """Counterexample-guided training of `network` (its structure, widths and K buffer are
    kept; K is not trained) for D <= 0 over X x Y at rate `lam` in metric `P`.

    Returns the float64 network of the last round with the loop's record. `status` is PROVED
    only when `prove_mpdi` proved the MPDI for that network (a sound proof; `certify run`
    re-checks it anyway).
    """
    with torch_threads(1):
        return _cegis(system, network, P, lam, settings or CegisSettings(), points, log)


def _cegis(system: System, network: GainNetwork, P: np.ndarray, lam: float,
           cs: CegisSettings, points: int, log: Log | None) -> CegisResult:
    t_start = time.perf_counter()
    say = log or (lambda _msg: None)
    P = np.asarray(P, dtype=np.float64)
    P_t = torch.as_tensor(P)
    K64 = network.K.detach().to(torch.float64).clone()
    net32 = _copy_net(network, torch.float32)
    net32.train()
    params: list[torch.Tensor] = []
    for layer in net32.layers:
        params += [layer.weight, layer.bias]
    for prm in params:
        prm.requires_grad_(True)
    opt = Adam(params, lr=cs.lr)
    xhat, y = collocation_points(system, points, cs.seed)
    gen = torch.Generator().manual_seed(cs.seed + 104729)
    box = np.concatenate([system.X, system.Y], 0)
    lo = torch.as_tensor(box[:, 0], dtype=torch.float64)
    hi = torch.as_tensor(box[:, 1], dtype=torch.float64)
    n = system.n
    fsettings = falsifier_settings(cs)
    rounds: list[RoundRecord] = []
    notes: list[str] = []
    best: tuple[GainNetwork, ProofOutcome] | None = None  # the last PROVED network
    last_net, last_proof, last_status = None, None, Status.UNKNOWN
    proved_rounds = 0
    for rnd in range(1, cs.rounds + 1):
        # --- train ---
        t0 = time.perf_counter()
        curvature = None if cs.curv_weight <= 0 else CurvaturePenalty(
            system, CurvatureSettings(weight=cs.curv_weight, radius=cs.curv_radius,
                                      pairs=cs.curv_pairs), cs.seed + 7919 * rnd)
        verifier = None if cs.verifier_weight <= 0 else VerifierPenalty(
            system, VerifierSettings(weight=cs.verifier_weight, margin=cs.verifier_margin),
            cs.seed + 6271 * rnd, lam=lam + cs.rate_slack, P=P_t, K=K64,
            dtype=torch.float32)
        obj = CertObjective(system, net32, xhat, y, lam=lam + cs.rate_slack, P=P_t,
                            margin=cs.margin, lip_weight=cs.lip_weight,
                            lip_power=cs.lip_power, mpdi_weight=cs.mpdi_weight,
                            curvature=curvature, verifier=verifier)
        try:
            for step in range(cs.iters_per_round):
                values = obj.evaluate(grad=True)
                check_finite({**values.as_dict(), "lip": obj.last_lip}, params,
                             f"CEGIS round {rnd}, Adam step {step}")
                opt.step()
            values = obj.evaluate(grad=False)
            check_finite({**values.as_dict(), "lip": obj.last_lip}, params,
                         f"the end of CEGIS round {rnd}", grad=False)
            lip, lip_max = obj.last_lip, obj.last_lip_max
        finally:
            obj.close()
        t_train = time.perf_counter() - t0
        net64 = _copy_net(net32, torch.float64, K64).eval().requires_grad_(False)
        problem = Problem(system, net64, lam, P)
        found = search_round(problem, cs, fsettings, lo, hi, gen,
                             deadline=t_start + cs.budget_seconds)
        status, proof, added = found.status, found.proof, found.added
        if added.shape[0]:
            xhat = torch.cat([xhat, added[:, :n]])
            y = torch.cat([y, added[:, n:]])
        rec = RoundRecord(round=rnd, loss=values.total, mpdi=values.mpdi, lip=lip,
                          lip_max=lip_max, max_lam_found=found.best_value,
                          status=found.label, proved_volume=found.proved_volume,
                          points=int(obj.N), added=int(added.shape[0]), train_seconds=t_train,
                          falsify_seconds=found.falsify_seconds,
                          proof_seconds=found.proof_seconds, proof_upper=found.proof_upper,
                          curv=values.curv, verifier=values.verifier)
        rounds.append(rec)
        say(rec.line())
        last_net, last_proof, last_status = net64, proof, status
        if status is Status.PROVED and proof is not None:
            slow = found.proof_seconds > cs.improve_proof_seconds
            if best is None or not slow:
                best = (net64, proof)
            proved_rounds += 1
            if proved_rounds > cs.improve_rounds:
                break
            if slow:
                keep = "it" if best[0] is net64 else "the previous PROVED network"
                notes.append(f"stopped improving after round {rnd}: its proof took "
                             f"{found.proof_seconds:.1f} s > {cs.improve_proof_seconds:g} s; "
                             f"keeping {keep}")
                say(notes[-1])
                break
        if time.perf_counter() - t_start > cs.budget_seconds:
            notes.append(f"time budget {cs.budget_seconds:g} s spent after round {rnd}")
            say(notes[-1])
            break
    if best is not None:
        net_out, proof_out, status_out = best[0], best[1], Status.PROVED
        if last_status is not Status.PROVED:
            notes.append("the last rounds did not prove; returning the last PROVED network")
    else:
        net_out, proof_out, status_out = last_net, last_proof, last_status
    return CegisResult(network=net_out, P=P, lam=float(lam), status=status_out, rounds=rounds,
                       proof=proof_out, xhat=xhat, y=y, seconds=time.perf_counter() - t_start,
                       settings=cs, notes=notes)


# ----- points from the verifier ---------------------------------------------------------


def jittered(points: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, copies: int,
             scale: float, generator: torch.Generator) -> torch.Tensor:
    """`points` [m, d] and `copies` Gaussian perturbations of each (std scale * width),
    clipped to the box -> [m (1 + copies), d]."""
    if copies <= 0 or points.shape[0] == 0:
        return points
    w = (hi - lo) * scale
    noise = torch.randn(copies, *points.shape, generator=generator, dtype=points.dtype) * w
    extra = (points.unsqueeze(0) + noise).reshape(-1, points.shape[1])
    extra = torch.minimum(torch.maximum(extra, lo), hi)
    return torch.cat([points, extra])


def leaf_boxes(boxes: dict[str, Any], d: int, statuses: tuple[str, ...] = ("unknown",
                                                                          "violated")
               ) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """The prover's leaves with a status in `statuses`: lo, hi [m, k] and the coordinates
    of X x Y (d of them) they span.

    Leaves come in full dimension (k = d) or projected: `boxes["dims"]` names the k
    coordinates when present, else they are the first k (the prover's (0, 1) projection).
    """
    status = boxes.get("status", [])
    keep = [i for i, s in enumerate(status) if s in statuses]
    lo = torch.as_tensor(np.asarray(boxes.get("lo", []), dtype=np.float64).reshape(len(status),
                                                                                  -1)[keep])
    hi = torch.as_tensor(np.asarray(boxes.get("hi", []), dtype=np.float64).reshape(len(status),
                                                                                  -1)[keep])
    k = lo.shape[1] if lo.ndim == 2 else 0
    dims = [int(i) for i in boxes.get("dims", range(k))]
    if len(dims) != k or any(not 0 <= i < d for i in dims) or len(set(dims)) != k:
        raise ValueError(f"prover leaves span {k} coordinates but name {dims} (of {d})")
    return lo, hi, dims


def unproved_points(problem: Problem, outcome: ProofOutcome, lam: float, *, limit: int,
                    per_leaf: int = 16, generator: torch.Generator) -> torch.Tensor:
    """Points of X x Y inside the prover's unproved leaves (status unknown/violated).

    In each leaf (`leaf_boxes`: full dimension, or projected on some coordinates), `per_leaf`
    seeded candidates: the leaf's centre and uniform points of the leaf on its coordinates,
    uniform in X x Y on the others; the one with the largest lam_max(D) is kept. The `limit`
    worst are returned, [m, n + p]. Any n and p.
    """
    s = problem.system
    full = np.concatenate([s.X, s.Y], 0)
    lo_all = torch.as_tensor(full[:, 0], dtype=torch.float64)
    hi_all = torch.as_tensor(full[:, 1], dtype=torch.float64)
    d = full.shape[0]
    lo_l, hi_l, dims = leaf_boxes(outcome.boxes or {}, d)
    m = lo_l.shape[0]
    if m == 0 or limit <= 0:
        return torch.empty(0, d, dtype=torch.float64)
    pts = lo_all + (hi_all - lo_all) * torch.rand(m, per_leaf, d, generator=generator,
                                                  dtype=torch.float64)
    inner = lo_l[:, None] + (hi_l - lo_l)[:, None] * torch.rand(
        m, per_leaf, len(dims), generator=generator, dtype=torch.float64)
    inner[:, 0] = 0.5 * (lo_l + hi_l)  # the leaf's centre is always a candidate
    pts[:, :, dims] = inner
    flat = pts.reshape(-1, d)
    n = problem.n
    with torch.no_grad():
        v = mpdi_lam_max(s, problem.network, problem.P_t, lam, flat[:, :n], flat[:, n:])
    v = torch.nan_to_num(v, nan=math.inf).reshape(m, per_leaf)
    best = torch.argmax(v, dim=1)
    chosen = pts[torch.arange(m), best]
    vals = v[torch.arange(m), best]
    order = torch.argsort(vals, descending=True)[:limit]
    return chosen[order]


# ----- one round's search ---------------------------------------------------------------


def falsifier_settings(cs: CegisSettings) -> VerifySettings:
    """The falsifier's settings for the loop (grid, adversarial starts and steps, seed)."""
    return VerifySettings(grid_points=max(1, cs.grid_points),
                          adversarial_starts=cs.adversarial_starts,
                          adversarial_steps=cs.adversarial_steps, top_counterexamples=64,
                          seed=cs.seed)


@dataclass
class RoundFindings:
    """What the falsifier and the prover found for one round's network."""

    status: Status
    label: str  # PROVED / VIOLATED / UNKNOWN / SKIPPED-NEAR-0 (see `search_round`)
    best_value: float  # largest float64 lam_max(D) the falsifier found (at design lam)
    proof: ProofOutcome | None  # None when a counterexample skipped the proof
    added: torch.Tensor  # new collocation points [k, n + p], k <= add_per_round
    falsify_seconds: float
    proof_seconds: float
    proved_volume: float | None
    proof_upper: float | None


def search_round(problem: Problem, cs: CegisSettings, fsettings: VerifySettings,
                 lo: torch.Tensor, hi: torch.Tensor, generator: torch.Generator,
                 deadline: float) -> RoundFindings:
    """Falsify, then (if nothing is above -margin/2) prove, the MPDI of `problem`.

    `lo`, `hi` [n + p]: the box X x Y (jitter is clipped to it); `deadline`: the
    `time.perf_counter()` at which the loop's time budget ends (caps the proof's seconds).
    """
    lam = problem.lam
    t0 = time.perf_counter()
    search = falsify_mpdi(problem, fsettings)
    t_fals = time.perf_counter() - t0
    d = lo.numel()
    top = torch.as_tensor(np.asarray(search.top_points, dtype=np.float64)).reshape(-1, d)
    topv = torch.as_tensor(np.asarray(search.top_values, dtype=np.float64)).reshape(-1)
    new: list[torch.Tensor] = []
    proof: ProofOutcome | None = None
    t_proof, vol, upper = 0.0, None, None
    status, label = Status.UNKNOWN, "UNKNOWN"
    if search.nonfinite or search.best_value > -0.5 * cs.margin:
        bad = top[topv > -0.5 * cs.margin] if topv.numel() else top
        new.append(jittered(bad, lo, hi, cs.jitter, cs.jitter_scale, generator))
        # a value above 0 violates the MPDI; one in (-margin/2, 0] is not a violation but is
        # too close to 0 for a proof to be worth its time: proof skipped, points added
        status = Status.VIOLATED if search.best_value > 0 else Status.UNKNOWN
        label = "VIOLATED" if search.best_value > 0 else "SKIPPED-NEAR-0"
    else:
        t0 = time.perf_counter()
        remaining = deadline - time.perf_counter()
        proof = prove_mpdi(problem, seconds=max(1.0, min(cs.proof_seconds, remaining)),
                           max_boxes=cs.proof_boxes, seeds=top, estimate_points=0)
        t_proof = time.perf_counter() - t0
        status, vol = proof.status, proof.stats.proved_volume_fraction
        label, upper = proof.status.value, proof.upper
        if proof.status is Status.VIOLATED and proof.counterexample is not None:
            c = proof.counterexample
            pt = torch.tensor([c.xhat + c.y], dtype=torch.float64)
            new.append(jittered(pt, lo, hi, cs.jitter, cs.jitter_scale, generator))
        elif proof.status is Status.UNKNOWN:
            new.append(unproved_points(problem, proof, lam, limit=cs.add_per_round,
                                       generator=generator))
    added = torch.cat(new)[: cs.add_per_round] if new else torch.empty(0, d)
    return RoundFindings(status=status, label=label, best_value=float(search.best_value),
                         proof=proof, added=added, falsify_seconds=t_fals,
                         proof_seconds=t_proof, proved_volume=vol, proof_upper=upper)
