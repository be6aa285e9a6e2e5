"""Error bounds from a certified rate: Theorem 3 as stated, the ISS bound, its metric variant.

METHOD §3.6-3.7. Inputs are the *proved* numbers of the other checks: `lam_cert` (a proved
lower bound on the contraction rate with metric P, in the convention D = He{P (Jf + dk/dxhat)}
+ 2 lam P, so the error contracts at rate 2 lam in the P-norm), `eps_bar` (a sound upper bound
on the boundary-condition residual over X) and `L` (a sound Lipschitz bound of k in y).
Nothing here is sampled: a bound is applicable only when every input is a finite sound
number, and its conditions of validity (a)-(d) are stated beside it in words.

Status words: PROVED (a bound holds); NOT APPLICABLE when lam_cert <= 0 (no contraction, so
no bound exists at all); UNKNOWN when an input is not finite or not a valid bound; SKIPPED
when an input was not established. A proved ultimate bound larger than half the diagonal of
X is true but says little: the result is marked `vacuous` and its message says "valid but
vacuous: larger than the box".

Bounds, with e = x - xhat, W = ||P^(1/2) e||, c = ||P^(1/2)||_2 (eps_bar + L vbar):

- theorem3 (P = I, lam > 2, eta = lam - 2):
  ||e(t)|| <= ||e0|| e^(-eta t) + eps_bar / (2 sqrt(eta)) + L vbar / (2 sqrt(eta))
- iss:  ||e(t)|| <= (e^(-2 lam t) W0 + (1 - e^(-2 lam t)) c / (2 lam)) / sqrt(lam_min(P))
- iss_metric: the same with c replaced by eps_bar_P + L_P vbar (residual and Lipschitz
  constant of P^(1/2) k), which is never larger when those are computed directly.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context
from certify.errors import SettingsError
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity, error_headline
from certify.results import BoundResult, BoundsResult, DissipationResult, Status

#: Names accepted by `bound_curve`.
BOUND_NAMES = ("theorem3", "iss", "iss_metric", "dissipation")
#: The headline bound is the best ultimate bound times this margin, reached at `settle_time`
#: from the worst start in X (the bound approaches its ultimate value only as t -> infinity).
HEADLINE_MARGIN = 1.1

# Relative outward nudge on every computed constant: the formulas are a handful of float64
# operations (relative error a few ulp); 1e-12 covers them with a wide margin.
_NUDGE = 1e-12


def _up(value: float) -> float:
    return value * (1.0 + _NUDGE) if value >= 0 else value * (1.0 - _NUDGE)


def _describe_missing(name: str, value: float | None, what: str) -> str | None:
    """A reason why `value` cannot enter a bound, or None when it is a finite number >= 0."""
    if value is None:
        return f"{name} was not established ({what} has no sound value)"
    if not math.isfinite(value):
        return f"{name} = {value} is not finite"
    if value < 0:
        return f"{name} = {value:.6g} < 0 is not a valid upper bound"
    return None


def metric_constants(P: np.ndarray) -> tuple[float, float, float]:
    """(lam_min(P) rounded down, ||P^(1/2)||_2 rounded up, kappa(P) rounded up).

    eigvalsh errs by about n u ||P||; the margin below covers it, so the bound stays sound.
    """
    P = np.asarray(P, dtype=np.float64)
    eig = np.linalg.eigvalsh((P + P.T) / 2)
    margin = 4.0 * P.shape[0] * np.finfo(np.float64).eps * float(np.abs(eig).max())
    lo, hi = float(eig[0]) - margin, float(eig[-1]) + margin
    if lo <= 0:
        return float("nan"), float("nan"), float("inf")
    return lo, _up(math.sqrt(hi)), _up(hi / lo)


def _is_identity(P: np.ndarray) -> bool:
    P = np.asarray(P, dtype=np.float64)
    return bool(np.array_equal(P, np.eye(P.shape[0])))


def _not_applicable(name: str, formula: str, reason: str) -> BoundResult:
    return BoundResult(name=name, applicable=False, reason=reason, rate=None, gain=None,
                       bias=None, bias_per_unit_noise=None, formula=formula)


def _theorem3(P: np.ndarray, lam: float | None, eps: float | None, L: float | None,
              vbar: float, common: list[str]) -> BoundResult:
    name = "theorem3"
    formula = ("||e(t)|| <= ||e0|| e^(-eta t) + eps_bar/(2 sqrt(eta)) + L vbar/(2 sqrt(eta)), "
               "eta = lam_cert - 2 (source, Theorem 3, P = I)")

    def no(reason: str) -> BoundResult:
        return _not_applicable(name, formula, reason)

    if common:
        return no("; ".join(common))
    assert lam is not None and eps is not None and L is not None
    if not _is_identity(P):
        return no("Theorem 3 of the source is stated for P = I only; this problem uses a "
                  "different metric P (use the ISS bound)")
    if not lam > 2.0:
        return no(f"lam_cert = {lam:.6g} <= 2: Theorem 3 needs lam > 2 (eta = lam - 2 > 0); "
                  "the ISS bound needs only lam > 0")
    eta = lam - 2.0
    denom = 2.0 * math.sqrt(eta)
    bias = _up((eps + L * vbar) / denom)
    return BoundResult(
        name=name, applicable=True,
        reason=f"P = I and lam_cert = {lam:.6g} > 2 (eta = {eta:.6g})",
        rate=eta, gain=1.0, bias=bias, bias_per_unit_noise=_up(L / denom), formula=formula)


def _iss(name: str, lam: float | None, c0: float | None, c1: float | None, vbar: float,
         lam_min: float, common: list[str], what: str, formula: str) -> BoundResult:
    """ISS bound with W' <= -2 lam W + c0 + c1 vbar; ||e|| <= W / sqrt(lam_min(P))."""

    def no(reason: str) -> BoundResult:
        return _not_applicable(name, formula, reason)

    if common:
        return no("; ".join(common))
    assert lam is not None and c0 is not None and c1 is not None
    if not lam_min > 0:
        return no("the metric P is not numerically positive definite")
    s = math.sqrt(lam_min)
    s = s * (1.0 - _NUDGE)  # sqrt rounded down, so 1/s is rounded up
    bias = _up((c0 + c1 * vbar) / (2.0 * lam) / s)
    return BoundResult(
        name=name, applicable=True,
        reason=f"lam_cert = {lam:.6g} > 0 with sound {what}",
        rate=2.0 * lam, gain=_up(1.0 / s), bias=bias,
        bias_per_unit_noise=_up(c1 / (2.0 * lam) / s), formula=formula)


