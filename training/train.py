"""Train a gain network: `train(system, config) -> TrainResult`.

Builds the network (seeded, or a given warm start) and the collocation points, then runs
Adam and L-BFGS (`training.optim`) on the objective of `training.objective` (forward mode
through `certify.model.gain.propagate`, a hand-written reverse pass, float32), records the loss
history and timings, and returns the trained network in float64 with its loss there.
Every evaluation is checked (`training.objective.check_finite`): a non-finite loss term,
weight or gradient stops the run with one line naming the phase, the iteration and the term
(`TrainingDiverged`: exit 2; a NaN gradient at a finite loss, `NonFiniteGradient`: exit 4),
before any checkpoint is written.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from certify.model.checkpoint import versions
from certify.model.network import GainNetwork
from certify.progress import NullProgress, Progress
from certify.search.threads import torch_threads
from certify.spec.system import System
from training import losses
from training.collocation import collocation_points
from training.curvature import CurvaturePenalty, CurvatureSettings
from training.objective import LossValues, Objective, check_finite
from training.optim import PhaseStats, run_adam, run_lbfgs
from training.presets import TrainConfig, check_for_system, make_config
from training.verifier import VerifierPenalty, VerifierSettings

TERMS = ("total", "mpdi", "bc", "curv", "verifier")  # the loss terms recorded per evaluation


# ----- the training run ----------------------------------------------------------------


@dataclass
class TrainResult:
    """A trained network (float64) with its loss history, timings and settings.

    `history[phase][term]` lists one value per objective evaluation: Adam has one per
    iteration; L-BFGS one per function evaluation, with `history["lbfgs"]["iteration"]` the
    L-BFGS iteration it belongs to (the last evaluation of an iteration is normally its
    accepted point). `final` holds the loss terms of the returned network, in float64.
    """

    network: GainNetwork
    history: dict[str, dict[str, list[float]]]
    timings: dict[str, float]
    config: TrainConfig
    final: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def record(self) -> dict[str, Any]:
        """The training record stored in the checkpoint (plain data and tensors)."""
        hist = {phase: {k: torch.tensor(v, dtype=torch.int64 if k == "iteration"
                                        else torch.float64) for k, v in cols.items()}
                for phase, cols in self.history.items()}
        return {"config": self.config.to_dict(), "seed": self.config.seed, "history": hist,
                "final": dict(self.final), "timings": dict(self.timings),
                "counts": dict(self.counts), "versions": versions(),
                "notes": "history: one entry per objective evaluation; lbfgs.iteration is "
                         "the L-BFGS iteration of each evaluation; final: float64 loss of "
                         "the saved weights on the training points"}


def _new_network(system: System, config: TrainConfig) -> GainNetwork:
    """The initial network, seeded without touching the global RNG state."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        net = GainNetwork(system.n, system.p, config.hidden, structure=config.structure,
                          activation=config.activation)
    return net.to(getattr(torch, config.dtype))


def train(system: System, config: TrainConfig | None = None, *,
          progress: Progress | None = None,
          network: GainNetwork | None = None) -> TrainResult:
    """Train a gain network for `system` with `config` (default: the paper preset).

    Adam (full batch) for `adam_iters` steps, then L-BFGS (strong Wolfe line search,
    `max_iter = lbfgs_iters`). Seeded: the same config gives the same weights on CPU (with the
    same thread count). `network`, if given, is the starting point (e.g. a warm start; its
    structure and widths win over the config's). Raises `SettingsError` for bad settings.
    """
    with torch_threads(1):
        return _train(system, config, progress=progress, network=network)


