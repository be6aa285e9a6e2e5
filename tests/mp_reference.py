"""An independent reference for the property tests: random small specs built as text AND as
mpmath closures, random tanh networks, and lam_max(D) at a point in 40-digit arithmetic.

Nothing here uses certify's parser, kernels or interval code: f is evaluated from closures
written beside the text, Jf by mpmath's numerical differentiation at 40 digits, the network
and its Jacobian by hand in mpmath, and the eigenvalues by mpmath's symmetric eigensolver.
Every float constant (coefficients, weights, P, lam, points) is a double and enters mpmath
exactly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mpmath
import numpy as np
import torch

from certify.model.network import GainNetwork

mp = mpmath.mp
DIGITS = 40

Closure = Callable[[Sequence[mpmath.mpf]], mpmath.mpf]


@dataclass
class RandomSpec:
    """A spec's TOML text and the matching closures of f (h_k = x_k, k < p)."""

    text: str
    f: list[Closure]
    n: int
    p: int
    X: np.ndarray
    P: np.ndarray
    lam: float
    defined: bool  # False: a term is undefined somewhere on X (the spec must be refused)


def _term(rng: np.random.Generator, n: int, X: np.ndarray, allow_undefined: bool
          ) -> tuple[str, Closure, bool]:
    """One small nonlinear term c * g(x_j [, x_k]) as text and closure."""
    j, k = int(rng.integers(n)), int(rng.integers(n))
    c = float(np.round(rng.uniform(-0.3, 0.3), 3))
    lo, hi = float(X[j, 0]), float(X[j, 1])
    shift = float(np.round(0.5 - lo, 3))  # x_j + shift >= 0.5 on the box
    kind = rng.choice(["poly", "sin", "cos", "tanh", "exp", "log", "sqrt", "tan", "abs+",
                       "abs-", "div"])
    xs, xk = f"x{j + 1}", f"x{k + 1}"
    defined = True
    if allow_undefined and rng.random() < 0.5:
        kind, defined = rng.choice(["log0", "sqrt0", "div0", "abs0"]), False
    table: dict[str, tuple[str, Closure]] = {
        "poly": (f"{c}*{xs}*{xk}", lambda x: c * x[j] * x[k]),
        "sin": (f"{c}*sin({xs})", lambda x: c * mpmath.sin(x[j])),
        "cos": (f"{c}*cos({xs} + {xk})", lambda x: c * mpmath.cos(x[j] + x[k])),
        "tanh": (f"{c}*tanh(2*{xs})", lambda x: c * mpmath.tanh(2 * x[j])),
        "exp": (f"{c}*exp(0.5*{xs})", lambda x: c * mpmath.exp(x[j] / 2)),
        "log": (f"{c}*log({xs} + {shift})", lambda x: c * mpmath.log(x[j] + mpmath.mpf(shift))),
        "sqrt": (f"{c}*sqrt({xs} + {shift})",
                 lambda x: c * mpmath.sqrt(x[j] + mpmath.mpf(shift))),
        "tan": (f"{c}*tan(0.25*{xs})", lambda x: c * mpmath.tan(x[j] / 4)),
        "abs+": (f"{c}*abs({xs} + {shift})", lambda x: c * abs(x[j] + mpmath.mpf(shift))),
        "abs-": (f"{c}*abs({xs} - {float(np.round(hi + 0.5, 3))})",
                 lambda x: c * abs(x[j] - mpmath.mpf(float(np.round(hi + 0.5, 3))))),
        "div": (f"{c}/({xs} + {shift})", lambda x: c / (x[j] + mpmath.mpf(shift))),
        "log0": (f"{c}*log({xs} - {lo})", lambda x: c * mpmath.log(x[j] - lo)),
        "sqrt0": (f"{c}*sqrt({xs} - {lo})", lambda x: c * mpmath.sqrt(x[j] - lo)),
        "div0": (f"{c}*{xs}/({xs} - {0.5 * (lo + hi)})", lambda x: c),
        "abs0": (f"{c}*abs({xs} - {0.5 * (lo + hi)})", lambda x: c),
    }
    text, fn = table[str(kind)]
    return text, fn, defined


