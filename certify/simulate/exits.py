"""Where each run's valid window ends: the first step at which a validity condition fails.

The proved bounds hold only while their conditions do (METHOD §3.7 (a)-(d)): the plant
state x and the observer state xhat in X, the true output h(x) in Y, and, where the bound
needs it, the measured output h(x) + v in Y. A non-finite state fails every condition. A
run is compared with the bound over [0, first exit) only.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from certify.results import BoundsResult
from certify.spec.system import System


def needs_measured_output(bounds: BoundsResult | None) -> bool:
    """Whether condition (d), y + v in Y, applies: L is a local bound, or the dissipation
    inequality (proved over X x Y only) is among the applicable bounds."""
    if bounds is None:
        return False
    joint = bounds.dissipation
    return bool(bounds.L_is_local or (joint is not None and joint.applicable))


def first_exit(system: System, x: torch.Tensor, xhat: torch.Tensor, v: torch.Tensor,
               t: torch.Tensor, measured: bool) -> tuple[np.ndarray, list[str]]:
    """First step index at which a validity condition fails, per run ([R]; T if never), and
    the reason in words ("" if never). x, xhat [T, R, n], v [T, R, p], t [T]; `measured`:
    condition (d), h(x) + v in Y, applies (`needs_measured_output`)."""
    T, R, n = x.shape
    X = torch.as_tensor(system.X, dtype=torch.float64)
    Y = torch.as_tensor(system.Y, dtype=torch.float64)
    hx = system.h(x.reshape(T * R, n)).reshape(T, R, system.p)
    checks: list[tuple[str, torch.Tensor, torch.Tensor, list[str]]] = [
        ("the plant state x left X", x, X, system.states),
        ("the observer state xhat left X", xhat, X, system.states),
        ("the true output h(x) left Y", hx, Y, system.outputs),
    ]
    if measured:
        checks.append(("the measured output h(x) + v left Y (L is a local bound)", hx + v, Y,
                       system.outputs))
    bad = torch.zeros(T, R, dtype=torch.bool)
    for _, val, box, _ in checks:
        inside = ((val >= box[:, 0]) & (val <= box[:, 1])).all(dim=-1)  # NaN -> outside
        bad |= ~inside
    any_bad = bad.any(dim=0)
    first = torch.where(any_bad, bad.to(torch.int8).argmax(dim=0), torch.full((R,), T))
    reasons: list[str] = []
    for r in range(R):
        k = int(first[r])
        if k >= T:
            reasons.append("")
            continue
        words = []
        for what, val, box, names in checks:
            row = val[k, r]
            for i, name in enumerate(names):
                a = float(row[i])
                if not math.isfinite(a):
                    words.append(f"{what}: {name} is not finite")
                elif a < box[i, 0]:
                    words.append(f"{what}: {name} = {a:.6g} < {float(box[i, 0]):g}")
                elif a > box[i, 1]:
                    words.append(f"{what}: {name} = {a:.6g} > {float(box[i, 1]):g}")
        reasons.append(f"t = {float(t[k]):.4g}: " + "; ".join(words))
    return first.numpy(), reasons