def validity_conditions(problem: Problem, *, vbar: float, L_is_local: bool,
                        c: float | None = None, lam: float | None = None) -> list[str]:
    """Conditions (a)-(d) of METHOD §3.7, in words, with the boxes of this problem."""
    sysm = problem.system
    X = ", ".join(f"{s} in [{lo:g}, {hi:g}]" for s, (lo, hi) in zip(sysm.states, sysm.X))
    Y = ", ".join(f"{s} in [{lo:g}, {hi:g}]" for s, (lo, hi) in zip(sysm.outputs, sysm.Y))
    radius = ""
    if c is not None and lam is not None and lam > 0:
        radius = (f" A checkable form: if x(s) stays in a set K and the P-ellipsoid "
                  f"{{z : ||P^(1/2)(z - x)|| <= max(W(0), c/(2 lam))}} (c/(2 lam) = "
                  f"{c / (2 * lam):.4g}) lies inside X for every x in K, then xhat stays in X.")
    cond = [
        f"(a) X is a box (convex) and both the plant state x(s) and the observer state "
        f"xhat(s) stay in X = {{{X}}} for all s in [0, t]; the bound holds only up to the "
        f"first exit (forward invariance, the source's Assumption 1, is not implied and is "
        f"checked by simulation).{radius}",
        f"(b) the true output h(x(s)) stays in Y = {{{Y}}} for all s in [0, t].",
        f"(c) the measurement noise is bounded: ||v(s)||_2 <= vbar = {vbar:g} for all s in "
        f"[0, t] (Euclidean norm in R^{sysm.p}); Gaussian white noise has no such bound, so "
        f"the bounds do not apply to it.",
    ]
    if L_is_local:
        cond.append("(d) the measured output y_e(s) = h(x(s)) + v(s) stays in Y for all s in "
                    "[0, t], because L is a local bound (sup ||dk/dy||_2 over X x Y) and "
                    "holds only for y in Y.")
    else:
        cond.append("(d) not needed: L is a global bound (LipSDP holds for every xhat in R^n "
                    "and y in R^p), so y_e = h(x) + v may leave Y.")
    return cond


