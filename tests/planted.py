"""Builders for test problems: linear ground truth and planted violations.

- `linear_system(A, C, ...)`: a spec for f = A x, h = C x (TOML text built here, then
  parsed by `System.from_text`, so it goes through the whitelist parser).
- `linear_problem(A, C, K, ...)`: zero network plus the exact linear injection K (y - C x):
  the closed-loop Jacobian is the constant A - K C, so lam_cert is known in closed form.
- `bump_network(...)`: a tanh MLP whose dk1/dxhat1 is large only in a thin slab on the
  entering face of a tiny box-shaped blob ("AND" of 2d steep sigmoids), nearly 0 elsewhere.
- `planted_problem(kind)`: a contracting linear base (lam_max(D) = -0.5 everywhere) plus a
  bump placed at a corner, along an edge, or inside: D is violated only in a region of
  about 1e-6 of the box volume.
"""

from __future__ import annotations

import numpy as np
import torch

from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.spec.system import System


def _fmt(v: float) -> str:
    return repr(float(v))


def linear_system(A: np.ndarray, C: np.ndarray, X: np.ndarray | None = None,
                  Y: np.ndarray | None = None, lam: float = 0.5,
                  P: np.ndarray | None = None, name: str = "linear") -> System:
    """Spec text for f = A x, h = C x over boxes X, Y (default [-1, 1] and C X)."""
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    n, p = A.shape[0], C.shape[0]
    X = np.array([[-1.0, 1.0]] * n) if X is None else np.asarray(X, dtype=float)
    if Y is None:
        Y = np.array([[-np.abs(C[i]) @ np.abs(X).max(1), np.abs(C[i]) @ np.abs(X).max(1)]
                      for i in range(p)])
    states = [f"x{i + 1}" for i in range(n)]
    outs = [f"y{i + 1}" for i in range(p)]

    def lin(row: np.ndarray) -> str:
        terms = [f"({_fmt(a)})*{s}" for a, s in zip(row, states) if a != 0]
        return " + ".join(terms) if terms else "0"

    P = np.eye(n) if P is None else np.asarray(P, dtype=float)
    text = "\n".join([
        f'name = "{name}"',
        f"states = {states!r}".replace("'", '"'),
        f"outputs = {outs!r}".replace("'", '"'),
        "f = [" + ", ".join(f'"{lin(r)}"' for r in A) + "]",
        "h = [" + ", ".join(f'"{lin(r)}"' for r in C) + "]",
        "[box]",
        "X = " + str([[float(a), float(b)] for a, b in X]),
        "Y = " + str([[float(a), float(b)] for a, b in Y]),
        "[design]",
        f"lam = {float(lam)!r}",
        "P = " + str([[float(v) for v in row] for row in P]),
    ])
    return System.from_text(text, origin=f"test spec {name}")


def linear_problem(A: np.ndarray, C: np.ndarray, K: np.ndarray, lam: float = 0.5,
                   P: np.ndarray | None = None, hidden: tuple[int, ...] = (4, 4),
                   structure: str = "direct", **kw: object) -> Problem:
    """Zero network weights plus the linear injection K (y - C x)."""
    system = linear_system(A, C, lam=lam, P=P, **kw)  # type: ignore[arg-type]
    net = GainNetwork(system.n, system.p, hidden, structure=structure,
                      K=torch.as_tensor(np.asarray(K, dtype=float)))
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.zero_()
            layer.bias.zero_()
    return Problem(system, net, lam, system.P if P is None else np.asarray(P, dtype=float))


def lam_cert_linear(A: np.ndarray, C: np.ndarray, K: np.ndarray,
                    P: np.ndarray | None = None) -> float:
    """Closed form: -lam_max(He{P (A - K C)}, P) / 2."""
    A, C, K = (np.asarray(M, dtype=float) for M in (A, C, K))
    P = np.eye(A.shape[0]) if P is None else np.asarray(P, dtype=float)
    J = A - K @ C
    S = 0.5 * (P @ J + (P @ J).T)
    L = np.linalg.cholesky(P)
    Li = np.linalg.inv(L)
    return float(-np.linalg.eigvalsh(Li @ S @ Li.T).max() / 2)


def bump_network(n: int, p: int, center: np.ndarray, half_width: np.ndarray,
                 sharpness: float = 400.0, gate: float = 3.0, amplitude: float = 0.005
                 ) -> GainNetwork:
    """k_1 = amplitude (v + 1) / 2 with v ~ indicator of the blob |z - center| <= half_width.

    dk_1/dxhat_1 ~ amplitude * gate * sharpness / 2 on the blob's lower x1-face (a slab of
    thickness ~ 1/sharpness), exponentially small away from the blob.
    """
    d = n + p
    center = np.asarray(center, dtype=float)
    half_width = np.broadcast_to(np.asarray(half_width, dtype=float), (d,))
    net = GainNetwork(n, p, (2 * d, 1), structure="direct")
    W0 = np.zeros((2 * d, d))
    b0 = np.zeros(2 * d)
    for i in range(d):
        W0[2 * i, i] = sharpness
        b0[2 * i] = -sharpness * (center[i] - half_width[i])
        W0[2 * i + 1, i] = -sharpness
        b0[2 * i + 1] = sharpness * (center[i] + half_width[i])
    W1 = np.full((1, 2 * d), gate)
    b1 = np.array([-gate * (2 * d - 1)])
    W2 = np.zeros((n, 1))
    W2[0, 0] = amplitude / 2
    b2 = np.zeros(n)
    b2[0] = amplitude / 2
    with torch.no_grad():
        for layer, (W, b) in zip(net.layers, ((W0, b0), (W1, b1), (W2, b2))):
            layer.weight.copy_(torch.as_tensor(W))
            layer.bias.copy_(torch.as_tensor(b))
    return net


BASE_A = np.array([[-1.0, 0.5], [-0.5, -1.0]])
BASE_C = np.array([[1.0, 0.0]])
BASE_LAM = 0.25  # He{A} + 2 lam I = -0.5 I


def planted_problem(kind: str) -> Problem:
    """Contracting linear base on X = [-1,1]^2, Y = [-1,1] plus a bump at `kind`:
    "corner", "edge" or "blob" (interior); the violating set has ~1e-6 of the volume."""
    system = linear_system(BASE_A, BASE_C, X=np.array([[-1.0, 1.0]] * 2),
                           Y=np.array([[-1.0, 1.0]]), lam=BASE_LAM, name=f"planted-{kind}")
    if kind == "corner":
        # entering face x1 = 1 - w, at the corner x2 = -1, y = -1
        net = bump_network(2, 1, np.array([1.0, -1.0, -1.0]), np.array([0.01, 0.01, 0.01]),
                           sharpness=400.0, amplitude=0.005)
    elif kind == "edge":
        # thin along x1 and x2, along the whole edge x2 = -1, x1 ~ 1 in y
        net = bump_network(2, 1, np.array([1.0, -1.0, 0.0]), np.array([0.004, 0.004, 2.0]),
                           sharpness=1000.0, amplitude=0.002)
    elif kind == "blob":
        net = bump_network(2, 1, np.array([0.3, -0.2, 0.1]), np.array([0.01, 0.01, 0.01]),
                           sharpness=400.0, amplitude=0.005)
    else:
        raise ValueError(f"unknown planted kind {kind!r}")
    return Problem(system, net, BASE_LAM, np.eye(2))