def random_spec(rng: np.random.Generator, n: int, p: int, cond_exp: float,
                allow_undefined: bool = False) -> RandomSpec:
    """A contracting-ish spec: f_i = -a_i x_i + a small nonlinear term, h = (x_1..x_p)."""
    lo = np.round(rng.uniform(-2.0, 1.0, n), 3)
    X = np.stack([lo, lo + np.round(rng.uniform(0.25, 2.0, n), 3)], axis=1)
    f_text, f_fns, defined = [], [], True
    for i in range(n):
        a = float(np.round(rng.uniform(0.5, 4.0), 3))
        text, fn, ok = _term(rng, n, X, allow_undefined and i == 0)
        defined &= ok
        f_text.append(f"-{a}*x{i + 1} + {text}")
        f_fns.append(lambda x, a=a, fn=fn, i=i: -a * x[i] + fn(x))
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P = (Q * np.logspace(0, cond_exp, n)) @ Q.T
    P = np.round(0.5 * (P + P.T), 12)
    P = 0.5 * (P + P.T)
    lam = float(np.round(rng.uniform(0.01, 0.6), 3))
    Y = X[:p] + np.array([-0.1, 0.1])
    names = [f"x{i + 1}" for i in range(n)]
    text = "\n".join([
        'name = "random"',
        "states = [" + ", ".join(f'"{s}"' for s in names) + "]",
        "outputs = [" + ", ".join(f'"y{k + 1}"' for k in range(p)) + "]",
        "f = [" + ", ".join(f'"{t}"' for t in f_text) + "]",
        "h = [" + ", ".join(f'"x{k + 1}"' for k in range(p)) + "]",
        "[box]",
        "X = " + repr([[float(a), float(b)] for a, b in X]),
        "Y = " + repr([[float(a), float(b)] for a, b in Y]),
        "[design]",
        f"lam = {lam!r}",
        "P = " + repr([[float(v) for v in row] for row in P]),
    ])
    return RandomSpec(text, f_fns, n, p, X, P, lam, defined)


def _mat(A: np.ndarray) -> mpmath.matrix:
    return mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in np.atleast_2d(A)])


def network(layers: Sequence[tuple[np.ndarray, np.ndarray]], z: Sequence[float]
            ) -> tuple[mpmath.matrix, mpmath.matrix]:
    """k(z) and dk/dz of the direct tanh MLP k(z) = W_L tanh(... tanh(W_0 z + b_0) ...) + b_L."""
    a = mpmath.matrix([mpmath.mpf(float(v)) for v in z])
    J = mpmath.eye(len(z))
    for W, b in layers[:-1]:
        pre = _mat(W) * a + _mat(b[:, None])
        t = [mpmath.tanh(pre[i]) for i in range(pre.rows)]
        a = mpmath.matrix(t)
        D = mpmath.diag([1 - ti * ti for ti in t])
        J = D * _mat(W) * J
    W, b = layers[-1]
    return _mat(W) * a + _mat(b[:, None]), _mat(W) * J


def network_jacobian_x(layers: Sequence[tuple[np.ndarray, np.ndarray]], z: Sequence[float],
                       n: int) -> mpmath.matrix:
    """dk/dxhat of the direct tanh MLP."""
    J = network(layers, z)[1]
    return J[:, :n]


def dk_dy_norm(layers, z: Sequence[float], n: int) -> mpmath.mpf:
    """||dk/dy||_2 at z (largest singular value, 40 digits)."""
    with mpmath.workdps(DIGITS):
        J = network(layers, z)[1]
        Jy = J[:, n:]
        return max(mpmath.svd_r(Jy, compute_uv=False))