def _dissipation_bound(d: DissipationResult | None, vbar: float, lam_min: float
                       ) -> BoundResult | None:
    """The bound of a proved dissipation inequality V' <= -alpha V + mu ||v||^2
    (+ mu_r ||P^(1/2) r||^2): V(t) <= e^(-alpha t) V(0) + (1 - e^(-alpha t)) V_inf with
    V_inf = (mu vbar^2 + mu_r eps_bar_P^2) / alpha, and ||e|| <= sqrt(V / lam_min(P))."""
    if d is None:
        return None
    formula = ("||e(t)|| <= sqrt((e^(-alpha t) W0^2 + (1 - e^(-alpha t)) (mu vbar^2 + mu_r "
               "eps_bar_P^2)/alpha) / lam_min(P)), W0 = ||P^(1/2) e0|| (joint dissipation "
               "certificate in [e; v])")
    if d.status != Status.PROVED or d.alpha is None or d.mu is None:
        return _not_applicable("dissipation", formula, f"not proved ({d.message})")
    if not lam_min > 0:
        return _not_applicable("dissipation", formula, "P is not numerically positive definite")
    noise = _up(_up(d.mu * vbar) * vbar)
    if d.mu_residual:
        eps = d.eps_bar if d.eps_bar is not None else math.inf
        noise = _up(noise + _up(_up(d.mu_residual * eps) * eps))
    s = math.sqrt(lam_min) * (1.0 - _NUDGE)
    w_inf = _up(math.sqrt(_up(noise / (d.alpha * (1.0 - _NUDGE)))))
    return BoundResult(
        name="dissipation", applicable=math.isfinite(w_inf),
        reason=(f"proved V' <= -{lower_text(d.alpha, 6)} V + {upper_text(d.mu, 6)} ||v||^2"
                + (f" + {upper_text(d.mu_residual, 6)} eps_bar_P^2" if d.mu_residual else "")
                + " over X x Y (valid while y + v stays in Y)"),
        rate=float(d.alpha), gain=_up(1.0 / s), bias=_up(w_inf / s),
        bias_per_unit_noise=_up(math.sqrt(_up(d.mu / d.alpha)) / s), formula=formula)


def inverse_diagonal_upper(P: np.ndarray) -> np.ndarray:
    """Sound upper bounds on the diagonal of P^-1 [n] (P symmetric positive definite).

    With X ~ P^-1 from a solve and R = P X - I evaluated with an error bound, P^-1 = X -
    P^-1 R, so (P^-1)_ii <= X_ii + ||R e_i|| / lam_min(P) (rounded up, lam_min rounded down
    by `metric_constants`)."""
    P = np.asarray(P, dtype=np.float64)
    n = P.shape[0]
    lam_min = metric_constants(P)[0]
    if not lam_min > 0:
        return np.full(n, np.inf)
    X = np.linalg.solve(P, np.eye(n))
    R = P @ X - np.eye(n)
    eps = np.finfo(np.float64).eps
    err = (n + 2) * eps * (np.abs(P) @ np.abs(X) + 1.0)  # |fl(R) - R| elementwise, widened
    col = np.sqrt(((np.abs(R) + err) ** 2).sum(0)) * (1 + 4 * eps)
    return np.array([_up(_up(X[i, i]) + _up(col[i] / lam_min)) for i in range(n)])


