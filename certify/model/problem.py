"""A verification problem: the system, the gain network, the metric P and the rate lam.

The matrix every proof is about is D = He{P (Jf + dk/dxhat)} + 2 lam P + Q, with an optional
constant symmetric term Q (`shift`, default none): the MPDI has Q = 0; the joint dissipation
certificate (`certify.prove.dissipation`) proves the same matrix function with a constant
positive semidefinite Q, so it reuses the MPDI prover unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from certify.model.network import GainNetwork
from certify.spec.system import System


@dataclass(eq=False)
class Problem:
    """Everything a check needs about *what* is verified (settings say *how*)."""

    system: System
    network: GainNetwork
    lam: float
    P: np.ndarray  # [n, n], symmetric positive definite
    device: str = "cpu"  # where the network's weights and P_t live (see `on`)
    shift: np.ndarray | None = None  # [n, n] constant symmetric Q added to D (None: 0)

    def __post_init__(self) -> None:
        self.network = self.network.double().eval()
        for param in self.network.parameters():
            param.requires_grad_(False)

    @property
    def P_t(self) -> torch.Tensor:
        return torch.as_tensor(self.P, dtype=torch.float64, device=self.device)

    @property
    def shift_t(self) -> torch.Tensor | None:
        """Q as a float64 tensor on the problem's device (None: no constant term)."""
        if self.shift is None:
            return None
        return torch.as_tensor(self.shift, dtype=torch.float64, device=self.device)

    def on(self, device: torch.device | str) -> Problem:
        """This problem with a copy of the network (and P_t) on `device` (self if already
        there): for the kernels that run on a GPU (`--device cuda`)."""
        device = torch.device(device)
        if device == torch.device(self.device):
            return self
        import copy

        net = copy.deepcopy(self.network).to(device)
        return Problem(system=self.system, network=net, lam=self.lam, P=self.P,
                       device=str(device), shift=self.shift)

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def p(self) -> int:
        return self.system.p

    @property
    def structural(self) -> bool:
        return self.network.structure == "structural"
