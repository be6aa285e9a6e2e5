"""A verification problem: the system, the gain network, the metric P and the rate lam.

The matrix every proof is about is D = He{P (Jf + dk/dxhat)} + 2 lam P + Q, with an optional
constant symmetric term Q (`shift`, default none): the MPDI has Q = 0; the dissipation
certificates (`certify.prove.dissipation`) prove the same matrix function with a constant
positive semidefinite Q, so they reuse the MPDI prover unchanged.

With a `NoiseInput` the matrix is the path certificate's, of size m = n + p: the noise enters
at the same point as the contraction. With J_F = Jf + dk/dxhat and B = dk/dy at (xhat, y),

    D~ = He{P~ J~} + 2 lam P~ + Q~,   J~ = [[J_F, B], [0, 0]],   P~ = diag(P, s I_p),
    Q~ = diag(Q, q I_p),   lam = alpha / 4,   q >= -mu/2 - 2 lam s (rounded up),

so that D~ = [[He{P J_F} + (alpha/2) P + Q, P B / 2], [B^T P / 2, (2 lam s + q) I]] with
2 lam s + q >= -mu/2: D~ <= 0 implies the path inequality of `NoiseInput` (the lower block
only more negative). The network, Jf and dk/dy are enclosed exactly as for the MPDI; the
prover sees one more square matrix of the same form (`P_t`, `shift_t` are P~ and Q~).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.spec.system import System


@dataclass(frozen=True)
class NoiseInput:
    """The measurement noise as a second input of the path (differential) dissipation
    certificate (`certify.prove.dissipation`): at every (xhat, y) of X x Y

        [[2 He{P J_F} + alpha P + 2 Q,  P B ],
         [B^T P,                        -mu I]]  <=  0

    (twice the problem's matrix D~, module docstring). `alpha` > 0 is the rate of the path
    energy, `mu` > 0 the noise gain, `scale` > 0 the noise block s of the prover's metric
    diag(P, s I) (it only conditions the proof: any s > 0 gives the same inequality)."""

    alpha: float
    mu: float
    scale: float

    def __post_init__(self) -> None:
        for name in ("alpha", "mu", "scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"NoiseInput.{name} must be a finite number > 0; got {v!r}")

    def lower_block(self, lam: float) -> float:
        """q, rounded up, with 2 lam s + q >= -mu/2 exactly (see the module docstring)."""
        two_lam_s = math.nextafter(2.0 * lam * self.scale, -math.inf)  # <= 2 lam s
        return math.nextafter(-0.5 * self.mu - two_lam_s, math.inf)


@dataclass(eq=False)
class Problem:
    """Everything a check needs about *what* is verified (settings say *how*)."""

    system: System
    network: GainNetwork
    lam: float
    P: np.ndarray  # [n, n], symmetric positive definite
    device: str = "cpu"  # where the network's weights and P_t live (see `on`)
    shift: np.ndarray | None = None  # [n, n] constant symmetric Q added to D (None: 0)
    #: the path certificate's noise input (module docstring); None: the MPDI's matrix
    noise: NoiseInput | None = None
    #: a metric that follows the state (`certify.model.metric.PolyMetric`), for the error
    #: bound of `certify.prove.metric`; None: the constant metric P only
    metric: PolyMetric | None = None

    def __post_init__(self) -> None:
        self.network = self.network.double().eval()
        for param in self.network.parameters():
            param.requires_grad_(False)
        if self.metric is not None and self.metric.n != self.system.n:
            raise ValueError(f"the metric is for {self.metric.n} states; the system has "
                             f"{self.system.n}")
        if self.noise is not None and self.lam != self.noise.alpha / 4.0:
            raise ValueError("a problem with a noise input is proved at lam = alpha / 4; got "
                             f"lam {self.lam!r} for alpha {self.noise.alpha!r}")

    @property
    def m(self) -> int:
        """The size of the matrix the prover bounds: n, or n + p with a noise input."""
        return self.n + (self.p if self.noise is not None else 0)

    @property
    def P_t(self) -> torch.Tensor:
        """The prover's metric [m, m]: P, or diag(P, s I_p) with a noise input."""
        P = torch.as_tensor(self.P, dtype=torch.float64, device=self.device)
        if self.noise is None:
            return P
        return torch.block_diag(P, self.noise.scale * torch.eye(
            self.p, dtype=torch.float64, device=self.device))

    @property
    def shift_t(self) -> torch.Tensor | None:
        """The constant term [m, m] as a float64 tensor on the problem's device: Q (None: no
        constant term), or diag(Q, q I_p) with a noise input (`NoiseInput.lower_block`)."""
        if self.noise is None:
            if self.shift is None:
                return None
            return torch.as_tensor(self.shift, dtype=torch.float64, device=self.device)
        f64 = dict(dtype=torch.float64, device=self.device)
        Q = (torch.zeros(self.n, self.n, **f64) if self.shift is None
             else torch.as_tensor(self.shift, **f64))
        q = self.noise.lower_block(self.lam)
        return torch.block_diag(Q, q * torch.eye(self.p, **f64))

    def on(self, device: torch.device | str) -> Problem:
        """This problem with a copy of the network (and P_t) on `device` (self if already
        there): for the kernels that run on a GPU (`--device cuda`)."""
        device = torch.device(device)
        if device == torch.device(self.device):
            return self
        import copy

        net = copy.deepcopy(self.network).to(device)
        return Problem(system=self.system, network=net, lam=self.lam, P=self.P,
                       device=str(device), shift=self.shift, noise=self.noise,
                       metric=self.metric)

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def p(self) -> int:
        return self.system.p

    @property
    def structural(self) -> bool:
        return self.network.structure == "structural"
