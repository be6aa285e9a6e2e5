"""The `bound` preset: observers designed for the certified error bound, not for the rate.

1. The linear observer k = K (y - h(xhat)) with constant metric P and the rate alpha that
   minimise the bound vbar sqrt(mu / (alpha lam_min(P))) of the joint inequality
   V' <= -alpha V + mu ||v||^2 (`certify.design.bound.design_bound_observer`: vertex SDP over
   the Jf enclosures on X, alpha searched, or floored by `--min-rate`, or fixed by `--lam`).
   Written as a structural `GainNetwork` whose MLP output is zero (last layer zero) with K in
   its buffer, at lam = LAM_FRACTION * alpha / 4 (the verifier's rate convention), so that
   `certify run` proves its contraction with room.
2. The learned attempt (`learn_bound_gain`, when `adam_iters` > 0): the same network as a
   warm start, trained by a counterexample-guided loop against the same inequality at a
   target mu below the linear design's at sampled points (`LearnSettings.mu_ratio`), with P
   and alpha fixed:
   loss mean relu(lam_max(D(alpha/4) + P B B^T P / (2 mu_target)) + margin) with B = dk/dy at
   the same point and at a shuffled other point (the mean-value argument pairs A and B from
   different points); each round adds the worst points of a fresh sample (each point's D with
   the most dangerous sampled gains, `worst_pair_eigs`). It is returned only when its
   sampled bound (`certify.design.bound.sampled_bound`, all pairs of A and B on a
   common sample) is below the linear design's on the same sample (by more than
   `BEAT_TOLERANCE`), the prover proves its contraction AND its certificate's best error
   bound (`certify.verify`, whatever bounds this version proves) beats the linear design's;
   otherwise the run says so in one line and writes the linear design.

Nothing here is trusted for the certificate: `certify run` re-verifies the checkpoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from certify.arith.text import upper_text
from certify.design.bound import (
    LAM_FRACTION,
    BoundDesign,
    design_bound_observer,
    pointwise_terms,
    sample_points,
    sampled_bound,
)
from certify.errors import CertifyError, SettingsError
from certify.model import checkpoint
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.results import Status
from certify.search.threads import torch_threads
from certify.spec.system import System
from training.bound_metric import (
    MetricCandidate,
    MetricSettings,
    design_linear_metric,
    learn_metric_gain,
)
from training.cegis import warm_start_network
from training.presets import TrainConfig
from training.proved import BEAT_TOLERANCE, REPORT_VBAR, certified_bound, copy_network

#: gains dk/dy each point's D is paired with in the search (the largest ||P dk/dy||)
SEARCH_GAINS = 32

#: prover budget for the contraction of the returned network (seconds, boxes); the proof
#: stops when it is done, the time is a cap for a loaded machine (vdp2's linear design
#: needs about 25k boxes)
PROOF_SECONDS = 180.0
PROOF_BOXES = 400_000


@dataclass(frozen=True)
class LearnSettings:
    """The learned attempt: rounds of Adam on the joint inequality, then a sampled search."""

    rounds: int = 4
    steps: int = 150  # Adam steps per round (TrainConfig.adam_iters)
    lr: float = 1e-3
    mu_ratio: float = 0.9  # mu_target = mu_ratio * the linear design's mu (the smaller of
    # its vertex mu and the mu it needs at the comparison's sample)
    margin: float = 0.01  # relu(lam_max + margin * alpha)
    eval_points: int = 4000  # fresh sample per round (the search) and the final comparison
    add_per_round: int = 256
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("rounds", "steps", "eval_points", "add_per_round", "seed"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"bound preset: {name} must be an int >= 0; got {v!r}")
        for name in ("lr", "mu_ratio", "margin"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"bound preset: {name} must be a finite number > 0; got {v!r}")


@dataclass
class LearnedAttempt:
    """What the learned attempt reached: sampled bounds per unit noise (learned and linear on
    the same sample), per-round records, whether it beat the linear design and was proved."""

    network: GainNetwork | None
    sampled_learned: float
    sampled_linear: float
    mu_target: float
    beat: bool
    proved: bool | None  # None: not tried (it did not beat the linear design)
    message: str
    rounds: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    final: GainNetwork | None = None  # the last round's network (returned or not)
    certified: dict[str, Any] | None = None  # both certificates' bounds, when compared

    def record(self) -> dict[str, Any]:
        return {"sampled_bound_learned_per_unit_noise": _finite(self.sampled_learned),
                "sampled_bound_linear_per_unit_noise": _finite(self.sampled_linear),
                "mu_target": self.mu_target, "beat": self.beat, "proved": self.proved,
                "message": self.message, "rounds": self.rounds, "seconds": self.seconds,
                "certified": self.certified}


@dataclass
class BoundTrainResult:
    """A `bound`-preset run: the returned network (float64), P, lam and what was compared."""

    network: GainNetwork
    P: np.ndarray
    lam: float
    design: BoundDesign
    returned: str  # "linear" or "learned"
    sampled_linear: float  # sampled bound per unit noise of the linear design
    attempt: LearnedAttempt | None
    proof: dict[str, Any]
    seconds: float = 0.0
    config: TrainConfig | None = None
    metric: PolyMetric | None = None  # the metric that follows the state, when returned
    metric_record: dict[str, Any] | None = None  # the metric designs tried and compared

    def record(self) -> dict[str, Any]:
        d = self.design
        out = {"preset": "bound", "returned": self.returned, "lam": self.lam,
               "method": "linear observer K (y - h(xhat)) from the vertex SDP minimising mu / "
                         "(alpha lam_min(P)) subject to V' <= -alpha V + mu ||v||^2 at the "
                         "vertices of interval enclosures of Jf over X; lam = "
                         f"{LAM_FRACTION:g} alpha / 4; MLP output zero",
               "alpha": d.alpha, "mu": d.mu, "lam_min_P": d.lam_min_P,
               "bound_per_unit_noise": d.per_unit_noise,
               "per_component_per_unit_noise": d.per_component,
               "report_vbar": REPORT_VBAR, "designed_bound": d.bound(REPORT_VBAR),
               "sampled_bound_linear": _finite(REPORT_VBAR * self.sampled_linear),
               "K": None if d.K is None else d.K.tolist(), "design": d.record(),
               "learned": None if self.attempt is None else self.attempt.record(),
               "metric": self.metric_record, "proof": self.proof, "seconds": self.seconds}
        if self.config is not None:
            out["config"] = self.config.to_dict()
            out["config"]["P"] = self.P.tolist()
            out["config"]["lam"] = self.lam
            out["seed"] = self.config.seed
        return out


def _fmt(v: float | None) -> str:
    return "none" if v is None else f"{v:.4g}"


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def linear_network(system: System, design: BoundDesign, config: TrainConfig) -> GainNetwork:
    """The design's gain K (y - h(xhat)) as a float64 structural network, MLP output zero."""
    return warm_start_network(system, config.hidden, K=design.K, structure="structural",
                              seed=config.seed, activation=config.activation)



