"""The `certified` preset's recipe: LMI metric and warm start, structural gain, CEGIS loop.

1. The metric P and a certified linear gain K come from the joint LMI of METHOD §4
   (`training.baseline.make_lmi_baseline`; memory-bounded vertex enumeration for n = 6),
   solved with a margin (`P_MARGIN`) larger than the baseline's, so that the kernel condition
   (which no gain can change, METHOD §3.5) leaves room for a proved rate above the design lam.
   Round 0: the linear-injection observer K (y - h) (the warm start's gain) is proved
   before Adam moves anything; when it does not prove within `WARM_PROOF_SECONDS`, the LMI
   is solved again with a larger margin (`WARM_MARGINS`): a flat lam_max(D) just below
   -margin can leave the prover no room on large boxes. When no CEGIS round proves, that
   PROVED observer is returned (a certified linear injection, MLP output zero), never an
   unproved network.
2. The gain is structural, k = G(xhat, y) (y - h(xhat)) + K (y - h(xhat)), so eps_bar = 0 by
   construction; the MLP's last layer starts at zero, so the initial gain IS the certified
   LMI gain.
3. `training.cegis.cegis` trains it (eigenvalue loss with margin in P, plus a penalty that
   lowers ||dk/dy||, the Lipschitz constant in y that multiplies the noise in the error
   bound, and the verification-aware term `training.curvature` that keeps dk/dxhat nearly
   constant over small sub-boxes, TrainConfig.curvature_weight), falsifies and proves each
   round, and returns the last PROVED network.

With `--metric` the given P is used instead and there is no warm start (K = 0).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from certify.errors import CertifyError
from certify.model import checkpoint
from certify.model.network import GainNetwork
from certify.prove.mpdi import ProofOutcome
from certify.results import Status
from certify.spec.system import System
from training.cegis import CegisResult, CegisSettings, cegis, warm_start_network
from training.presets import TrainConfig

#: margin of the LMI that gives P and the warm-start K (the baseline uses 0.05)
P_MARGIN = 0.5

#: margins tried in turn (from P_MARGIN up) until the warm start proves in round 0
WARM_MARGINS = (P_MARGIN, 2.0, 4.0, 8.0)

#: prover budget of each round-0 proof of a warm start (seconds; boxes: the CEGIS budget)
WARM_PROOF_SECONDS = 30.0

#: CEGIS settings of the certified preset (TrainConfig carries margin, points, hidden, seed,
#: adam_iters = Adam steps per round, adam_lr)
DEFAULT_CEGIS = CegisSettings(margin=0.2, mpdi_weight=10.0, rate_slack=0.02, lip_weight=0.02,
                              lip_power=8.0, rounds=14, improve_rounds=8,
                              improve_proof_seconds=2.0, iters_per_round=300,
                              grid_points=60_000, proof_boxes=300_000, proof_seconds=40.0,
                              budget_seconds=200.0)


@dataclass
class CertifiedResult:
    """A certified-preset run: the network (float64), P, lam and the loop's record."""

    network: GainNetwork
    P: np.ndarray
    lam: float
    status: Status
    cegis: CegisResult
    start: dict[str, Any] = field(default_factory=dict)  # where P and K came from
    seconds: float = 0.0
    config: TrainConfig | None = None

    def record(self) -> dict[str, Any]:
        """The checkpoint's training record (plain data)."""
        out = {"preset": "certified", "lam": self.lam, "P": self.P.tolist(),
               "status": self.status.value, "start": self.start, "seconds": self.seconds,
               **self.cegis.record()}
        if self.config is not None:
            out["config"] = self.config.to_dict()
            out["config"]["P"] = self.P.tolist()
            out["seed"] = self.config.seed
        return out


