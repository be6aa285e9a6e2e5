"""A metric that follows the state: M(x) = sum_k x^(a_k) M_k, a symmetric matrix polynomial.

`PolyMetric` holds the exponents a_k [K, n] (non-negative integers, total degree at most
`MAX_DEGREE`) and the coefficients M_k [K, n, n] (symmetric float64). It is data only: values
and derivatives at points (`value`, `partials`, torch, differentiable in x), plain-data round
trips for checkpoints and certificates (`to_dict`, `from_dict`) and the checks that refuse a
malformed metric with one line (`PolyMetric.__post_init__`). Positive definiteness is a
property of the metric *on a region*, which only the prover can establish
(`certify.prove.metric`); nothing here assumes it. A constant metric P is the polynomial with
the single exponent 0 (`PolyMetric.constant`).

The metric depends on the state alone, never on the measured output: the path argument of
`certify.prove.metric` differentiates M along the flow of each path point, and the measured
output y + v has no bounded derivative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from certify.errors import CertifyError

#: the largest total degree of a metric polynomial
MAX_DEGREE = 4
#: the version of the plain-data form (`to_dict`)
FORMAT = 1


class MetricError(CertifyError):
    """A metric that cannot be used as given (one line naming the problem)."""


@dataclass(frozen=True, eq=False)
class PolyMetric:
    """M(x) = sum_k prod_i x_i^(exponents[k, i]) coefficients[k] (module docstring)."""

    exponents: np.ndarray  # [K, n] int
    coefficients: np.ndarray  # [K, n, n] float64, symmetric

    def __post_init__(self) -> None:
        e = np.asarray(self.exponents)
        c = np.asarray(self.coefficients, dtype=np.float64)
        if e.ndim != 2 or c.ndim != 3 or len(e) != len(c) or len(e) == 0:
            raise MetricError("a metric polynomial needs exponents [K, n] and coefficients "
                              f"[K, n, n] with K >= 1; got shapes {e.shape} and {c.shape}")
        n = e.shape[1]
        if c.shape[1:] != (n, n):
            raise MetricError(f"metric coefficients must be {n} x {n} matrices (one per state); "
                              f"got {c.shape[1]} x {c.shape[2]}")
        if not np.issubdtype(e.dtype, np.integer) and not np.all(e == np.round(e)):
            raise MetricError("metric exponents must be whole numbers")
        e = e.astype(np.int64)
        if np.any(e < 0):
            raise MetricError("metric exponents must be >= 0")
        degree = int(e.sum(1).max())
        if degree > MAX_DEGREE:
            raise MetricError(f"the metric polynomial has degree {degree}; at most "
                              f"{MAX_DEGREE} is supported")
        if len({tuple(r) for r in e}) != len(e):
            raise MetricError("a monomial of the metric is listed twice")
        if not np.all(np.isfinite(c)):
            raise MetricError("the metric has a coefficient that is not a finite number")
        if not np.array_equal(c, c.transpose(0, 2, 1)):
            k = int(np.argmax(np.abs(c - c.transpose(0, 2, 1)).reshape(len(c), -1).max(1)))
            raise MetricError(f"the metric is not symmetric: the coefficient of monomial "
                              f"{_monomial_text(e[k])} differs from its transpose")
        object.__setattr__(self, "exponents", e)
        object.__setattr__(self, "coefficients", c)

    # ---- construction
    @classmethod
    def constant(cls, P: np.ndarray) -> PolyMetric:
        P = np.asarray(P, dtype=np.float64)
        return cls(np.zeros((1, P.shape[0]), dtype=np.int64), P[None].copy())

    @property
    def n(self) -> int:
        return int(self.exponents.shape[1])

    @property
    def degree(self) -> int:
        return int(self.exponents.sum(1).max())

    @property
    def is_constant(self) -> bool:
        return self.degree == 0

    # ---- points
    def monomials(self, x: torch.Tensor) -> torch.Tensor:
        """x^(a_k) at points x [B, n] -> [B, K] (differentiable: no in-place updates)."""
        cols = []
        for e in self.exponents:
            m = torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
            for i, a in enumerate(e):
                if a:
                    m = m * x[:, i] ** int(a)
            cols.append(m)
        return torch.stack(cols, 1)

    def value(self, x: torch.Tensor) -> torch.Tensor:
        """M(x) at points x [B, n] -> [B, n, n]."""
        c = torch.as_tensor(self.coefficients, dtype=x.dtype, device=x.device)
        return torch.einsum("bk,kij->bij", self.monomials(x), c)

    def partials(self, x: torch.Tensor) -> torch.Tensor:
        """dM/dx_i at points x [B, n] -> [B, n (i), n, n]."""
        out = []
        for i in range(self.n):
            d = self.derivative(i)
            out.append(d.value(x) if d is not None
                       else torch.zeros(x.shape[0], self.n, self.n, dtype=x.dtype,
                                        device=x.device))
        return torch.stack(out, 1)

    def derivative(self, i: int) -> PolyMetric | None:
        """dM/dx_i as a metric polynomial (None where it is 0)."""
        keep = self.exponents[:, i] > 0
        if not keep.any():
            return None
        e = self.exponents[keep].copy()
        c = self.coefficients[keep] * e[:, i, None, None].astype(np.float64)
        e[:, i] -= 1
        return PolyMetric(e, c)

    def rate_along(self, x: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
        """Mdot = sum_i dM/dx_i F_i at points x [B, n] with velocities F [B, n] -> [B, n, n]."""
        return torch.einsum("bi,bijk->bjk", F, self.partials(x))

    # ---- plain data
    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "kind": "polynomial",
                "exponents": self.exponents.tolist(),
                "coefficients": self.coefficients.tolist()}

    @classmethod
    def from_dict(cls, data: Any, n: int | None = None) -> PolyMetric:
        """The metric of `to_dict`'s form (refused with one line when malformed)."""
        if not isinstance(data, dict) or data.get("kind") != "polynomial":
            raise MetricError("a state-dependent metric must be a table with kind = "
                              "'polynomial', exponents and coefficients")
        if data.get("format", FORMAT) != FORMAT:
            raise MetricError(f"metric format {data.get('format')!r} is not supported "
                              f"(this certify reads format {FORMAT})")
        try:
            e = np.asarray(data["exponents"])
            c = np.asarray(data["coefficients"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise MetricError(f"the metric's exponents or coefficients cannot be read "
                              f"({exc})") from None
        m = cls(e, c)
        if n is not None and m.n != n:
            raise MetricError(f"the metric is for {m.n} states; the system has {n}")
        return m

    def text(self, names: list[str] | None = None, digits: int = 4) -> str:
        """'M(x) = M0 + x1^2 M1 + ...' with the matrices written out (reports)."""
        parts = []
        for e, c in zip(self.exponents, self.coefficients):
            mat = "[" + ", ".join("[" + ", ".join(f"{v:.{digits}g}" for v in row) + "]"
                                  for row in c) + "]"
            mono = _monomial_text(e, names)
            parts.append(mat if mono == "1" else f"{mono} {mat}")
        return " + ".join(parts)


def _monomial_text(e: np.ndarray, names: list[str] | None = None) -> str:
    names = names or [f"x{i + 1}" for i in range(len(e))]
    factors = [names[i] + (f"^{int(a)}" if a > 1 else "") for i, a in enumerate(e) if a]
    return " ".join(factors) or "1"


def even_monomials(n: int, degree: int) -> np.ndarray:
    """Every exponent [K, n] of even total degree <= `degree` (a metric even in x: M(x) =
    M(-x), the shape of the designs for systems symmetric about the origin)."""
    out = [e for e in _exponents(n, degree) if sum(e) % 2 == 0]
    return np.array(out, dtype=np.int64)


def all_monomials(n: int, degree: int) -> np.ndarray:
    """Every exponent [K, n] of total degree <= `degree`."""
    return np.array(list(_exponents(n, degree)), dtype=np.int64)


def _exponents(n: int, degree: int):
    def rec(i: int, left: int):
        if i == n:
            yield ()
            return
        for a in range(left + 1):
            for rest in rec(i + 1, left - a):
                yield (a, *rest)
    return sorted(rec(0, degree), key=lambda e: (sum(e), tuple(-a for a in e)))


def monomial_count(n: int, degree: int) -> int:
    return math.comb(n + degree, degree)