def worst_start(bound: BoundResult, P: np.ndarray, X: np.ndarray) -> float:
    """The largest start value of `bound` over starts with x and xhat in the box X [n, 2]:
    e0 in [-w, w] (w the widths), so ||e0|| <= ||w|| and max e0^T P e0 is attained at a
    vertex of that box (a convex function; 2^(n-1) sign patterns, n <= 16)."""
    w = np.asarray(X, dtype=np.float64)[:, 1] - np.asarray(X, dtype=np.float64)[:, 0]
    if bound.name == "theorem3":
        return _up(float(np.linalg.norm(w)))
    n = w.shape[0]
    if n > 16:
        return _up(float(np.linalg.norm(w)) * math.sqrt(metric_constants(P)[1] ** 2))
    signs = np.array([[1.0] + [1.0 - 2.0 * ((k >> j) & 1) for j in range(n - 1)]
                      for k in range(2 ** (n - 1))])
    v = signs * w
    quad = np.einsum("ki,ij,kj->k", v, np.asarray(P, dtype=np.float64), v)
    return _up(math.sqrt(_up(float(quad.max()))))


def settle_time(bounds: BoundsResult, which: str, start: float, level: float) -> float:
    """The first time t >= 0 after which `bound_curve(bounds, which, start, t)` <= `level`
    (the curves decrease monotonically towards the ultimate value, so one crossing), found
    by bisection to a relative 1e-6 and rounded up; 0 when it starts below."""
    def at(t: float) -> float:
        return float(bound_curve(bounds, which, start, np.array([t]))[0])
    if at(0.0) <= level:
        return 0.0
    hi = 1.0
    while at(hi) > level:
        hi *= 2.0
        if hi > 1e12:
            return math.inf
    lo = 0.0
    while hi - lo > 1e-6 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if at(mid) > level else (lo, mid)
    return hi


def _headline(r: BoundsResult, P: np.ndarray, X: np.ndarray) -> None:
    """Fill `best`, `ultimate`, `headline`, `settle_time` and `per_component` of `r` from its
    applicable bound with the smallest ultimate value (in place)."""
    applicable = [b for b in r.bounds() if b.applicable and b.bias is not None]
    if not applicable:
        return
    best = min(applicable, key=lambda b: float(b.bias))  # type: ignore[arg-type]
    r.best, r.ultimate = best.name, float(best.bias)  # type: ignore[arg-type]
    r.headline = _up(HEADLINE_MARGIN * r.ultimate)
    t_settle = settle_time(r, best.name, worst_start(best, P, X), r.headline)
    r.settle_time = t_settle if math.isfinite(t_settle) else None  # ultimate 0: only as t -> inf
    if best.name == "theorem3":
        r.per_component = [r.ultimate] * P.shape[0]
    else:  # |e_i| <= W sqrt((P^-1)_ii), W <= bias sqrt(lam_min) <= bias / gain
        w_inf = _up(r.ultimate / float(best.gain) * (1 + _NUDGE))  # type: ignore[arg-type]
        r.per_component = [min(r.ultimate, _up(w_inf * math.sqrt(d)))
                           for d in inverse_diagonal_upper(P)]