def lmi_start(system: System, lam: float, *, margin: float = P_MARGIN, hidden: tuple[int, ...]
              = (8,)) -> tuple[GainNetwork, np.ndarray, dict[str, Any]]:
    """The LMI observer (P, K) at rate lam, trying a few budgets in order: the margin with
    ||PK|| <= 1e3, 1e4, then without a gain bound, then half the margin (twice). Raises
    CertifyError with the last reason when none is PROVED."""
    from training.baseline import make_lmi_baseline

    tries: list[dict[str, Any]] = []
    m = float(margin)
    for _ in range(3):
        tries += [{"margin": m, "gain_max": g} for g in (1e3, 1e4, None)]
        m *= 0.5
    last: Exception | None = None
    for kw in tries:
        try:
            net, P, info = make_lmi_baseline(system, lam, hidden=hidden, **kw)
        except CertifyError as exc:
            last = exc
            continue
        info = {k: v for k, v in info.items() if k != "metric"}
        info.update({"gain_max": kw["gain_max"], "margin": kw["margin"],
                     "K": net.K.tolist()})
        return net, P, info
    raise CertifyError(f"certified preset: no LMI metric for {system.name} at lam = {lam:g} "
                       f"({last})")


def proved_lmi_start(system: System, lam: float, config: TrainConfig, cs: CegisSettings,
                     log: Any = None) -> tuple[GainNetwork, np.ndarray, dict[str, Any],
                                                tuple[GainNetwork, ProofOutcome] | None]:
    """Round 0: the LMI warm start at the first margin of WARM_MARGINS whose linear-injection
    observer `prove_mpdi` proves within WARM_PROOF_SECONDS and the CEGIS box budget.

    The observer proved is the LMI baseline network (direct structure, MLP output exactly
    zero: gain K (y - h)); the structural warm start for CEGIS has the same gain, but the
    prover pays for its (16, 16) MLP on every box (many times slower per box).
    Returns (structural warm start, P, start info, (proved network, its outcome) or None);
    when no margin proves, the first margin's start and None (training goes on from it).
    Raises `training.preflight.Infeasible` when no margin gives an LMI metric."""
    from certify.model.problem import Problem
    from certify.prove.mpdi import prove_mpdi

    first: tuple[GainNetwork, np.ndarray, dict[str, Any]] | None = None
    tried: list[dict[str, Any]] = []
    for margin in WARM_MARGINS:
        try:
            base, P, info = lmi_start(system, lam, margin=margin)
        except CertifyError as exc:
            if first is None and margin == WARM_MARGINS[-1]:
                from training.preflight import no_design

                raise no_design(system, "certified", str(exc)) from None
            continue
        net = warm_start_network(system, config.hidden, K=base.K.detach().clone(),
                                 structure="structural", seed=config.seed,
                                 activation=config.activation)
        first = first or (net, P, info)
        t0 = time.perf_counter()
        out = prove_mpdi(Problem(system, base, lam, P), seconds=WARM_PROOF_SECONDS,
                         max_boxes=cs.proof_boxes, estimate_points=0)
        seconds = time.perf_counter() - t0
        tried.append({"margin": info["margin"], "status": out.status.value,
                      "upper": out.upper, "seconds": round(seconds, 2),
                      "boxes": out.stats.boxes_processed,
                      "proved_volume": out.stats.proved_volume_fraction})
        if log is not None:
            log(f"round 0: LMI observer at margin {info['margin']:g} (||K|| "
                f"{info['gain_norm']:.4g}, cond P {info['kappa_P']:.4g}): {out.status.value} "
                f"in {seconds:.1f} s, {out.stats.boxes_processed} boxes, proved volume "
                f"{out.stats.proved_volume_fraction:.3f}")
        if out.status is Status.PROVED:
            return net, P, {**info, "round0": tried}, (base, out)
    if first is None:  # pragma: no cover - every margin raised, the last re-raised above
        raise CertifyError(f"certified preset: no LMI metric for {system.name}")
    return first[0], first[1], {**first[2], "round0": tried}, None


def cegis_settings(config: TrainConfig, base: CegisSettings = DEFAULT_CEGIS,
                   **overrides: Any) -> CegisSettings:
    """The loop's settings from the preset's config (margin, seed, Adam steps and lr)."""
    values = dataclasses.asdict(base)
    values.update(margin=config.margin, seed=config.seed, iters_per_round=config.adam_iters,
                  lr=config.adam_lr, curv_weight=config.curvature_weight,
                  curv_radius=config.curvature_radius, verifier_weight=config.verifier_weight)
    values.update({k: v for k, v in overrides.items() if v is not None})
    return CegisSettings(**values)


