"""A verification problem: the system, the gain network, the metric P and the rate lam."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from certify.network import GainNetwork
from certify.system import System


@dataclass(eq=False)
class Problem:
    """Everything a check needs about *what* is verified (settings say *how*)."""

    system: System
    network: GainNetwork
    lam: float
    P: np.ndarray  # [n, n], symmetric positive definite

    def __post_init__(self) -> None:
        self.network = self.network.double().eval()
        for param in self.network.parameters():
            param.requires_grad_(False)

    @property
    def P_t(self) -> torch.Tensor:
        return torch.as_tensor(self.P, dtype=torch.float64)

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def p(self) -> int:
        return self.system.p

    @property
    def structural(self) -> bool:
        return self.network.structure == "structural"
