"""The metric-weighted gain R k (R^T R ~ P): its constants bound those of P^(1/2) k soundly.

The error bounds need eps_bar_P = sup_X ||P^(1/2) k(x, h(x))|| and L_P = sup ||P^(1/2) dk/dy||
over X x Y (or a global Lipschitz constant of P^(1/2) k in y). Both are constants of the gain
whose last layer (W_L, b_L) and injection K are pre-multiplied by P^(1/2): for a structural
gain G = N reshaped to [n, p], R G is the network with last layer (R kron I_p) W_L. So the
existing provers run unchanged on a *weighted problem* whose network carries
W' = fl(R_f Theta), Theta = (W_L, b_L, K), R_f a float symmetric square root of P. Two
roundings separate its constants from those of P^(1/2) k, and both are bounded here:

1. R_f^T R_f != P. With E = P - R_f^T R_f (bounded with its rounding error),
   ||P^(1/2) u||^2 = ||R_f u||^2 + u^T E u <= ||R_f u||^2 (1 + ||E|| / lam_min(R_f^T R_f)),
   so every constant of R_f k times `factor` = sqrt(1 + ||E|| / lam_min(R_f^T R_f)) bounds
   the one of P^(1/2) k (u = k or u = (dk/dy) w).
2. fl(R_f Theta) != R_f Theta: k and dk/dy are linear in Theta given the hidden layers, so
   R_f k = k(W') - k(Delta) with Delta = fl(R_f Theta) - R_f Theta, |Delta| <= gamma_{n+1}
   |R_f| |Theta| elementwise. `Weighting.value_error` and `Weighting.dy_error` bound
   ||k(Delta)|| on the boundary y = h(x) and ||dk(Delta)/dy|| by closed forms (norms of
   |Delta|'s bound times bounds of the hidden layer's values and slopes over the box); they
   are of order 1e-15 relative and only keep the argument exact.

Hence sup ||P^(1/2) dk/dy|| <= factor (sup ||dk'/dy|| + dy_error), and likewise for the
residual and for a global Lipschitz constant (LipSDP on the weighted network).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch

from certify.arith.intervals import gamma
from certify.model.problem import Problem
from certify.spec.enclosures import h_enclosure

__all__ = ["Weighting", "weighting", "spd_lam_min"]

_F64 = torch.float64
_UP = 1.0 + 1e-12  # relative widening of a few float64 operations (errors ~1e-15)


def spd_lam_min(P: np.ndarray) -> float:
    """A lower bound on lam_min(P) for a symmetric P (eigvalsh minus n u ||P|| times 4:
    Weyl's bound on the backward error); NaN when the bound is not positive."""
    P = np.asarray(P, dtype=np.float64)
    eig = np.linalg.eigvalsh(0.5 * (P + P.T))
    margin = 4.0 * P.shape[0] * np.finfo(np.float64).eps * float(np.abs(eig).max())
    lo = float(eig[0]) - margin
    return lo if lo > 0 else float("nan")


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    return (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


@dataclass(frozen=True)
class Weighting:
    """A weighted problem and the numbers that turn its constants into those of P^(1/2) k.

    `problem`: the original problem with its network's last layer and K replaced by
    fl(R_f Theta) (same system, P, lam; no shift). `factor` >= 1, `value_error` and
    `dy_error` >= 0 as in the module docstring (inf where a bound is not available)."""

    problem: Problem
    R: np.ndarray  # [n, n] float64, R^T R ~ P
    factor: float
    value_error: float
    dy_error: float

    def bound(self, weighted_upper: float | None, error: float) -> float | None:
        """factor (weighted_upper + error), rounded up; None when not finite."""
        if weighted_upper is None or not math.isfinite(weighted_upper):
            return None
        value = self.factor * (float(weighted_upper) + error) * _UP
        return value if math.isfinite(value) else None


def _factor(P: np.ndarray, R: np.ndarray) -> float:
    n = P.shape[0]
    E = P - R.T @ R
    err = gamma(n + 2) * (np.abs(R.T) @ np.abs(R) + np.abs(P))
    e_norm = float(np.sqrt(((np.abs(E) + err) ** 2).sum())) * _UP  # ||E||_2 <= ||E||_F
    lam = spd_lam_min(P)
    if not lam > e_norm:
        return math.inf
    return math.sqrt(1.0 + e_norm / ((lam - e_norm) / _UP)) * _UP


def _hidden_bounds(problem: Problem) -> tuple[float, float]:
    """(sup ||a_{L-1}||_2, sup ||d a_{L-1} / dy||_2) over X x Y: the last hidden layer's
    values and slopes in y (a_0 = z = (xhat, y) when there is no hidden layer), by norms and
    |f(x)| <= |f(0)| + Lip(f) |x| (or sup |f| where bounded). Crude by design: they multiply
    rounding errors of order 1e-15 only."""
    net = problem.network
    act = net.act
    box = np.concatenate([problem.system.X, problem.system.Y], 0).astype(np.float64)
    zmax = np.abs(box).max(1)
    layers = [(W.detach().cpu().to(_F64).numpy(), b.detach().cpu().to(_F64).numpy())
              for W, b in net.layer_weights()]
    n = problem.n
    amax = zmax
    slope = 1.0  # || d a / dy ||_2; for a_0 = z it is || [0; I] || = 1
    f0 = abs(float(act.f(torch.zeros(1, dtype=_F64))[0])) + 1e-12
    lip = act.lipschitz
    for i, (W, b) in enumerate(layers[:-1]):
        pre = (np.abs(W) @ amax + np.abs(b)) * _UP
        amax = np.minimum(f0 + lip * pre, act.value_bound) * _UP
        Wy = W[:, n:] if i == 0 else W
        slope = slope * float(np.linalg.norm(Wy, 2)) * lip * _UP
    return float(np.linalg.norm(amax)) * _UP, slope


def _residual_reach(problem: Problem) -> float:
    """sup ||y - h(xhat)||_2 over X x Y, from the interval enclosure of h over X."""
    s = problem.system
    X = torch.as_tensor(s.X, dtype=_F64)
    hl, hh = h_enclosure(s, X[None, :, 0], X[None, :, 1])
    hl, hh = hl[0].numpy(), hh[0].numpy()
    if not (np.all(np.isfinite(hl)) and np.all(np.isfinite(hh))):
        return math.inf
    reach = np.maximum(np.abs(s.Y[:, 1] - hl), np.abs(hh - s.Y[:, 0]))
    return float(np.linalg.norm(reach)) * _UP


def weighting(problem: Problem, R: np.ndarray | None = None) -> Weighting:
    """The weighted problem for `problem` (R: a float square root of P; the symmetric one
    by default) and its correction numbers."""
    P = np.asarray(problem.P, dtype=np.float64)
    R = _sqrt_psd(P) if R is None else np.asarray(R, dtype=np.float64)
    n, p = problem.n, problem.p
    net = copy.deepcopy(problem.network)
    last = net.layers[-1]
    Rt = torch.as_tensor(R, dtype=_F64)
    net = net.cpu()
    W, b, K = (last.weight.detach().to(_F64), last.bias.detach().to(_F64),
               net.K.detach().to(_F64))
    big = Rt if not problem.structural else torch.kron(Rt, torch.eye(p, dtype=_F64))
    with torch.no_grad():
        last.weight.copy_(big @ W)
        last.bias.copy_(big @ b)
        net.K.copy_(Rt @ K)
    g = gamma(n + 1)
    bigabs = big.abs().numpy()
    dW = g * bigabs @ np.abs(W.numpy())
    db = g * bigabs @ np.abs(b.numpy())
    dK = g * np.abs(R) @ np.abs(K.numpy())
    a_norm, a_slope = _hidden_bounds(problem)
    nW2, nWF = float(np.linalg.norm(dW, 2)), float(np.linalg.norm(dW))
    nb, nK = float(np.linalg.norm(db)), float(np.linalg.norm(dK, 2))
    if problem.structural:
        # k(Delta) = reshape(dW a + db) r + dK r vanishes at y = h(x)
        value_error = 0.0
        r_max = _residual_reach(problem)
        dy_error = (nWF * a_norm + nb + nWF * a_slope * r_max + nK) * _UP
    else:
        value_error = (nW2 * a_norm + nb) * _UP
        dy_error = (nW2 * a_slope + nK) * _UP
    weighted = Problem(system=problem.system, network=net, lam=problem.lam,
                       P=problem.P).on(problem.device)
    return Weighting(problem=weighted, R=R, factor=_factor(P, R),
                     value_error=value_error if math.isfinite(value_error) else math.inf,
                     dy_error=dy_error if math.isfinite(dy_error) else math.inf)