def check_bounds(problem: Problem, *, lam_cert: float | None, eps_bar: float | None,
                 L: float | None, vbar: float, eps_bar_P: float | None = None,
                 L_P: float | None = None, L_is_local: bool = False,
                 dissipation: DissipationResult | None = None) -> BoundsResult:
    """Theorem 3 (as stated), the ISS bound and its metric variant at noise level `vbar`.

    All inputs must be sound: `lam_cert` a proved lower bound on the rate (metric
    `problem.P`), `eps_bar`, `L` (and `eps_bar_P`, `L_P`) proved upper bounds. PROVED when the
    ISS bound is applicable; NOT APPLICABLE when lam_cert <= 0 (no bound exists); SKIPPED
    when an input was not established (None); UNKNOWN when one is not finite or negative.
    A proved ultimate bound above half the diagonal of X is flagged `vacuous`.
    """
    if vbar is None or isinstance(vbar, bool) or not math.isfinite(float(vbar)) or vbar < 0:
        raise SettingsError(f"settings noise must be a number >= 0; got {vbar!r}")
    vbar = float(vbar)
    P = np.asarray(problem.P, dtype=np.float64)
    lam_min, sqrtP_norm, kappa = metric_constants(P)

    def as_float(v: float | None) -> float | None:
        return None if v is None else float(v)

    lam, eps, Lf = as_float(lam_cert), as_float(eps_bar), as_float(L)
    epsP, LP = as_float(eps_bar_P), as_float(L_P)

    missing: list[str] = []  # inputs not established (None)
    invalid: list[str] = []  # inputs that exist but cannot give a bound
    if lam is None:
        missing.append("lam_cert was not established (no proved contraction rate)")
    elif not math.isfinite(lam):
        invalid.append(f"lam_cert = {lam} is not finite")
    elif lam <= 0:
        invalid.append(f"lam_cert = {lam:.6g} <= 0: no contraction was certified, so no bound "
                       "exists")
    no_rate = lam is not None and math.isfinite(lam) and lam <= 0
    for nm, v, what in (("eps_bar", eps, "the residual check"),
                        ("L", Lf, "the Lipschitz check")):
        r = _describe_missing(nm, v, what)
        if r:
            (missing if v is None else invalid).append(r)
    common = invalid + missing

    theorem3 = _theorem3(P, lam, eps, Lf, vbar, common)
    iss_formula = ("||e(t)|| <= (e^(-2 lam t) W0 + (1 - e^(-2 lam t)) ||P^(1/2)||_2 "
                   "(eps_bar + L vbar)/(2 lam)) / sqrt(lam_min(P)), W0 = ||P^(1/2) e0||, "
                   "lam = lam_cert")
    iss = _iss("iss", lam, None if eps is None else _up(sqrtP_norm * eps),
               None if Lf is None else _up(sqrtP_norm * Lf), vbar, lam_min, common,
               "eps_bar and L", iss_formula)

    # the sharper variant: eps_bar_P, L_P; a missing one is replaced by its sound fallback
    # ||P^(1/2)|| eps_bar (resp. ||P^(1/2)|| L) and the reason says so.
    metric_formula = ("||e(t)|| <= (e^(-2 lam t) W0 + (1 - e^(-2 lam t)) (eps_bar_P + L_P "
                      "vbar)/(2 lam)) / sqrt(lam_min(P)), eps_bar_P = sup ||P^(1/2) k(x, h(x))||,"
                      " L_P = Lipschitz constant of P^(1/2) k in y")
    if epsP is None and LP is None:
        iss_metric = BoundResult(
            name="iss_metric", applicable=False,
            reason="eps_bar_P and L_P (the residual and Lipschitz constant of P^(1/2) k) were "
                   "not computed", rate=None, gain=None, bias=None, bias_per_unit_noise=None,
            formula=metric_formula)
    else:
        mcommon = list(common)
        notes = []
        for nm, v in (("eps_bar_P", epsP), ("L_P", LP)):
            if v is not None:
                r = _describe_missing(nm, v, "the metric variant")
                if r:
                    mcommon.append(r)
        if epsP is None and eps is not None:
            epsP = _up(sqrtP_norm * eps)
            notes.append("eps_bar_P <= ||P^(1/2)|| eps_bar")
        if LP is None and Lf is not None:
            LP = _up(sqrtP_norm * Lf)
            notes.append("L_P <= ||P^(1/2)|| L")
        what = "eps_bar_P and L_P" + (f" (using {', '.join(notes)})" if notes else "")
        iss_metric = _iss("iss_metric", lam, epsP, LP, vbar, lam_min, mcommon, what,
                          metric_formula)

    c = None
    if iss.applicable:
        c = sqrtP_norm * (eps + Lf * vbar)  # type: ignore[operator]
    validity = validity_conditions(problem, vbar=vbar, L_is_local=L_is_local, c=c, lam=lam)
    joint = _dissipation_bound(dissipation, vbar, lam_min)

    half_diagonal = box_half_diagonal(problem)
    r = BoundsResult(status=Status.SKIPPED, message="", vbar=vbar, lam_cert=lam, eps_bar=eps,
                     L=Lf, theorem3=theorem3, iss=iss, iss_metric=iss_metric,
                     validity=validity, kappa_P=kappa, L_is_local=bool(L_is_local),
                     box_half_diagonal=half_diagonal, dissipation=joint)
    applicable = [b for b in r.bounds() if b.applicable]
    if applicable:
        _headline(r, P, np.asarray(problem.system.X, dtype=np.float64))
        assert r.ultimate is not None and r.headline is not None
        r.vacuous = r.headline > half_diagonal  # what the headline says, not its limit
        t3 = (f"applicable, ultimate bound {upper_text(theorem3.bias, 4)}"
              if theorem3.applicable else f"not applicable ({theorem3.reason})")
        size = (f"valid but vacuous: larger than the box, whose half-diagonal is "
                f"{half_diagonal:.4g}"
                if r.vacuous else f"useful: the box's half-diagonal is {half_diagonal:.4g}")
        # bounds rounded up (the text never claims more than was proved), the headline's
        # numbers as the headline itself prints them (`error_headline`)
        parts = ", ".join(f"{b.name} {upper_text(b.bias, 4)}" for b in applicable)
        r.status = Status.PROVED
        when = ("as t -> infinity" if r.settle_time is None
                else f"after t >= {upper_text(r.settle_time, 2)} s")
        limits = ", ".join(upper_text(v) for v in r.per_component or [])
        r.message = (f"||e|| <= {upper_text(r.headline)} for noise <= {vbar:g} {when} "
                     f"({size}); ultimate bounds (t -> infinity): {parts}"
                     + (f", per component |e_i| <= {limits}" if limits else "")
                     + f"; Theorem 3 as stated: {t3}. Valid only under conditions (a)-(d).")
    elif no_rate and not [x for x in invalid if not x.startswith("lam_cert")]:
        r.status = Status.NOT_APPLICABLE
        r.message = "no error bound exists: " + "; ".join(common)
    else:
        r.status = Status.UNKNOWN if invalid else Status.SKIPPED
        r.message = "no error bound: " + "; ".join(common)
    return r