def residual_norm(layers, x: Sequence[float], p: int) -> mpmath.mpf:
    """||k(x, h(x))||_2 with h(x) = (x_1..x_p), 40 digits."""
    with mpmath.workdps(DIGITS):
        k = network(layers, [*x, *x[:p]])[0]
        return mpmath.sqrt(sum(k[i] ** 2 for i in range(k.rows)))


def exact_lam_max(S: np.ndarray, digits: int = 50) -> mpmath.mpf:
    """lam_max of the symmetric matrix given by S's lower triangle (a double array), at
    `digits` digits (mpmath's symmetric eigensolver)."""
    with mpmath.workdps(digits):
        n = S.shape[0]
        M = mpmath.matrix(n, n)
        for i in range(n):
            for j in range(n):
                M[i, j] = mpmath.mpf(float(S[max(i, j), min(i, j)]))
        return max(mpmath.eigsy(M, eigvals_only=True))


def jacobian_f(spec: RandomSpec, x: Sequence[float]) -> mpmath.matrix:
    xs = [mpmath.mpf(float(v)) for v in x]
    J = mpmath.matrix(spec.n, spec.n)
    for i in range(spec.n):
        for j in range(spec.n):
            def along(t, i=i, j=j):
                y = list(xs)
                y[j] = t
                return spec.f[i](y)
            J[i, j] = mpmath.diff(along, xs[j])
    return J


def lam_max_D(spec: RandomSpec, layers, xhat: Sequence[float], y: Sequence[float],
              lam: float | None = None) -> mpmath.mpf:
    """lam_max(He{P (Jf + dk/dxhat)} + 2 lam P) at (xhat, y), 40 digits."""
    with mpmath.workdps(DIGITS):
        J = jacobian_f(spec, xhat) + network_jacobian_x(layers, [*xhat, *y], spec.n)
        P = _mat(spec.P)
        PJ = P * J
        lam_v = mpmath.mpf(spec.lam if lam is None else lam)
        D = (PJ + PJ.T) / 2 + 2 * lam_v * P
        return max(mpmath.eigsy(D, eigvals_only=True))


def manifold_q(spec: RandomSpec, xhat: Sequence[float]) -> mpmath.mpf:
    """q = lam_max of S = He{P Jf} + 2 lam P on ker C, C selecting x_1..x_p (exact basis)."""
    with mpmath.workdps(DIGITS):
        J = jacobian_f(spec, xhat)
        P = _mat(spec.P)
        PJ = P * J
        S = (PJ + PJ.T) / 2 + 2 * mpmath.mpf(spec.lam) * P
        idx = list(range(spec.p, spec.n))
        sub = mpmath.matrix([[S[i, j] for j in idx] for i in idx])
        return max(mpmath.eigsy(sub, eigvals_only=True))


def random_network(rng: np.random.Generator, n: int, p: int, kind: str) -> GainNetwork:
    """A direct tanh MLP (1-2 hidden layers of 2-4): small, exactly-zero-layer, saturated
    (first layer x200) or large weights; float64."""
    hidden = tuple(int(w) for w in rng.integers(2, 5, size=int(rng.integers(1, 3))))
    net = GainNetwork(n, p, hidden).double()
    scale = {"small": 0.05, "zero": 0.5, "saturated": 0.05, "large": 1.5}[kind]
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.copy_(torch.as_tensor(rng.normal(0, scale, layer.weight.shape)))
            layer.bias.copy_(torch.as_tensor(rng.normal(0, scale, layer.bias.shape)))
        if kind == "zero":  # an exactly zero layer somewhere
            i = int(rng.integers(len(net.layers)))
            net.layers[i].weight.zero_()
        if kind == "saturated":
            net.layers[0].weight.mul_(200.0)
    return net


def network_layers(net: GainNetwork) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(W, b)] of every layer as float64 numpy arrays (for `lam_max_D`)."""
    return [(W.detach().numpy(), b.detach().numpy()) for W, b in net.weights()]
