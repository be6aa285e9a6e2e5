"""The objective of counterexample-guided training (`CertObjective`).

It is the eigenvalue loss in the metric P with a margin,

    L = mean_j relu(lam_max(D_j) + margin)  +  lip_weight * (mean_j ||dk/dy_j||_F^(2q))^(1/(2q))
        + curv_weight * C + verifier_weight * V

with D = He{P (Jf + dk/dxhat)} + 2 (lam + rate_slack) P. The second term is a mild, sup-leaning
(q > 1) penalty on the gain's sensitivity to y, the constant L that multiplies the noise in
the error bound sqrt(kappa(P)) (eps_bar + L vbar) / (2 lam). C (`training.curvature`) is the
verification-aware term: the variation of dk/dxhat over pairs of points at a small distance,
which keeps the network cheap to prove, and V (`training.verifier`) the surrogate of the
prover's own box bound on sampled sub-boxes. It reuses the fast float32 forward-mode trunk of
`training.objective.Objective` (the one propagation `certify.model.gain.propagate` over chunk
buffers) with the y-columns added to the forward tangents; the head forms dk/dxhat and dk/dy
by `certify.model.gain.compose` (as the parent does) and autograd differentiates the small head
only. The penalty's gradient at the zero field dk/dy = 0 is 0 (`power_mean_norm`). Kept apart
from the loop (`training.cegis`) because it is the part that is differentiated: tests
compare its gradient with autograd.
"""

from __future__ import annotations

import torch

from certify.model.gain.buffered import ChunkBuffers
from certify.model.kernels import sym
from certify.model.network import GainNetwork
from certify.spec.system import System
from training import losses
from training.curvature import CurvaturePenalty
from training.objective import LossValues, Objective
from training.verifier import VerifierPenalty


def power_mean_norm(s: torch.Tensor, q: float) -> torch.Tensor:
    """(mean_j s_j^q)^(1/(2q)) for s_j = ||dk/dy_j||_F^2 >= 0, q >= 1: the penalty's power
    mean of the norms ||dk/dy_j||_F, computed as sqrt(m) (mean_j (s_j/m)^q)^(1/(2q)) with
    m = max_j s_j so that s^q cannot overflow for large q.

    It is a norm of the field dk/dy (an L^(2q) mean of Frobenius norms: convex and
    1-homogeneous), differentiable except where every dk/dy_j is zero (the zero warm start,
    K = 0 and the MLP's last layer zero). There its value is its minimum, 0, and the formula's
    gradient would be 0 * inf = NaN; the gradient given there is 0, which is a subgradient of
    a norm at its minimum (the subdifferential at 0 is the dual unit ball). A smoothed form
    (e.g. sqrt(x + eps^2) - eps) would also be finite, but would change the penalty's value
    everywhere and its meaning (the constant L of the error bound, as recorded per round);
    this keeps both exact. For q >= 1 the points with s_j = 0 among nonzero ones have a
    finite derivative (d s^q / ds = q s^(q-1) is 0 or 1 at s = 0).
    """
    scale = s.detach().max()
    if not bool(scale > 0):  # every dk/dy is zero (or s is not finite: NaN/inf propagate)
        return s.sum() * 0.0
    return torch.sqrt(scale) * ((s / scale) ** q).mean() ** (1.0 / (2.0 * q))


class CertObjective(Objective):
    """Eigenvalue loss in the metric P with margin, plus the ||dk/dy|| penalty.

    The trunk runs forward mode over all n + p input columns (the parent's buffers are
    rebuilt for that); the head is differentiated by autograd on [N, n, n] matrices.
    """

    def __init__(self, system: System, net: GainNetwork, xhat: torch.Tensor, y: torch.Tensor,
                 *, lam: float, P: torch.Tensor, margin: float, lip_weight: float = 0.0,
                 lip_power: float = 1.0, mpdi_weight: float = 1.0, mu_bc: float = 1.0,
                 workers: int = 2, curvature: CurvaturePenalty | None = None,
                 verifier: VerifierPenalty | None = None) -> None:
        weights = losses.LossWeights(mu1=1.0, mu2=float(mu_bc), rho=(1.0,) * system.n)
        super().__init__(system, net, xhat, y, lam=lam, P=P, weights=weights, loss="eigen",
                         margin=margin, workers=workers, curvature=curvature,
                         verifier=verifier)
        self.lip_weight, self.lip_power = float(lip_weight), float(lip_power)
        if not self.lip_power >= 1:
            raise ValueError(f"lip_power must be >= 1; got {lip_power!r}")
        self.mpdi_weight = float(mpdi_weight)
        n, p = system.n, system.p
        self.m = n + p  # forward tangents for every input column (xhat and y)
        self.chunks = [ChunkBuffers(ch.Z, ch.C, self.widths, self.m, not self.structural)
                       for ch in self.chunks]
        self.last_lip = 0.0
        self.last_lip_max = 0.0  # max ||dk/dy||_F over the collocation points

    def _head(self, val: torch.Tensor, tan: torch.Tensor, k_bc: torch.Tensor | None,
              grad: bool) -> tuple[float, float, list[torch.Tensor] | None]:
        N = self.N
        val_l = val.detach().requires_grad_(grad)
        tan_l = tan.detach().requires_grad_(grad)
        kbc_l = None if k_bc is None else k_bc.detach().requires_grad_(grad)
        with torch.enable_grad():
            gain = self._compose(val_l, tan_l, with_dy=True)  # dk/dxhat less -K Hx (in D0)
            M, dky = gain.dk_dx, gain.dk_dy
            D = self.D0 + sym(M if self.P_is_identity else self.P @ M)
            mpdi = losses.eigen_loss(D, self.margin, reduce="sum")
            total = self.mpdi_weight * mpdi / N
            lip = torch.zeros((), dtype=D.dtype)
            if self.lip_weight > 0:
                lip = power_mean_norm((dky * dky).sum(dim=(1, 2)), self.lip_power)
                total = total + self.lip_weight * lip
            bc = torch.zeros((), dtype=D.dtype)
            if kbc_l is not None:
                bc = (kbc_l * kbc_l).sum()
                total = total + self.weights.mu2 * bc / N
            self.last_lip = float(lip.detach())
            self.last_lip_max = float(torch.sqrt((dky * dky).sum(dim=(1, 2)).max()).detach())
            if not grad:
                return float(mpdi), float(bc), None
            inputs = [val_l, tan_l] + ([kbc_l] if kbc_l is not None else [])
            grads = torch.autograd.grad(total, inputs, allow_unused=True)
        grads = [torch.zeros_like(x) if g is None else g for x, g in zip(inputs, grads)]
        return float(mpdi), float(bc), grads

    def evaluate(self, grad: bool = True) -> LossValues:
        v = super().evaluate(grad)
        total = self.mpdi_weight * v.mpdi + self.weights.mu2 * v.bc \
            + self.lip_weight * self.last_lip + self.extra_total(v.curv, v.verifier)
        return LossValues(total=total, mpdi=v.mpdi, bc=v.bc, curv=v.curv, verifier=v.verifier)