def _train(system: System, config: TrainConfig | None, *, progress: Progress | None,
           network: GainNetwork | None) -> TrainResult:
    t_start = time.perf_counter()
    config = make_config(system) if config is None else config
    check_for_system(config, system)
    progress = progress or NullProgress()
    lam = float(system.lam if config.lam is None else config.lam)
    P = torch.as_tensor(system.P if config.P is None else config.P, dtype=torch.float64)
    rho = config.rho if config.rho is not None else (1.0,) * system.n
    weights = losses.LossWeights(mu1=config.mu1, mu2=config.mu2, rho=tuple(rho))
    dtype = getattr(torch, config.dtype)
    if network is None:
        net = _new_network(system, config)
    else:
        net = GainNetwork.from_architecture(network.architecture())
        net.load_state_dict(network.state_dict())
        net = net.to(dtype)
    net.train()
    for prm in net.parameters():
        prm.requires_grad_(True)
    xhat, y = collocation_points(system, config.points, config.seed)
    curvature = None
    if config.curvature_weight > 0:
        curvature = CurvaturePenalty(system, CurvatureSettings(
            weight=config.curvature_weight, radius=config.curvature_radius), config.seed,
            dtype)
    verifier = None
    if config.verifier_weight > 0:
        verifier = VerifierPenalty(system, VerifierSettings(weight=config.verifier_weight),
                                   config.seed, lam=lam, P=P,
                                   K=net.K.detach().to(torch.float64), dtype=dtype)
    objective = Objective(system, net, xhat, y, lam=lam, P=P, weights=weights,
                          loss=config.loss, margin=config.margin, curvature=curvature,
                          verifier=verifier)
    history: dict[str, dict[str, list[float]]] = {}
    timings: dict[str, float] = {"setup": time.perf_counter() - t_start}

    def recorder(phase: str) -> Callable[[LossValues, int], None]:
        cols = history.setdefault(phase, {"iteration": [], **{k: [] for k in TERMS}})

        def record(values: LossValues, iteration: int) -> None:
            check_finite(values.as_dict(), objective.params, f"{phase} iteration {iteration}")
            cols["iteration"].append(iteration)
            for key in TERMS:
                cols[key].append(getattr(values, key))
        return record

    stats: dict[str, PhaseStats] = {}
    try:
        _optimise(objective, config, stats, timings, recorder, progress)
        check_finite({}, objective.params, "the end of training", grad=False)
    finally:
        objective.close()
    t0 = time.perf_counter()
    final_net = GainNetwork.from_architecture(net.architecture())
    final_net.load_state_dict({k: v.detach() for k, v in net.state_dict().items()})
    final_net = final_net.double().eval().requires_grad_(False)
    final_curv = None if curvature is None else CurvaturePenalty(
        system, curvature.settings, config.seed, torch.float64)
    final_ver = None if verifier is None else VerifierPenalty(
        system, verifier.settings, config.seed, lam=lam, P=P,
        K=final_net.K.to(torch.float64), dtype=torch.float64)
    final_obj = Objective(system, final_net, xhat, y, lam=lam, P=P, weights=weights,
                          loss=config.loss, margin=config.margin, workers=1,
                          curvature=final_curv, verifier=final_ver)
    final = final_obj.evaluate(grad=False).as_dict()
    check_finite(final, [], "the final float64 evaluation", grad=False)
    timings["final_eval"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    counts = {"adam_iterations": stats["adam"].iterations if "adam" in stats else 0,
              "lbfgs_iterations": stats["lbfgs"].iterations if "lbfgs" in stats else 0,
              "lbfgs_evaluations": stats["lbfgs"].evaluations if "lbfgs" in stats else 0,
              "evaluations": objective.evaluations}
    return TrainResult(network=final_net, history=history, timings=timings, config=config,
                       final=final, counts=counts)


def _optimise(objective: Objective, config: TrainConfig, stats: dict[str, PhaseStats],
              timings: dict[str, float], recorder: Callable[[str], Any],
              progress: Progress) -> None:
    """Adam, then L-BFGS, as the config says; fills `stats` and `timings`."""
    if config.adam_iters > 0:
        t0 = time.perf_counter()
        stats["adam"] = run_adam(objective, objective.params, iters=config.adam_iters,
                                 lr=config.adam_lr, record=recorder("adam"), progress=progress)
        timings["adam"] = time.perf_counter() - t0
    if config.lbfgs_iters > 0:
        t0 = time.perf_counter()
        stats["lbfgs"] = run_lbfgs(objective, objective.params, iters=config.lbfgs_iters,
                                   lr=config.lbfgs_lr, record=recorder("lbfgs"),
                                   progress=progress)
        timings["lbfgs"] = time.perf_counter() - t0