def joint_eigs(system: System, net: GainNetwork, P: np.ndarray, alpha: float, mu: float,
               xhat: torch.Tensor, y: torch.Tensor, perm: torch.Tensor | None = None
               ) -> torch.Tensor:
    """lam_max(D(alpha/4) + P B B^T P / (2 mu)) at the points [N] (B at the same point), and
    with `perm` [N] also with B taken at the points perm ([2N]); differentiable."""
    D, B = pointwise_terms(system, net, P, alpha, xhat, y)
    PB = torch.as_tensor(P, dtype=D.dtype) @ B
    S = [D + PB @ PB.transpose(-1, -2) / (2.0 * mu)]
    if perm is not None:
        PBp = PB[perm]
        S.append(D + PBp @ PBp.transpose(-1, -2) / (2.0 * mu))
    M = torch.cat(S)
    return torch.linalg.eigvalsh(0.5 * (M + M.transpose(-1, -2)))[:, -1]


def worst_pair_eigs(system: System, net: GainNetwork, P: np.ndarray, alpha: float,
                    mu: float, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """max over B in {dk/dy at the SEARCH_GAINS points with the largest ||P dk/dy||} of
    lam_max(D_i(alpha/4) + P B B^T P / (2 mu)) at each point i -> [N] (no gradients)."""
    with torch.no_grad():
        D, B = pointwise_terms(system, net, P, alpha, xhat, y)
        PB = torch.as_tensor(P, dtype=D.dtype) @ B
        top = torch.argsort(PB.flatten(1).norm(dim=1), descending=True)[:SEARCH_GAINS]
        R = PB[top] @ PB[top].transpose(-1, -2) / (2.0 * mu)  # [m, n, n]
        out = torch.full((D.shape[0],), -math.inf, dtype=D.dtype)
        for Rj in R:
            M = D + Rj
            lm = torch.linalg.eigvalsh(0.5 * (M + M.transpose(-1, -2)))[:, -1]
            out = torch.maximum(out, lm)
    return out


def learn_bound_gain(system: System, design: BoundDesign, start: GainNetwork,
                     config: TrainConfig, settings: LearnSettings | None = None,
                     log: Any = None) -> LearnedAttempt:
    """Train `start` (a copy; float64) against the joint inequality at mu_target and compare
    its sampled bound with the linear design's on a common sample (see the module doc).
    `network` is the round's network with the smallest sampled bound when that beats the
    linear design by more than BEAT_TOLERANCE, else None; `final` is the last round's."""
    t0 = time.perf_counter()
    ls = settings or LearnSettings(steps=config.adam_iters, lr=config.adam_lr,
                                   seed=config.seed)
    say = log or (lambda _m: None)
    assert design.P is not None and design.alpha is not None and design.mu is not None
    P, alpha = design.P, float(design.alpha)
    linear = sampled_bound(system, start, P, alpha, points=ls.eval_points, seed=ls.seed + 1)
    # the target is below what the linear design needs at the samples (the comparison is
    # made there), which can be far below its vertex mu
    mu_t = ls.mu_ratio * min(float(design.mu), float(linear["mu"]))
    margin = ls.margin * alpha
    net = copy_network(start)
    params = [p for layer in net.layers for p in (layer.weight, layer.bias)]
    for prm in params:
        prm.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=ls.lr)
    from training.collocation import collocation_points

    xhat, y = collocation_points(system, config.points, ls.seed)
    gen = torch.Generator().manual_seed(ls.seed + 7919)
    best = (linear["per_unit_noise"], None)
    frozen = None
    rounds: list[dict[str, Any]] = []
    with torch_threads(1):
        for rnd in range(1, ls.rounds + 1):
            loss_v = math.nan
            for _ in range(ls.steps):
                perm = torch.randperm(xhat.shape[0], generator=gen)
                lm = joint_eigs(system, net, P, alpha, mu_t, xhat, y, perm)
                loss = torch.relu(lm + margin).mean()
                if not torch.isfinite(loss):
                    raise CertifyError(f"bound preset: the learned attempt's loss is not "
                                       f"finite in round {rnd}")
                opt.zero_grad()
                loss.backward()
                opt.step()
                loss_v = float(loss.detach())
            # the search: a fresh sample, its worst points join the training set
            sx, sy = sample_points(system, ls.eval_points, ls.seed + 1000 + rnd)
            with torch.no_grad():
                v = worst_pair_eigs(system, net, P, alpha, mu_t, sx, sy)
            v = torch.nan_to_num(v, nan=math.inf)
            worst = torch.argsort(v, descending=True)[: ls.add_per_round]
            xhat, y = torch.cat([xhat, sx[worst]]), torch.cat([y, sy[worst]])
            frozen = copy_network(net).eval().requires_grad_(False)
            sb = sampled_bound(system, frozen, P, alpha, points=ls.eval_points,
                               seed=ls.seed + 1)
            rec = {"round": rnd, "loss": loss_v, "max_joint_eig": float(v.max()),
                   "sampled_bound_per_unit_noise": _finite(sb["per_unit_noise"]),
                   "points": int(xhat.shape[0])}
            rounds.append(rec)
            say(f"learned round {rnd}: loss {loss_v:.4g}, max lam_max of the joint matrix at "
                f"mu_target {float(v.max()):.4g}, sampled bound "
                f"{REPORT_VBAR * sb['per_unit_noise']:.4g} (linear "
                f"{REPORT_VBAR * linear['per_unit_noise']:.4g})")
            if sb["per_unit_noise"] < best[0] * (1.0 - BEAT_TOLERANCE):
                best = (sb["per_unit_noise"], frozen)
    learned = min((r["sampled_bound_per_unit_noise"] or math.inf for r in rounds),
                  default=math.inf)
    beat = best[1] is not None
    if beat:
        msg = (f"the learned gain beat the linear design at sampled points: sampled bound "
               f"{REPORT_VBAR * learned:.4g} vs {REPORT_VBAR * linear['per_unit_noise']:.4g}")
    else:
        msg = (f"the learned gain did not beat the linear design: sampled bound "
               f"{REPORT_VBAR * learned:.4g} vs {REPORT_VBAR * linear['per_unit_noise']:.4g}; "
               f"returning the linear design")
    return LearnedAttempt(network=best[1], sampled_learned=learned,
                          sampled_linear=linear["per_unit_noise"], mu_target=mu_t, beat=beat,
                          proved=None, message=msg, rounds=rounds,
                          seconds=time.perf_counter() - t0, final=frozen)


