"""The counterexample search of one CEGIS round, and the points it adds to training.

For the network a round has just trained: the verifier's falsifier
(`certify.checks.mpdi.falsify_mpdi`: grid + adversarial ascent, float64); if nothing is above
-margin/2, the sound prover (`certify.prover.prove_mpdi`) with a box budget. What they find
becomes new collocation points: the counterexamples (with small seeded jitter) and the
centres of the prover's unproved leaf boxes (full dimension, or lifted to the coordinates a
projection drops by a small search), for any number of states and outputs. The refinement
loop that calls this each round is `training.cegis`. Nothing here is trusted for the
certificate: `certify run` re-verifies the checkpoint.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from certify.checks.mpdi import falsify_mpdi
from certify.kernels import mpdi_lam_max
from certify.problem import Problem
from certify.prover import ProofOutcome, prove_mpdi
from certify.results import Status
from certify.settings import VerifySettings

if TYPE_CHECKING:
    from training.cegis import CegisSettings


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
    label: str  # PROVED / VIOLATED / UNKNOWN / FALSIFIED (counterexample, proof skipped)
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
        status = Status.VIOLATED if search.best_value > 0 else Status.UNKNOWN
        label = "VIOLATED" if search.best_value > 0 else "FALSIFIED"
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
