"""What `certify.verify` proves of a candidate design (the bound preset's comparisons):
candidates are compared by the bounds the verifier proves, never by what training measured."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.spec.system import System

#: the noise level the training run reports bounds at (the verifier's default `--noise`)
REPORT_VBAR = 0.15

#: a candidate beats another when its bound (sampled or proved) is below the other's
#: by more than this fraction (a smaller difference is the evaluation's rounding)
BEAT_TOLERANCE = 1e-3


def copy_network(net: GainNetwork) -> GainNetwork:
    """A float64 copy of `net` (its own parameters)."""
    out = GainNetwork.from_architecture(net.architecture())
    out.load_state_dict({k: v.detach().clone() for k, v in net.state_dict().items()})
    return out.double()


def certified_bound(system: System, net: GainNetwork, lam: float, P: np.ndarray, *,
                    metric: PolyMetric | None = None, vbar: float = REPORT_VBAR
                    ) -> dict[str, Any]:
    """`certify.verify` on (net, lam, P, metric) without simulation or figures, at noise
    `vbar`: the verdict and the error-bound check's best ultimate bound (None when none is
    proved), with the metric's stages (the bound with M(x) and its last tube, None when not
    proved). Whatever bounds the verifier proves decide; the comparison reads only the
    result's fields."""
    from certify.model.checkpoint import Checkpoint
    from certify.model.problem import Problem
    from certify.settings import VerifySettings
    from certify.verify import verify

    ck = Checkpoint(problem=Problem(system, net, lam, P, metric=metric), path="", sha256="")
    t0 = time.perf_counter()
    cert = verify(ck, VerifySettings(noise=vbar, skip=("simulation",)), figures=False)
    b = cert.checks.get("bounds")
    m = cert.checks.get("metric_bound")
    stages = getattr(m, "stages", None) or []
    return {"verdict": cert.verdict, "mpdi": cert.checks["mpdi"].status.value,
            "ultimate": getattr(b, "ultimate", None), "best": getattr(b, "best", None),
            "metric_ultimate": getattr(m, "ultimate", None),
            "metric_tau": float(stages[-1]["tau"]) if stages else None,
            "seconds": time.perf_counter() - t0}