def prove_contraction(system: System, net: GainNetwork, lam: float, P: np.ndarray
                      ) -> dict[str, Any]:
    """The prover on D(lam) <= 0 over X x Y (PROOF_SECONDS, PROOF_BOXES): plain data."""
    from certify.model.problem import Problem
    from certify.prove.mpdi import prove_mpdi

    t0 = time.perf_counter()
    out = prove_mpdi(Problem(system, net, lam, P), seconds=PROOF_SECONDS,
                     max_boxes=PROOF_BOXES, estimate_points=0)
    return {"status": out.status.value, "upper": out.upper,
            "boxes": out.stats.boxes_processed,
            "proved_volume": out.stats.proved_volume_fraction,
            "seconds": time.perf_counter() - t0}


def min_alpha_for(min_rate: float | None) -> float | None:
    """The alpha floor whose checkpoint rate LAM_FRACTION * alpha / 4 is >= min_rate."""
    return None if min_rate is None else 4.0 * float(min_rate) / LAM_FRACTION


def train_bound(system: System, config: TrainConfig, *, min_rate: float | None = None,
                rate: float | None = None, subdivisions: int | None = None,
                learn: LearnSettings | None = None, prove: bool = True,
                metric: MetricSettings | bool = True, log: Any = None) -> BoundTrainResult:
    """Run the bound recipe (module doc). `min_rate`: the checkpoint's lam is at least this;
    `rate`: design at exactly this lam (alpha = 4 rate / LAM_FRACTION). The learned attempt
    runs when config.adam_iters > 0 (or `learn` is given with steps > 0). `prove=False` skips
    the proofs and certificates (tests of the loop only: a learned gain that beats the linear
    one at samples is then returned unproved). `metric`: the designs with a metric that
    follows the state (`training.bound_metric`): True for the default settings, False for
    none; they run only with a free rate and proofs. Raises `training.preflight.Infeasible`
    when no linear design is found (with the reason when none exists)."""
    t0 = time.perf_counter()
    say = log or (lambda _m: None)
    alpha = None if rate is None else 4.0 * float(rate) / LAM_FRACTION
    design = design_bound_observer(system, min_alpha=min_alpha_for(min_rate), alpha=alpha,
                                   subdivisions=subdivisions)
    if design.status is not Status.PROVED or design.P is None:
        from training.preflight import no_design

        raise no_design(system, "bound", f"no linear observer: {design.message}")
    say(design.message)
    assert design.alpha is not None
    lam = float(design.lam())
    P = np.asarray(design.P)
    lin = linear_network(system, design, config)
    lin.eval().requires_grad_(False)
    sampled_lin = sampled_bound(system, lin, P, design.alpha, seed=config.seed + 1)
    say(f"designed bound {design.bound(REPORT_VBAR):.4g} at noise {REPORT_VBAR:g} (vertex "
        f"SDP; per component "
        + ", ".join(f"{REPORT_VBAR * c:.3g}" for c in design.per_component or [])
        + f"), sampled {REPORT_VBAR * sampled_lin['per_unit_noise']:.4g}; the checkpoint states "
          f"lam = {lam:.4g} ({LAM_FRACTION:g} x alpha/4, a margin for the MPDI proof)")
    attempt = None
    chosen, returned = lin, "linear"
    proof: dict[str, Any] = {}
    steps = learn.steps if learn is not None else config.adam_iters
    ms = metric if isinstance(metric, MetricSettings) else MetricSettings()
    with_metric = prove and rate is None and min_rate is None and metric is not False
    found = (_with_metric(system, design, lin, lam, P, config, ms, steps > 0, say)
             if with_metric else None)
    if found is not None and found[0] is not None:
        cand, record = found
        res = BoundTrainResult(network=cand.network, P=cand.P, lam=cand.lam, design=design,
                               returned=f"{cand.kind} with M(x)",
                               sampled_linear=sampled_lin["per_unit_noise"], attempt=None,
                               proof={"status": cand.certified.get("mpdi"),
                                      "verdict": cand.certified.get("verdict")},
                               seconds=time.perf_counter() - t0, config=config,
                               metric=cand.metric, metric_record=record)
        say(f"returning the {res.returned}: proved ultimate bound {upper_text(cand.ultimate)} "
            f"at noise {REPORT_VBAR:g}")
        return res
    metric_record = None if found is None else found[1]
    if steps > 0 and system.p >= 1:
        attempt = learn_bound_gain(system, design, lin, config, learn, log)
        if attempt.beat and attempt.network is not None:
            proof = prove_contraction(system, attempt.network, lam, P) if prove else {}
            attempt.proved = proof.get("status") == Status.PROVED.value
            if attempt.proved:
                mine = certified_bound(system, attempt.network, lam, P)
                theirs = certified_bound(system, lin, lam, P)
                attempt.certified = {"learned": mine, "linear": theirs}
                a, b = mine["ultimate"], theirs["ultimate"]
                if a is not None and (b is None or a < b * (1.0 - BEAT_TOLERANCE)):
                    chosen, returned = attempt.network, "learned"
                    attempt.message += (f"; its contraction is PROVED at lam {lam:.4g} and its "
                                        f"certified bound {a:.4g} ({mine['best']}) beats the "
                                        f"linear design's {_fmt(b)}")
                else:
                    attempt.message += (f"; but its certified bound {_fmt(a)} does not beat "
                                        f"the linear design's {_fmt(b)}; returning the linear "
                                        "design")
                    proof = {}
            elif not prove:
                chosen, returned = attempt.network, "learned"
            else:
                attempt.message += (f"; but its contraction was not proved ({proof['status']})"
                                    "; returning the linear design")
                proof = {}
        say(attempt.message)
    if prove and not proof:
        proof = prove_contraction(system, chosen, lam, P)
    if proof:
        say(f"contraction D(lam) <= 0 over X x Y at lam {lam:.4g}: {proof['status']} in "
            f"{proof['seconds']:.1f} s ({proof['boxes']} boxes)")
    return BoundTrainResult(network=chosen, P=P, lam=lam, design=design, returned=returned,
                            sampled_linear=sampled_lin["per_unit_noise"], attempt=attempt,
                            proof=proof, seconds=time.perf_counter() - t0, config=config,
                            metric_record=metric_record)


