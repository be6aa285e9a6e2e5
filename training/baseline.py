"""The certified LMI baseline: k0 = K (y - h(xhat)) from the joint LMI in (P, Y = P K).

A `GainNetwork` whose MLP output is exactly zero (last layer zero, weight and bias) and whose
linear injection buffer `K` is the LMI gain, structure "direct". Then dk/dxhat = -K C and
D = He{P (Jf - K C)} + 2 lam P, which the LMI bounds by -margin I at every vertex of the
interval enclosures of Jf over X, so `certify run` can prove it. The hidden layers keep a
seeded random initialisation so that the network is also a usable warm start for training
(a zero network would have zero gradients in its hidden layers).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from certify.checks.metric import DEFAULT_KAPPA_MAX, observer_lmi
from certify.errors import CertifyError
from certify.model import checkpoint
from certify.model.network import GainNetwork
from certify.results import Status, to_jsonable
from certify.spec.system import System

BASELINE_MARGIN = 0.05

#: vertex LMIs the SDP of `bounded_observer_lmi` gets at most (cvxpy's canonicalisation took
#: 160 s for 4096 6x6 LMIs, and 3^6 sub-boxes x 4096 vertices grew past 16 GB)
MAX_SDP_VERTICES = 1024

#: above this many vertex LMIs (sub-boxes x 2^entries, before pruning) `observer_lmi`'s
#: default subdivision is replaced by `bounded_observer_lmi` (lorenz, vdp, vdp2 stay below)
MAX_DEFAULT_VERTICES = 2**16


def make_lmi_baseline(system: System, lam: float, *, hidden: Sequence[int] = (8,),
                      margin: float = BASELINE_MARGIN, kappa_max: float = DEFAULT_KAPPA_MAX,
                      gain_max: float | None = 1e3, subdivisions: int | None = None,
                      objective: str = "kappa", seed: int = 0
                      ) -> tuple[GainNetwork, np.ndarray, dict[str, Any]]:
    """(network, P, info) for the LMI observer at rate lam; raises CertifyError if none.

    info holds the `MetricResult` (as plain data) and the gain's norm and condition number.
    """
    lmi = observer_lmi
    if subdivisions is None and default_vertex_count(system) > MAX_DEFAULT_VERTICES:
        lmi = bounded_observer_lmi
    res = lmi(system, lam, margin=margin, kappa_max=kappa_max, gain_max=gain_max,
              subdivisions=subdivisions, objective=objective)
    if res.status is not Status.PROVED or res.P is None or res.K is None:
        raise CertifyError(f"no certified LMI observer for {system.name} at lam = {lam:g}: "
                           f"{res.message}")
    P = np.asarray(res.P, dtype=np.float64)
    P = 0.5 * (P + P.T)
    K = np.asarray(res.K, dtype=np.float64)
    gen_state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        net = GainNetwork(system.n, system.p, hidden, structure="direct").double()
    finally:
        torch.random.set_rng_state(gen_state)
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        net.K.copy_(torch.as_tensor(K, dtype=torch.float64))
    info = {
        "metric": to_jsonable(res),
        "gain_norm": float(np.linalg.norm(K, 2)),
        "kappa_P": float(np.linalg.cond(P)),
        "margin": margin,
        "objective": objective,
    }
    return net, P, info


def _varying_entries(system: System) -> tuple[np.ndarray, np.ndarray]:
    """(varies, all_differ) [n, n] bool over all of X: entries of the Jf enclosure wider than
    its outward rounding, and entries whose enclosure has lo != hi at all (the coupling
    constants of vdp2/vdp3 differ by one rounding, which doubles the vertices per entry)."""
    from certify.checks.metric import sub_boxes
    from certify.spec.enclosures import jacobian_f_enclosure

    lo, hi = sub_boxes(system, 1, manifold=False)
    Jlo, Jhi = (t[0].numpy() for t in jacobian_f_enclosure(system, lo, hi))
    width = Jhi - Jlo
    return width > 1e-9 * (1.0 + np.maximum(np.abs(Jlo), np.abs(Jhi))), width > 0


def default_vertex_count(system: System) -> int:
    """Vertex LMIs `observer_lmi` would build by default (sub-boxes x 2^varying entries)."""
    from certify.checks.metric import default_subdivisions

    _, differ = _varying_entries(system)
    return default_subdivisions(system.n) ** system.n * 2 ** int(differ.sum())


def bounded_observer_lmi(system: System, lam: float, *, margin: float, kappa_max: float,
                         gain_max: float | None, subdivisions: int | None = None,
                         objective: str = "kappa") -> Any:
    """`certify.checks.metric.observer_lmi` with its memory bounded: vertices are enumerated
    only over the Jacobian entries that really vary (wider than rounding), and X is cut into
    the most sub-boxes per side that keep at most MAX_SDP_VERTICES vertex LMIs. The answer is
    re-checked in numpy at every vertex of the full enclosures (rounding-wide entries too),
    as `observer_lmi` does; the prover proves the observer anyway."""
    import time

    from certify.checks.metric import enclosure_vertices, observer_values, output_matrix, sub_boxes
    from certify.design import sdp
    from certify.results import MetricResult

    t0 = time.perf_counter()
    if not lam > 0:
        raise ValueError(f"lam must be > 0; got {lam}")
    varies, _ = _varying_entries(system)
    per_box = 2 ** int(varies.sum())
    per = subdivisions or max(1, int((MAX_SDP_VERTICES / per_box) ** (1.0 / system.n) + 1e-9))
    lo, hi = sub_boxes(system, per, manifold=False)
    verts = enclosure_vertices(system, lo, hi, relevant=varies)
    C = output_matrix(system)
    res = sdp.observer_sdp(verts.pruned, C, lam, margin=margin, kappa_max=kappa_max,
                           gain_max=gain_max, objective=objective)
    info = {**res.stats(), "sub_boxes": verts.boxes, "subdivisions": per,
            "sdp_vertices": len(verts.pruned), "gain_max": gain_max}
    if res.status is not Status.PROVED:
        return MetricResult(res.status, f"bounded LMI observer: {res.message}", None, None,
                            margin, lam, solver=info, seconds=time.perf_counter() - t0)
    P, K = res.variables["P"], res.variables["K"]
    full = enclosure_vertices(system, lo, hi).all
    top = float(observer_values(full, P, K, C, lam).max())
    info.update(check_max_vertex_value=top, vertices=len(full),
                gain_norm=float(np.linalg.norm(K, 2)))
    if not (top <= -0.5 * margin and float(np.linalg.eigvalsh(P)[0]) > 0):
        return MetricResult(Status.UNKNOWN, f"the LMI answer failed the re-check (max vertex "
                            f"value {top:.3g} > {-0.5 * margin:g})", None, None, margin, lam,
                            solver=info, seconds=time.perf_counter() - t0)
    msg = (f"LMI observer found: cond P = {np.linalg.cond(P):.4g}, ||K||_2 = "
           f"{info['gain_norm']:.4g}; lam_max <= {top:.3g} at all {len(full)} vertices of the "
           f"Jf enclosures on {verts.boxes} sub-boxes (re-checked in numpy)")
    return MetricResult(Status.PROVED, msg, P.tolist(), float(np.linalg.cond(P)), margin, lam,
                        K=K.tolist(), solver=info, seconds=time.perf_counter() - t0)


def save_lmi_baseline(path: str | Path, system: System, lam: float, **kwargs: Any
                      ) -> dict[str, Any]:
    """Write the LMI-baseline checkpoint (training record preset "lmi-baseline"); returns
    {"sha256", "P", "K", "kappa_P", "gain_norm"}. kwargs go to `make_lmi_baseline`."""
    net, P, info = make_lmi_baseline(system, lam, **kwargs)
    record = {
        "preset": "lmi-baseline",
        "method": "joint LMI He{P Jf - Y C} + 2 lam P <= -margin I at the vertices of "
                  "interval enclosures of Jf over X; K = P^-1 Y; MLP output zero",
        "lam": float(lam),
        "margin": info["margin"],
        "objective": info["objective"],
        "kappa_P": info["kappa_P"],
        "gain_norm": info["gain_norm"],
        "K": net.K.detach().clone(),
        "solver": info["metric"].get("solver", {}),
    }
    sha = checkpoint.save(path, system=system, network=net, lam=lam, P=P, training=record)
    return {"sha256": sha, "P": P.tolist(), "K": net.K.tolist(),
            "kappa_P": info["kappa_P"], "gain_norm": info["gain_norm"]}
