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

from certify.design.metric import (
    DEFAULT_KAPPA_MAX,
    MAX_DEFAULT_VERTICES,
    bounded_observer_lmi,
    default_vertex_count,
    observer_lmi,
)
from certify.errors import CertifyError
from certify.model import checkpoint
from certify.model.network import GainNetwork
from certify.results import Status, to_jsonable
from certify.spec.system import System

BASELINE_MARGIN = 0.05

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