def _with_metric(system: System, design: BoundDesign, lin: GainNetwork, lam: float,
                 P: np.ndarray, config: TrainConfig, ms: MetricSettings, learn: bool, say: Any
                 ) -> tuple[MetricCandidate | None, dict[str, Any]]:
    """The designs with M(x) (`training.bound_metric`): the best proved candidate when it
    beats the constant-metric linear design's certificate (else None), and the record."""
    constant = certified_bound(system, lin, lam, P)
    say(f"the constant-metric linear design's certificate: ultimate bound "
        f"{_fmt(constant['ultimate'])} ({constant['best']})")
    tried: list[dict[str, Any]] = []
    cand = design_linear_metric(system, np.asarray(design.K), vbar=REPORT_VBAR,
                                hidden=config.hidden, settings=ms, seed=config.seed,
                                activation=config.activation, log=say, tried=tried)
    record: dict[str, Any] = {"constant_certified": constant, "tried": tried, "learned": None}
    b = constant["ultimate"]
    if cand is None or not (b is None or cand.ultimate < b * (1.0 - BEAT_TOLERANCE)):
        say("the designs with M(x) did not beat the constant metric's certificate"
            if cand is not None else "no design with M(x) was proved")
        return None, record
    if learn and ms.learn:
        att = learn_metric_gain(system, cand, vbar=REPORT_VBAR, settings=ms,
                                activation=config.activation, log=say)
        record["learned"] = att.record()
        say(att.message)
        if att.candidate is not None:
            cand = att.candidate
    record["returned"] = cand.record()
    return cand, record