def train_certified(system: System, config: TrainConfig, *, P: np.ndarray | None = None,
                    settings: CegisSettings | None = None, log: Any = None
                    ) -> CertifiedResult:
    """Run the certified recipe for `system` at config.lam (P given: no warm start)."""
    t0 = time.perf_counter()
    lam = float(config.lam if config.lam is not None else system.lam)
    cs = settings or cegis_settings(config)
    proved: tuple[GainNetwork, ProofOutcome] | None = None
    if P is None:
        net, P, start, proved = proved_lmi_start(system, lam, config, cs, log)
        K = net.K.detach().clone()
        start = {"source": "joint LMI (P, K), warm start k0 = K (y - h(xhat))", **start}
    else:
        P = np.asarray(P, dtype=np.float64)
        K = None
        start = {"source": "--metric (no warm start)", "kappa_P": float(np.linalg.cond(P))}
        net = warm_start_network(system, config.hidden, K=K, structure="structural",
                                 seed=config.seed, activation=config.activation)
    if log is not None:
        warm = "none" if K is None else f"K = {np.round(K.numpy().ravel(), 3).tolist()}"
        rows = ", ".join("[" + ", ".join(f"{v:.4g}" for v in row) + "]" for row in P)
        log(f"metric P = [{rows}] (cond {np.linalg.cond(P):.4g}); "
            f"warm start: {warm}")
    res = cegis(system, net, P, lam, settings=cs, points=config.points, log=log)
    if res.status is not Status.PROVED and proved is not None:
        note = ("no CEGIS round proved; returning the observer proved in round 0 (the joint-"
                "LMI linear injection K (y - h), MLP output zero)")
        if log is not None:
            log(note)
        res = dataclasses.replace(res, network=proved[0], status=Status.PROVED,
                                  proof=proved[1], notes=[*res.notes, note])
    return CertifiedResult(network=res.network, P=np.asarray(P), lam=lam, status=res.status,
                           cegis=res, start=start, seconds=time.perf_counter() - t0,
                           config=config)


def save_certified(path: str | Path, system: System, result: CertifiedResult) -> str:
    """Write the checkpoint (network, lam, P and the loop's record); returns its sha256."""
    return checkpoint.save(path, system=system, network=result.network, lam=result.lam,
                           P=result.P, training=result.record())


def run_certified(args: argparse.Namespace, system: System, config: TrainConfig,
                  stdout: TextIO | None = None) -> int:
    """`certify train SYSTEM --preset certified -o FILE`: train, write, say what was proved.

    Exit code 0 when the loop ended PROVED, 1 when it wrote a checkpoint it could not prove
    (the checkpoint is still written, for inspection)."""
    out = stdout or sys.stdout
    quiet = bool(getattr(args, "quiet", False))
    output = Path(args.output)
    if output.exists() and output.is_dir():
        raise CertifyError(f"--output {output} is a directory; give a file name like "
                           f"{system.name}.ckpt")

    def log(msg: str) -> None:
        if not quiet:
            print(msg, file=out, flush=True)

    P = np.asarray(config.P, dtype=np.float64) if getattr(args, "metric", None) else None
    log(f"training {system.name} with preset certified: lam {config.lam:g}, {config.points} "
        f"points, hidden {','.join(map(str, config.hidden))}, structural gain (eps_bar = 0), "
        f"Adam {config.adam_iters} steps per round, seed {config.seed}")
    result = train_certified(system, config, P=P, log=log)
    try:
        sha = save_certified(output, system, result)
    except OSError as exc:
        raise CertifyError(f"cannot write checkpoint {output}: {exc.strerror or exc}") from None
    proof = result.cegis.proof
    what = (f"PROVED D <= 0 over X x Y at lam {result.lam:g} (max lam_max(D) <= "
            f"{proof.upper:.4g})" if result.status is Status.PROVED and proof is not None
            else f"not proved ({result.status.value})")
    log(f"wrote {output} (sha256 {sha[:12]}) in {result.seconds:.1f} s: {what}; "
        f"run `certify run {output}` for the full certificate")
    return 0 if result.status is Status.PROVED else 1
