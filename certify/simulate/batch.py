"""The runs of the simulation check, side by side in one batch: who starts where, under
which noise.

Every chosen start (`certify.simulate.starts`) is run under each bounded noise kind of
`NOISE_KINDS`, in the order (start 1, uniform), (start 1, switching), (start 2, uniform),
...: uniform noise (random directions of norm vbar held a few steps, one seeded draw for all
uniform runs: `certify.simulate.integrate.bounded_noise` with `seed`) and switching noise
(worst-case-like, chosen from the states: `certify.simulate.noise.SwitchingNoise`, seed + 3).
When the spec has the source's initial condition, the source's protocol is run last:
Gaussian noise of std `SOURCE_NOISE_STD` (seed + 2), outside the theorem's conditions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from certify.model.problem import Problem
from certify.settings import VerifySettings
from certify.simulate.integrate import bounded_noise, gaussian_noise
from certify.simulate.noise import SwitchingNoise
from certify.simulate.starts import InitialConditions, source_initial_condition
from certify.spec.system import System

#: The source's simulation protocol: white Gaussian measurement noise of this std.
SOURCE_NOISE_STD = 0.15
#: The bounded noise kinds every start is run with: random directions of norm vbar held a
#: few steps, and worst-case-like noise chosen from the states
NOISE_KINDS = ("uniform", "switching")


@dataclass
class RunBatch:
    """The runs, row r of every array: label, how it started (`notes`), "bounded" or
    "gaussian" (`kinds`), the noise kind, x0 and xhat0 [R, n], the noise [steps, R, p] (the
    switching rows filled as the runs go, by `feedback`)."""

    labels: list[str]
    notes: list[str]
    kinds: list[str]
    noise_kinds: list[str]
    x0: torch.Tensor
    xhat0: torch.Tensor
    noise: torch.Tensor
    feedback: SwitchingNoise | None

    @property
    def bounded(self) -> list[int]:
        """Rows of the runs with bounded noise (inside the theorem's conditions)."""
        return [r for r, kind in enumerate(self.kinds) if kind == "bounded"]

    @property
    def e0(self) -> np.ndarray:
        """Initial errors x0 - xhat0 [R, n]."""
        return (self.x0 - self.xhat0).numpy()


def run_count(system: System, settings: VerifySettings) -> int:
    """How many runs `plan_runs` makes: every start under each noise kind, and the source's
    protocol when the spec has its initial condition (one of the starts is then the
    source's)."""
    src = source_initial_condition(system) is not None
    return settings.sim_initial_conditions * len(NOISE_KINDS) + int(src)


def plan_runs(problem: Problem, ics: InitialConditions, *, steps: int, dt: float,
              vbar: float, seed: int) -> RunBatch:
    """Every start under each of `NOISE_KINDS`, then the source's protocol (see the module
    docstring), with their noise over `steps` steps of `dt`."""
    system, p = problem.system, problem.system.p
    S = len(ics.labels)
    labels, notes, kinds, noise_kinds = [], [], [], []
    for i in range(S):
        for kind in NOISE_KINDS:
            labels.append(f"{ics.labels[i]}, {kind} noise")
            notes.append(ics.notes[i])
            kinds.append("bounded")
            noise_kinds.append(kind)
    pick = torch.arange(S).repeat_interleave(len(NOISE_KINDS))
    x0, xhat0 = ics.x0[pick], ics.xhat0[pick]
    R_b = len(labels)
    noise = torch.zeros(steps, R_b, p, dtype=torch.float64)
    uni = [r for r in range(R_b) if noise_kinds[r] == "uniform"]
    sw = [r for r in range(R_b) if noise_kinds[r] == "switching"]
    noise[:, uni] = bounded_noise(steps, len(uni), p, vbar, dt, seed=seed)
    feedback = (SwitchingNoise(system, problem.network, np.asarray(problem.P, dtype=np.float64),
                               vbar, sw, dt=dt, seed=seed + 3, max_window=steps * dt / 4)
                if sw else None)
    src = source_initial_condition(system)
    if src is not None:
        labels.append(f"source protocol (Gaussian noise, std {SOURCE_NOISE_STD:g}; outside "
                      "the theorem's conditions)")
        notes.append("the source's x0 and xhat0 with its Gaussian noise")
        x0 = torch.cat([x0, torch.tensor([src[0]], dtype=torch.float64)])
        xhat0 = torch.cat([xhat0, torch.tensor([src[1]], dtype=torch.float64)])
        noise = torch.cat([noise, gaussian_noise(steps, 1, p, SOURCE_NOISE_STD,
                                                 seed=seed + 2)], dim=1)
        kinds.append("gaussian")
        noise_kinds.append("gaussian")
    return RunBatch(labels=labels, notes=notes, kinds=kinds, noise_kinds=noise_kinds, x0=x0,
                    xhat0=xhat0, noise=noise, feedback=feedback)