def box_half_diagonal(problem: Problem) -> float:
    """Half the Euclidean diagonal of X: the largest ||x - c|| over X from its centre."""
    X = np.asarray(problem.system.X, dtype=np.float64)
    return float(0.5 * np.linalg.norm(X[:, 1] - X[:, 0]))


def initial_value(which: str, e0: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The start value a bound multiplies: ||e0|| (theorem3) or W0 = ||P^(1/2) e0|| (ISS).

    e0 has shape [n] or [R, n]; returns a scalar array or shape [R].
    """
    e0 = np.asarray(e0, dtype=np.float64)
    if which == "theorem3":
        return np.linalg.norm(e0, axis=-1)
    if which not in BOUND_NAMES:
        raise ValueError(f"unknown bound {which!r}; one of {BOUND_NAMES}")
    quad = np.einsum("...i,ij,...j->...", e0, np.asarray(P, dtype=np.float64), e0)
    return np.sqrt(np.maximum(quad, 0.0)) * (1.0 + _NUDGE)


def bound_curve(bounds: BoundsResult, which: str, start: float | np.ndarray,
                t: np.ndarray) -> np.ndarray:
    """The bound on ||e(t)|| over times t [T] for start values [R] (or a scalar) -> [R, T] or [T].

    `start` is ||e0|| for "theorem3" and W0 = ||P^(1/2) e0|| for "iss"/"iss_metric" (see
    `initial_value`). Raises ValueError when that bound is not applicable.
    """
    if which not in BOUND_NAMES:
        raise ValueError(f"unknown bound {which!r}; one of {BOUND_NAMES}")
    b: BoundResult | None = getattr(bounds, which)
    if b is None or not b.applicable:
        raise ValueError(f"bound {which} is not applicable: "
                         f"{b.reason if b is not None else 'not computed'}")
    t = np.asarray(t, dtype=np.float64)
    s = np.asarray(start, dtype=np.float64)
    decay = np.exp(-b.rate * t)  # type: ignore[operator]
    s_ = s[..., None] if s.ndim else s
    if which == "theorem3":
        return b.gain * s_ * decay + b.bias  # type: ignore[operator]
    if which == "dissipation":  # V(t) <= e^(-alpha t) V0 + (1 - e^(-alpha t)) V_inf
        w_inf = b.bias / b.gain  # type: ignore[operator]
        return b.gain * np.sqrt(s_ * s_ * decay + (1.0 - decay) * w_inf * w_inf)  # type: ignore
    return b.gain * s_ * decay + (1.0 - decay) * b.bias  # type: ignore[operator]


def ultimate_bound_per_unit_noise(*, lam_cert: float | None, eps_bar: float | None,
                                  L: float | None, vbar: float, kappa_P: float = 1.0
                                  ) -> float | None:
    """sqrt(kappa(P)) (eps_bar + L vbar) / (2 lam_cert): the ISS ultimate bound at `vbar`.

    The quantity of `bench/compare.py`'s older table, evaluated at the given vbar (not
    divided by it). None when it does not exist (lam_cert <= 0 or an input missing/non-finite).
    """
    vals = (lam_cert, eps_bar, L, vbar, kappa_P)
    if any(v is None or not math.isfinite(float(v)) for v in vals):
        return None
    if lam_cert <= 0 or eps_bar < 0 or L < 0 or vbar < 0 or kappa_P < 1:  # type: ignore[operator]
        return None
    return _up(math.sqrt(kappa_P) * (eps_bar + L * vbar) / (2.0 * lam_cert))  # type: ignore[operator]


# ----------------------------------------------------------------------------- check protocol

def _bias_quantity(label: str, b: BoundResult | None, r: BoundsResult) -> Quantity:
    """A bound's ultimate value as a report side: vacuous when larger than the box."""
    if b is None:
        return Quantity(label, None, "not computed")
    if not b.applicable:
        return Quantity(label, None, "no bound exists" if r.status == Status.NOT_APPLICABLE
                        else "not applicable")
    big = r.box_half_diagonal is not None and float(b.bias or 0.0) > r.box_half_diagonal
    return Quantity(label, b.bias, suffix=" (vacuous: larger than the box)" if big else "",
                    bound="upper")