def save_bound(path: str | Path, system: System, result: BoundTrainResult) -> str:
    """Write the checkpoint (network, lam, P, the metric M(x) when one was returned, and the
    record); returns its sha256."""
    return checkpoint.save(path, system=system, network=result.network, lam=result.lam,
                           P=result.P, training=result.record(), metric=result.metric)


def run_bound(args: argparse.Namespace, system: System, config: TrainConfig,
              stdout: TextIO | None = None) -> int:
    """`certify train SYSTEM --preset bound -o FILE [--min-rate R | --lam R]`.

    Exit code 0 when the returned network's contraction was PROVED, 1 otherwise (the
    checkpoint is written either way, for inspection)."""
    out = stdout or sys.stdout
    quiet = bool(getattr(args, "quiet", False))
    output = Path(args.output)
    min_rate = getattr(args, "min_rate", None)
    rate = getattr(args, "lam", None)
    if min_rate is not None and rate is not None:
        raise SettingsError("training: give --min-rate (a floor on the rate) or --lam (a fixed "
                            "rate), not both")
    if getattr(args, "metric", None):
        raise SettingsError("training: --metric does not apply to preset bound (it designs P)")

    def log(msg: str) -> None:
        if not quiet:
            print(msg, file=out, flush=True)

    how = (f"rate fixed at lam {rate:g}" if rate is not None else
           f"rate >= {min_rate:g}" if min_rate is not None else
           "rate free; then a metric M(x) designed for it, kept when its certificate is better")
    learn = (f"then a learned attempt ({LearnSettings.rounds} rounds x {config.adam_iters} "
             f"Adam steps, hidden {','.join(map(str, config.hidden))}"
             + ("" if rate is not None or min_rate is not None else
                f"; against M(x): {MetricSettings.rounds} rounds x {MetricSettings.steps} "
                f"steps, hidden {','.join(map(str, MetricSettings.hidden))}") + ")"
             if config.adam_iters > 0 else "no learned attempt (--adam-iters 0)")
    log(f"training {system.name} with preset bound: linear observer designed for the error "
        f"bound ({how}), {learn}, seed {config.seed}")
    result = train_bound(system, dataclasses.replace(config), min_rate=min_rate, rate=rate,
                         log=log)
    try:
        sha = save_bound(output, system, result)
    except OSError as exc:
        raise CertifyError(f"cannot write checkpoint {output}: {exc.strerror or exc}") from None
    d = result.design
    if result.metric is not None:
        cert = (result.metric_record or {}).get("returned", {}).get("certified", {})
        what = (f"metric of degree {result.metric.degree}, proved ultimate bound ||e|| -> <= "
                f"{upper_text(cert['ultimate'])}" if cert.get("ultimate") is not None
                else f"metric of degree {result.metric.degree}")
    else:
        what = f"designed bound ||e|| -> <= {d.bound(REPORT_VBAR):.4g}"
    log(f"wrote {output} (sha256 {sha[:12]}) in {result.seconds:.1f} s: the {result.returned} "
        f"design, lam {result.lam:.4g}, {what} at noise {REPORT_VBAR:g}; run "
        f"`certify run {output}` for the full certificate")
    return 0 if result.proof.get("status") == Status.PROVED.value else 1
