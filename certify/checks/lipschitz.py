"""Lipschitz constant L of k in y, uniformly in xhat (METHOD §3.4).

Three numbers side by side: LipSDP-Neuron (verified on the rebuilt LMI, a global bound: any
xhat, any y), the naive product of spectral norms (global), and a sampled lower bound
(max ||dk/dy||_2 on a grid of X x Y + gradient ascent). A local bound from the interval
prover (sup ||dk/dy||_2 over X x Y) may be passed in. `value` is the smallest sound bound.

For the structural architecture k = G(xhat, y)(y - h(xhat)) the MLP's Lipschitz constant
does not bound k's: dk/dy = (dG/dy) r + G with r = y - h(xhat) unbounded globally. Then
LipSDP is not applicable (None) and only local bounds (valid while y, y_e stay in Y) exist.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from certify.arith.text import upper_text
from certify.checks.base import Check, Context, setting_quantity
from certify.checks.residual import is_identity
from certify.design import lipsdp, sdp
from certify.model.kernels import gain_terms
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.prove.weighted import Weighting, weighting
from certify.results import LipschitzResult, ProofStats, Status
from certify.search.falsify import maximize_over_box
from certify.search.witness import dk_dy_norm_lower
from certify.settings import VerifySettings

_F64 = torch.float64
_NULL_PROGRESS = NullProgress()
_ROUND_UP = 1.0 + 1e-12  # covers the SVD's relative error in a product of a few norms
#: the local dk/dy proof's relative tolerance (`side_proofs.bound_dk_dy`, passed by
#: `LipschitzCheck`); it runs only when the global bound is more than this above the sampled
#: lower bound
LOCAL_ROOM = 1e-3


def mlp_in_y(net: GainNetwork, n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """The MLP with xhat frozen: [W0y, W1, ..., W_{H-1}] and W_out (numpy float64); for a
    network without hidden layers (N affine) ([], W0y)."""
    Ws = [layer.weight.detach().to(_F64).numpy() for layer in net.layers]
    if len(Ws) == 1:
        return [], Ws[0][:, n:]
    return [Ws[0][:, n:], *Ws[1:-1]], Ws[-1]


def naive_bound(net: GainNetwork, n: int, out: np.ndarray | None = None) -> float:
    """prod ||W_i||_2 over the y-path times Lip(f)^H (tanh: 1) + ||K||_2, rounded up; direct
    only."""
    Ws, Wo = mlp_in_y(net, n)
    K = net.K.detach().to(_F64).numpy()
    if out is not None:
        Wo, K = out @ Wo, out @ K
    prod = float(np.prod([np.linalg.norm(W, 2) for W in [*Ws, Wo]])) * net.act.lipschitz ** len(Ws)
    return (prod + float(np.linalg.norm(K, 2))) * _ROUND_UP ** (len(Ws) + 3)


def structural_local_naive(problem: Problem) -> float | None:
    """A sound bound on sup ||dk/dy||_2 over X x Y for k = G (y - h) + K (y - h).

    dk/dy dy = reshape(dN/dy dy) r + (G + K) dy, so ||dk/dy|| <= L_N ||r||max + ||G||max +
    ||K||, with L_N the naive constant of the MLP in y, ||G||_2 <= ||G||_F <= || |W_out| 1 c +
    |b_out| ||_2 (c = sup |f|: 1 for tanh; None for an unbounded activation) and ||r|| from
    the interval enclosure of h over X.
    """
    from certify.spec.enclosures import h_enclosure

    net, system = problem.network, problem.system
    Ws, Wo = mlp_in_y(net, system.n)
    if not math.isfinite(net.act.value_bound):
        return None
    LN = float(np.prod([np.linalg.norm(W, 2) for W in [*Ws, Wo]])) * net.act.lipschitz ** len(Ws)
    b = net.layers[-1].bias.detach().to(_F64).numpy()
    if Ws:  # |G| <= |W_out| sup|f| + |b_out|
        reach = np.abs(Wo).sum(1) * net.act.value_bound
    else:  # no hidden layer: G = W0 z + b, |G| <= |W0| max|z| + |b| over X x Y
        zmax = np.abs(np.concatenate([system.X, system.Y])).max(1)
        reach = np.abs(net.layers[0].weight.detach().to(_F64).numpy()) @ zmax
    Gmax = float(np.linalg.norm(reach + np.abs(b)))
    X = torch.as_tensor(system.X, dtype=_F64)
    hl, hh = h_enclosure(system, X[None, :, 0], X[None, :, 1])
    hl, hh = hl[0].numpy(), hh[0].numpy()
    if not (np.all(np.isfinite(hl)) and np.all(np.isfinite(hh))):
        return None
    Y = system.Y
    rmax = float(np.linalg.norm(np.maximum(np.abs(Y[:, 1] - hl), np.abs(hh - Y[:, 0]))))
    K = float(np.linalg.norm(net.K.detach().to(_F64).numpy(), 2))
    return (LN * rmax + Gmax + K) * _ROUND_UP ** (len(Ws) + 6)


def dk_dy_norms(problem: Problem, z: torch.Tensor) -> torch.Tensor:
    """||dk/dy(xhat, y)||_2 at z = (xhat, y) [B, n+p] -> [B] (differentiable; NaN stays NaN)."""
    n = problem.n
    J = gain_terms(problem.system, problem.network, z[:, :n], z[:, n:], with_dy=True).dk_dy
    finite = torch.isfinite(J).all(dim=-1).all(dim=-1)
    safe = torch.where(finite[:, None, None], J, torch.zeros_like(J))  # SVD fails on NaN
    # scale by a power of two per point (exact) so that huge gains do not overflow the norm
    e = torch.frexp(safe.detach().abs().amax((-1, -2)).clamp_min(2.0 ** -1000)).exponent
    safe = torch.ldexp(safe, -e[:, None, None])
    if J.shape[-1] == 1:
        norm = torch.linalg.vector_norm(safe[..., 0], dim=-1)
    else:
        norm = torch.linalg.matrix_norm(safe, ord=2)
    return torch.where(finite, torch.ldexp(norm, e), torch.full_like(J[:, 0, 0], float("nan")))


def sampled_lower(problem: Problem, points: int = 20_000, starts: int = 16, steps: int = 60,
                  seed: int = 0) -> tuple[float, list[float]]:
    """max ||dk/dy||_2 over a grid of X x Y, then projected ascent from the best points.

    The search runs on float64 values; the number returned is a SOUND lower bound of
    ||dk/dy||_2 at the best point found (`certify.search.witness.dk_dy_norm_lower`), so it is a
    lower bound on the supremum whatever the rounding.
    """
    box = np.vstack([problem.system.X, problem.system.Y])
    out = maximize_over_box(lambda z: dk_dy_norms(problem, z), box[:, 0], box[:, 1],
                            grid_points=points, starts=starts, steps=steps, top_k=1, seed=seed,
                            task="Lipschitz grid")
    if not math.isfinite(out.best_value):
        return float("nan"), out.best_point.tolist()
    sound = float(dk_dy_norm_lower(problem, torch.as_tensor(out.best_point)[None])[0])
    return (sound if math.isfinite(sound) else float("nan")), out.best_point.tolist()


def lipsdp_for(problem: Problem, method: str = "ipm") -> sdp.SdpResult | None:
    """Verified LipSDP for k in y; None for the structural architecture (for P^(1/2) k: the
    weighted problem of `certify.prove.weighted`)."""
    net = problem.network
    if net.structure != "direct":
        return None
    Ws, Wo = mlp_in_y(net, problem.n)
    K = net.K.detach().to(_F64).numpy()
    if not Ws:  # no hidden layer: k is affine in y, L = ||W0y + K||_2 exactly
        L = float(np.linalg.norm(Wo + K, 2)) * _ROUND_UP
        return sdp.SdpResult(Status.PROVED, "affine in y: exact", L, solver="closed-form",
                             raw_value=L, verified=True)
    return lipsdp.lipsdp_neuron(Ws, Wo, K, method=method, slope=net.act.slope_bounds)


def check_lipschitz(problem: Problem, settings: VerifySettings | None = None, *,
                    progress: Progress = _NULL_PROGRESS, local_upper: float | None = None,
                    sample_points: int = 20_000,
                    local: Callable[[], tuple[float | None, ProofStats]] | None = None,
                    local_P: Callable[[], tuple[float | None, ProofStats]] | None = None,
                    weighted: Weighting | None = None) -> LipschitzResult:
    """LipSDP (verified), naive, sampled lower bound and the caller's local bound.

    `value` is the smallest sound bound and `which` names it ("lipsdp", "naive" - both
    global - or "local" - valid while y and y_e stay in Y). PROVED when a finite sound bound
    exists, UNKNOWN otherwise; ERROR if a sampled value exceeds a sound bound (a bug).
    `local`: computes the local bound (the dk/dy branch and bound) when `local_upper` is not
    given; it is called only when the global bound leaves room for it, i.e. is more than
    `LOCAL_ROOM` above the sampled lower bound (else the local bound could lower L by less
    than that: for k affine in y the global bound is exact, and a local proof by entry
    magnitudes, exact only for p = 1, would spend its whole budget without closing).
    `L_P`: the same constant for P^(1/2) k, the smaller of the metric-weighted LipSDP and
    `local_P()` (the caller's local bound of sup ||P^(1/2) dk/dy||), both through
    `certify.prove.weighted` (sound for the float square root of P; `weighted`: its
    weighting of the problem, default made here); L_P = L when P = I. `local` and `local_P`
    return their bound and their proof's stats (`ProofStats`, summed into `proof`).
    """
    t0 = time.perf_counter()
    settings = settings or VerifySettings()
    task = "lipschitz"
    progress.start(task, total=3)
    structural = problem.network.structure != "direct"
    identity_metric = is_identity(problem.P)
    if not identity_metric and weighted is None:
        weighted = weighting(problem)
    proofs: list[ProofStats] = []
    solver: dict = {}
    res = lipsdp_for(problem)
    progress.update(task)
    lipsdp = lipsdp_raw = eig = None
    verified = False
    lipsdp_P = None
    if res is not None:
        solver = res.stats()
        lipsdp_raw = res.raw_value
        eig = res.check_max_eig
        if res.status is Status.PROVED and res.value is not None and math.isfinite(res.value):
            lipsdp, verified = res.value, True
        if not identity_metric:
            resP = lipsdp_for(weighted.problem)
            solver["metric_weighted"] = resP.stats() if resP is not None else None
            if resP is not None and resP.status is Status.PROVED:
                lipsdp_P = weighted.bound(resP.value, weighted.dy_error)
        else:
            lipsdp_P = lipsdp
    if structural:
        naive = structural_local_naive(problem)
        naive_f = math.inf if naive is None else naive
    else:
        naive_f = naive_bound(problem.network, problem.n)
    progress.update(task)
    sampled, where = sampled_lower(problem, points=min(sample_points, settings.grid_points),
                                   seed=settings.seed)
    progress.update(task)
    global_bound = min([b for b in (lipsdp, None if structural else naive_f)
                        if b is not None and math.isfinite(b)], default=math.inf)
    local_skipped = False
    if local_upper is None and local is not None:
        if math.isfinite(sampled) and global_bound <= sampled * (1.0 + LOCAL_ROOM):
            local_skipped = True
        else:
            local_upper, stats = local()
            proofs.append(stats)
    cands: list[tuple[float, str]] = []
    if lipsdp is not None:
        cands.append((lipsdp, "lipsdp"))
    if local_upper is not None and math.isfinite(local_upper):
        cands.append((float(local_upper), "local"))
    if math.isfinite(naive_f):
        cands.append((naive_f, "local" if structural else "naive"))
    value, which = (min(cands) if cands else (None, ""))
    if structural and value is not None:
        which = "local"
    # L_P: the same constant for P^(1/2) k (equal to L when P = I)
    if identity_metric:
        L_P, L_P_which, local_upper_P = value, ("local" if which == "local" else "global"), None
    else:
        local_upper_P = None
        if local_P is not None:
            local_upper_P, stats = local_P()
            proofs.append(stats)
        cands_P = [(v, w) for v, w in ((lipsdp_P, "global"), (local_upper_P, "local"))
                   if v is not None and math.isfinite(v)]
        L_P, L_P_which = min(cands_P) if cands_P else (None, "")
    seconds = time.perf_counter() - t0
    parts = [f"sampled >= {sampled:.6g}"]
    if lipsdp is not None:
        parts.append(f"LipSDP {upper_text(lipsdp, 6)} (verified)")
    elif res is not None:
        parts.append(f"LipSDP unverified ({res.message})")
    else:
        parts.append("LipSDP not applicable (structural k = G (y - h): the MLP's constant does "
                     "not bound k's)")
    parts.append(f"naive {upper_text(naive_f, 6)}"
                 + (" (local, over X x Y)" if structural else ""))
    if local_upper is not None:
        parts.append(f"interval prover {upper_text(local_upper, 6)} (local)")
    if L_P is not None and not identity_metric:
        parts.append(f"L_P (P^(1/2) k) <= {upper_text(L_P, 6)} ({L_P_which})")
    elif local_skipped:
        parts.append(f"local proof not run (the global bound is within {LOCAL_ROOM:g} of the "
                     "sampled value)")
    if value is None:
        status, msg = Status.UNKNOWN, "no finite sound bound; " + "; ".join(parts)
    elif not math.isfinite(sampled):
        status, msg = Status.UNKNOWN, "dk/dy is NaN/Inf at some points; " + "; ".join(parts)
    elif sampled > value:  # both sound: a sound lower bound above a sound upper one
        status = Status.ERROR
        msg = (f"BUG: sampled ||dk/dy|| = {sampled:.6g} at {where} exceeds the sound bound "
               f"{value:.6g} ({which}); " + "; ".join(parts))
    else:
        status = Status.PROVED
        msg = (f"L <= {upper_text(value, 6)} ({which}" + (", valid while y and y_e stay in Y" if
               which == "local" else ", any xhat and y") + "); " + "; ".join(parts))
    progress.finish(task, msg)
    solver["sampled_at"] = where
    return LipschitzResult(
        status=status, message=msg, lipsdp=lipsdp, lipsdp_raw=lipsdp_raw,
        lipsdp_verified=verified, lipsdp_lmi_max_eig=eig, naive=naive_f, sampled=sampled,
        local_upper=local_upper, value=value, which=which, solver=solver, seconds=seconds,
        lipsdp_P=lipsdp_P, L_P=L_P, L_P_which=L_P_which, local_upper_P=local_upper_P,
        proof=ProofStats.total(proofs),
    )


# ----------------------------------------------------------------------------- check protocol

class LipschitzCheck(Check):
    """L, the Lipschitz constant of k in y: LipSDP, the local interval bound, naive, sampled."""

    name = "lipschitz"
    title = "Lipschitz constant L"
    result_type = LipschitzResult
    reads = ("lipschitz_boxes", "grid_points", "seed")

    def run(self, context: Context) -> LipschitzResult:
        from certify.prove.side import bound_dk_dy

        budget = dict(max_boxes=context.settings.lipschitz_boxes, deadline=context.deadline,
                      rel_tol=LOCAL_ROOM)

        def local() -> tuple[float | None, ProofStats]:
            return bound_dk_dy(context.on_device(), **budget)

        def local_P() -> tuple[float | None, ProofStats]:
            w = context.weighted()
            upper, stats = bound_dk_dy(context.on_device(w.problem), **budget)
            return w.bound(upper, w.dy_error), stats

        return check_lipschitz(context.problem, context.settings, progress=context.progress,
                               local=local, local_P=local_P,
                               weighted=None if is_identity(context.problem.P)
                               else context.weighted())

    def present(self, r: LipschitzResult, certificate: Any) -> Presentation:
        s = certificate.settings or {}
        which = f" ({r.which})" if r.which else ""
        solver = (r.solver or {}).get("name", "")
        setting = [setting_quantity("lipschitz_boxes", s)]
        if solver:
            setting.append(Quantity("LipSDP with", solver))
        facts = [Quantity("Used", r.value, "no sound bound", suffix=which, bound="upper")]
        if r.solver:
            facts += [Quantity(f"LipSDP solver: {k}", v) for k, v in r.solver.items()
                      if not isinstance(v, (dict, list))]
        return Presentation(
            sampled=Quantity("L \u2265 (sampled max \u2016\u2202k/\u2202y\u2016)", r.sampled,
                             bound="lower"),
            proved=Quantity("L \u2264 (bound used)", r.value, "no sound bound", suffix=which,
                            bound="upper"),
            setting=tuple(setting),
            numbers=(Quantity("LipSDP (verified)", r.lipsdp, "not verified", sig=6,
                              bound="upper"),
                     Quantity("LipSDP raw", r.lipsdp_raw, sig=6),
                     Quantity("LMI max eigenvalue", r.lipsdp_lmi_max_eig, sig=3, signed=True),
                     Quantity("local interval bound", r.local_upper, sig=6, bound="upper"),
                     Quantity("naive", r.naive, sig=6, bound="upper"),
                     Quantity("sampled", r.sampled, sig=6, bound="lower"),
                     Quantity("used", r.value, sig=6, suffix=which, bound="upper")),
            facts=tuple(facts))


CHECK = LipschitzCheck()