class BoundsCheck(Check):
    """Theorem 3 as stated and the ISS bounds, from the proved rate, residual and L."""

    name = "bounds"
    title = "Error bounds (Theorem 3, ISS)"
    result_type = BoundsResult
    reads = ("noise",)
    uses = ("rate", "residual", "lipschitz", "dissipation")

    def run(self, context: Context) -> BoundsResult:
        rate, res, lip, joint = (context.result(n) for n in
                                 ("rate", "residual", "lipschitz", "dissipation"))
        lam_cert = None
        if rate is not None:  # a witnessed rate <= 0 (VIOLATED) rules a bound out; else proof
            violated = rate.status == Status.VIOLATED and rate.sampled_upper <= 0
            lam_cert = rate.sampled_upper if violated else rate.proved_lower
            if not violated and lam_cert is not None and lam_cert <= 0:
                lam_cert = None  # a proved lower bound <= 0 is no rate, but not "none exists"
        eps_bar_P = None
        if res is not None:  # sup ||P^(1/2) k(x, h(x))||: 0 by design for structural gains
            eps_bar_P = 0.0 if res.structural else res.upper_P
        L_P = lip.L_P if lip is not None else None
        # condition (d) (y + v in Y) is needed by every bound built on a local constant
        local = lip is not None and (lip.which == "local" or lip.L_P_which == "local")
        return check_bounds(
            context.problem, lam_cert=lam_cert, eps_bar=res.upper if res is not None else None,
            L=lip.value if lip is not None else None, vbar=context.settings.noise,
            eps_bar_P=eps_bar_P, L_P=L_P, L_is_local=bool(local),
            dissipation=joint)

    def present(self, r: BoundsResult, certificate: Any) -> Presentation:
        """The proved side is the headline bound (||e|| after t >= settle_time, from the best
        bound); a vacuous one carries the qualifier "vacuous" wherever its status is shown."""
        head = error_headline(r, (getattr(certificate, "system", None) or {}).get("states"))
        numbers = [Quantity("vbar", r.vbar, sig=6),
                   Quantity("lam_cert", r.lam_cert, sig=6, bound="lower"),
                   Quantity("eps_bar", r.eps_bar, sig=6, bound="upper"),
                   Quantity("L", r.L, sig=6, bound="upper"),
                   Quantity("box half-diagonal", r.box_half_diagonal, sig=6),
                   Quantity("vacuous (larger than the box)", r.vacuous)]
        if head.proved:
            numbers += [Quantity("error bound", head.sentence(unicode=False)),
                        Quantity("error bound per component",
                                 head.components_text(unicode=False) or None, "not computed"),
                        Quantity("error bound size", head.size_text()),
                        Quantity("best bound", r.best or head.source),
                        Quantity("headline bound", r.headline, sig=6, bound="upper"),
                        Quantity("settle time", r.settle_time, sig=6, bound="upper"),
                        Quantity("ultimate bound", r.ultimate, sig=6, bound="upper")]
        else:
            numbers.append(Quantity("error bound", head.reason))
        for b in r.bounds():
            if b.applicable:
                numbers += [Quantity(f"{b.name} bias", b.bias, sig=6, bound="upper"),
                            Quantity(f"{b.name} rate", b.rate, sig=6, bound="lower"),
                            Quantity(f"{b.name} gain", b.gain, sig=6, bound="upper")]
            else:
                numbers.append(Quantity(b.name, f"not applicable: {b.reason}"))
        if head.proved and r.headline is not None:
            after = ("" if r.settle_time is None
                     else f"after t \u2265 {upper_text(r.settle_time, 2)} s; ")
            proved = Quantity(f"\u2016e\u2016 bound ({r.best})", upper_text(r.headline),
                              suffix=f" ({after}{head.size_word()})")
        else:
            best = min((b for b in r.bounds() if b.applicable and b.bias is not None),
                       key=lambda b: float(b.bias), default=None)  # type: ignore[arg-type]
            proved = _bias_quantity(f"ultimate bound ({best.name if best else 'ISS'})",
                                    best or r.iss, r)
        facts = [Quantity("Status", r.status.value)]
        if head.proved:
            facts += [Quantity("Error bound", head.sentence()),
                      Quantity("Per component", head.components_text() or None,
                               "not computed"),
                      Quantity("Size", head.size_text()),
                      Quantity("From", head.source_text())]
        facts += [Quantity("Noise level v\u0304", r.vbar),
                  Quantity("\u03bb_cert used", r.lam_cert, "none: no bound", bound="lower"),
                  Quantity("\u03b5\u0304 used", r.eps_bar, bound="upper"),
                  Quantity("L used", r.L, bound="upper"),
                  Quantity("cond(P)", r.kappa_P, bound="upper"),
                  Quantity("Half-diagonal of X", r.box_half_diagonal, "not recorded")]
        if not head.proved:
            facts.append(Quantity("Error bound", None, head.reason))
        return Presentation(
            sampled=_bias_quantity("Theorem 3 (as stated): ultimate bias", r.theorem3, r),
            proved=proved,
            setting=(Quantity("v\u0304 =", r.vbar),
                     Quantity("\u03bb_cert used:", r.lam_cert, "none", bound="lower")),
            numbers=tuple(numbers), facts=tuple(facts),
            qualifier="vacuous" if head.proved and r.vacuous else "")


CHECK = BoundsCheck()
