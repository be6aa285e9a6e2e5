"""The error bounds from proved constants: formulas, curves, headline, validity conditions.

The mathematics behind the `bounds` check (`certify.checks.bounds`), in one place for every
consumer (the check, the simulation that compares runs with a bound, the reports through the
certificate). Inputs are *proved* numbers: `lam_cert` (a proved lower bound on the contraction
rate with metric P, in the convention D = He{P (Jf + dk/dxhat)} + 2 lam P, so the error
contracts at rate 2 lam in the P-norm), `eps_bar` (a sound upper bound on the
boundary-condition residual over X), `L` (a sound Lipschitz bound of k in y) and a proved
dissipation inequality. Nothing here is sampled: a bound is applicable only when every input
is a finite sound number and its ultimate value is a finite float (a noise level so large
that it overflows gives no bound, never an infinite one).

Bounds, with e = x - xhat, W = ||P^(1/2) e||, c = ||P^(1/2)||_2 (eps_bar + L vbar):

- theorem3 (P = I, lam > 2, eta = lam - 2):
  ||e(t)|| <= ||e0|| e^(-eta t) + eps_bar / (2 sqrt(eta)) + L vbar / (2 sqrt(eta))
- iss:  ||e(t)|| <= (e^(-2 lam t) W0 + (1 - e^(-2 lam t)) c / (2 lam)) / sqrt(lam_min(P))
- iss_metric: the same with c replaced by eps_bar_P + L_P vbar (residual and Lipschitz
  constant of P^(1/2) k), which is never larger when those are computed directly.
- dissipation: V' <= -alpha V + mu ||v||^2 (+ mu_r ||P^(1/2) r||^2) with V = e^T P e
  (`certify.prove.dissipation`): V(t) <= e^(-alpha t) V0 + (1 - e^(-alpha t)) V_inf.

The headline is the best ultimate value times HEADLINE_MARGIN and the time after which every
start in X is below it; an ultimate value of 0 (no noise, no residual) is reached only as
t -> infinity, and the headline says so instead of naming a time.

The validity region (`validity_region`) turns conditions (a)-(b) from assumptions into
proved facts for a set of starts: the plant in a region R proved forward invariant
(`certify.prove.invariance`) and an initial error small enough that xhat never leaves X.
"""

from __future__ import annotations

import math

import numpy as np

from certify.arith.text import lower_text, upper_text
from certify.model.problem import Problem
from certify.results import (
    BoundResult,
    BoundsResult,
    DissipationResult,
    InvarianceResult,
    MetricBoundResult,
    Status,
)

#: Names accepted by `bound_curve`.
BOUND_NAMES = ("theorem3", "iss", "iss_metric", "dissipation", "metric")


#: The headline bound is the best ultimate bound times this margin, reached at `settle_time`
#: from the worst start in X (the bound approaches its ultimate value only as t -> infinity).
HEADLINE_MARGIN = 1.1


# Relative outward nudge on every computed constant: the formulas are a handful of float64
# operations (relative error a few ulp); 1e-12 covers them with a wide margin.
NUDGE = 1e-12


def up_rel(value: float) -> float:
    return value * (1.0 + NUDGE) if value >= 0 else value * (1.0 - NUDGE)


def describe_missing(name: str, value: float | None, what: str) -> str | None:
    """A reason why `value` cannot enter a bound, or None when it is a finite number >= 0."""
    if value is None:
        return f"{name} was not established ({what} has no sound value)"
    if not math.isfinite(value):
        return f"{name} = {value} is not finite"
    if value < 0:
        return f"{name} = {value:.6g} < 0 is not a valid upper bound"
    return None


def overflow(vbar: float) -> str:
    """Why a bound whose ultimate value overflows float64 is not given (never as infinite)."""
    return (f"the bound at noise vbar = {vbar:g} exceeds the floating-point range (no finite "
            "number to state)")


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
    return lo, up_rel(math.sqrt(hi)), up_rel(hi / lo)


def _is_identity(P: np.ndarray) -> bool:
    P = np.asarray(P, dtype=np.float64)
    return bool(np.array_equal(P, np.eye(P.shape[0])))


def not_applicable(name: str, formula: str, reason: str) -> BoundResult:
    return BoundResult(name=name, applicable=False, reason=reason, rate=None, gain=None,
                       bias=None, bias_per_unit_noise=None, formula=formula)


def theorem3_bound(P: np.ndarray, lam: float | None, eps: float | None, L: float | None,
              vbar: float, common: list[str]) -> BoundResult:
    name = "theorem3"
    formula = ("||e(t)|| <= ||e0|| e^(-eta t) + eps_bar/(2 sqrt(eta)) + L vbar/(2 sqrt(eta)), "
               "eta = lam_cert - 2 (source, Theorem 3, P = I)")

    def no(reason: str) -> BoundResult:
        return not_applicable(name, formula, reason)

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
    bias = up_rel((eps + L * vbar) / denom)
    if not math.isfinite(bias):
        return no(overflow(vbar))
    return BoundResult(
        name=name, applicable=True,
        reason=f"P = I and lam_cert = {lam:.6g} > 2 (eta = {eta:.6g})",
        rate=eta, gain=1.0, bias=bias, bias_per_unit_noise=up_rel(L / denom), formula=formula)


def iss_bound(name: str, lam: float | None, c0: float | None, c1: float | None, vbar: float,
         lam_min: float, common: list[str], what: str, formula: str) -> BoundResult:
    """ISS bound with W' <= -2 lam W + c0 + c1 vbar; ||e|| <= W / sqrt(lam_min(P))."""

    def no(reason: str) -> BoundResult:
        return not_applicable(name, formula, reason)

    if common:
        return no("; ".join(common))
    assert lam is not None and c0 is not None and c1 is not None
    if not lam_min > 0:
        return no("the metric P is not numerically positive definite")
    s = math.sqrt(lam_min)
    s = s * (1.0 - NUDGE)  # sqrt rounded down, so 1/s is rounded up
    bias = up_rel((c0 + c1 * vbar) / (2.0 * lam) / s)
    if not math.isfinite(bias):
        return no(overflow(vbar))
    return BoundResult(
        name=name, applicable=True,
        reason=f"lam_cert = {lam:.6g} > 0 with sound {what}",
        rate=2.0 * lam, gain=up_rel(1.0 / s), bias=bias,
        bias_per_unit_noise=up_rel(c1 / (2.0 * lam) / s), formula=formula)


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


def dissipation_bound(d: DissipationResult | None, vbar: float, lam_min: float
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
        return not_applicable("dissipation", formula, f"not proved ({d.message})")
    if not lam_min > 0:
        return not_applicable("dissipation", formula, "P is not numerically positive definite")
    # W_inf = sqrt((mu vbar^2 + mu_r eps^2) / alpha) as a hypotenuse (no squares to overflow)
    alpha = d.alpha * (1.0 - NUDGE)
    w_inf = up_rel(math.sqrt(up_rel(d.mu / alpha)) * vbar)
    if d.mu_residual:
        eps = d.eps_bar if d.eps_bar is not None else math.inf
        w_inf = up_rel(math.hypot(w_inf, up_rel(math.sqrt(up_rel(d.mu_residual / alpha)) * eps)))
    s = math.sqrt(lam_min) * (1.0 - NUDGE)
    if not math.isfinite(up_rel(w_inf / s)):
        return not_applicable("dissipation", formula, overflow(vbar))
    return BoundResult(
        name="dissipation", applicable=True,
        reason=(f"proved V' <= -{lower_text(d.alpha, 6)} V + {upper_text(d.mu, 6)} ||v||^2"
                + (f" + {upper_text(d.mu_residual, 6)} eps_bar_P^2" if d.mu_residual else "")
                + " over X x Y (valid while y + v stays in Y)"),
        rate=float(d.alpha), gain=up_rel(1.0 / s), bias=up_rel(w_inf / s),
        bias_per_unit_noise=up_rel(math.sqrt(up_rel(d.mu / d.alpha)) / s), formula=formula)


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
    return np.array([up_rel(up_rel(X[i, i]) + up_rel(col[i] / lam_min)) for i in range(n)])


def worst_start(bound: BoundResult, P: np.ndarray, X: np.ndarray) -> float:
    """The largest start value of `bound` over starts with x and xhat in the box X [n, 2]:
    e0 in [-w, w] (w the widths), so ||e0|| <= ||w|| and max e0^T P e0 is attained at a
    vertex of that box (a convex function; 2^(n-1) sign patterns, n <= 16)."""
    w = np.asarray(X, dtype=np.float64)[:, 1] - np.asarray(X, dtype=np.float64)[:, 0]
    if bound.name == "theorem3":
        return up_rel(float(np.linalg.norm(w)))
    n = w.shape[0]
    if n > 16:
        return up_rel(float(np.linalg.norm(w)) * math.sqrt(metric_constants(P)[1] ** 2))
    signs = np.array([[1.0] + [1.0 - 2.0 * ((k >> j) & 1) for j in range(n - 1)]
                      for k in range(2 ** (n - 1))])
    v = signs * w
    quad = np.einsum("ki,ij,kj->k", v, np.asarray(P, dtype=np.float64), v)
    return up_rel(math.sqrt(up_rel(float(quad.max()))))


def settle_time(bounds: BoundsResult, which: str, start: float, level: float) -> float:
    """The first time t >= 0 after which `bound_curve(bounds, which, start, t)` <= `level`
    (the curves decrease monotonically towards the ultimate value, so one crossing), found
    by bisection to a relative 1e-6 and rounded up by a further relative 1e-6 (the curve's
    float evaluation errs far less); 0 when it starts below. inf when `level` is not above 0
    (a curve reaches 0 only as t -> infinity: a finite time there would only mark where
    e^(-rate t) underflows) or the crossing is beyond 1e12 s."""
    def at(t: float) -> float:
        return float(bound_curve(bounds, which, start, np.array([t]))[0])
    if not (math.isfinite(level) and level > 0):
        return math.inf
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
    return hi * (1.0 + 1e-6)


def fill_headline(r: BoundsResult, P: np.ndarray, X: np.ndarray) -> None:
    """Fill `best`, `ultimate`, `headline`, `settle_time` and `per_component` of `r` from its
    applicable bound with the smallest ultimate value (in place)."""
    applicable = [b for b in r.bounds() if b.applicable and b.bias is not None]
    if not applicable:
        return
    best = min(applicable, key=lambda b: float(b.bias))  # type: ignore[arg-type]
    r.best, r.ultimate = best.name, float(best.bias)  # type: ignore[arg-type]
    r.headline = up_rel(HEADLINE_MARGIN * r.ultimate)
    t_settle = settle_time(r, best.name, worst_start(best, P, X), r.headline)
    r.settle_time = t_settle if math.isfinite(t_settle) else None  # ultimate 0: only as t -> inf
    if best.name == "theorem3":
        r.per_component = [r.ultimate] * P.shape[0]
    elif best.components is not None:
        r.per_component = [min(r.ultimate, c) for c in best.components]
    else:  # |e_i| <= W sqrt((P^-1)_ii), W <= bias sqrt(lam_min) <= bias / gain
        w_inf = up_rel(r.ultimate / float(best.gain) * (1 + NUDGE))  # type: ignore[arg-type]
        r.per_component = [min(r.ultimate, up_rel(w_inf * math.sqrt(d)))
                           for d in inverse_diagonal_upper(P)]


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
    return np.sqrt(np.maximum(quad, 0.0)) * (1.0 + NUDGE)


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
    if which == "metric":
        return _metric_curve(bounds, b, s, t)  # the start values as given
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
    return up_rel(math.sqrt(kappa_P) * (eps_bar + L * vbar) / (2.0 * lam_cert))  # type: ignore[operator]


def metric_bound(m: MetricBoundResult | None, stage1: BoundResult | None, t1: float | None
                 ) -> BoundResult | None:
    """The bound in stages of a proved `MetricBoundResult` (`certify.prove.metric`): the
    dissipation bound `stage1` until its settle time `t1` (where V <= ENTRY^2 V_inf from
    every start in X), then each stage's d^2 curve with d the metric's distance and
    ||e|| <= d / sqrt(m_min), |e_i| <= gamma_i d."""
    if m is None:
        return None
    formula = ("||e(t)|| <= the dissipation bound until t1, then sqrt(e^(-alpha (t - s)) c + "
               "(1 - e^(-alpha (t - s))) d_inf^2 / m_min) per stage (Riemannian path "
               "certificate with M(x) on tubes around the output manifold)")
    if m.status != Status.PROVED or not m.stages or not m.m_min:
        return not_applicable("metric", formula, f"not proved ({m.message})")
    if stage1 is None or not stage1.applicable or t1 is None or not math.isfinite(t1):
        return not_applicable("metric", formula, "the first stage (the dissipation bound) has "
                              "no finite settle time")
    gain = up_rel(1.0 / (math.sqrt(m.m_min) * (1.0 - NUDGE)))
    pieces, start = [], float(t1)
    for s in m.stages:
        pieces.append(dict(start=start, alpha=float(s["alpha"]), entry=up_rel(s["entry"]),
                           v_inf=up_rel(s["v_inf"]), tau=float(s["tau"])))
        start = up_rel(start + float(s["duration"]))
    d_inf = up_rel(math.sqrt(pieces[-1]["v_inf"]))
    bias = up_rel(gain * d_inf)
    if not math.isfinite(bias):
        return not_applicable("metric", formula, "the bound is not a finite number")
    box = ", ".join(f"[{lo:.4g}, {hi:.4g}]" for lo, hi in (m.plant_box or []))
    return BoundResult(
        name="metric", applicable=True,
        reason=(f"the metric M(x) in {len(m.stages)} stage(s) after the dissipation bound "
                f"(from t >= {t1:.3g} s); valid while the plant state stays in {box} and the "
                "noise is bounded"),
        rate=float(m.stages[-1]["alpha"]), gain=gain, bias=bias,
        bias_per_unit_noise=None, formula=formula, pieces=pieces,
        components=[up_rel(g * d_inf) for g in m.gamma])


def _metric_curve(bounds: BoundsResult, b: BoundResult, start: np.ndarray, t: np.ndarray
                  ) -> np.ndarray:
    """The staged curve: the dissipation bound before the first piece; after, the smaller
    of it and the piece in force (both are bounds there)."""
    first = bound_curve(bounds, "dissipation", start, t)
    out = first.copy()
    for k, piece in enumerate(b.pieces or []):
        end = b.pieces[k + 1]["start"] if k + 1 < len(b.pieces) else math.inf
        tau = t - piece["start"]
        decay = np.exp(-piece["alpha"] * np.maximum(tau, 0.0))
        value = b.gain * np.sqrt(decay * piece["entry"] + (1.0 - decay) * piece["v_inf"])
        use = (t >= piece["start"]) & (t < end)
        out = np.where(use, np.minimum(first, value), out)
    return out


# ----------------------------------------------------------------------------- validity region

#: the bounds whose curves keep W = ||P^(1/2) e|| below max(W(0), W_inf) for all t
W_BOUNDS = ("dissipation", "iss_metric", "iss")


def _down(x: float) -> float:
    return math.nextafter(x, -math.inf)


def _inside(box: np.ndarray, outer: np.ndarray) -> bool:
    return bool(np.all(box[:, 0] >= outer[:, 0]) and np.all(box[:, 1] <= outer[:, 1]))


def validity_region(r: BoundsResult, P: np.ndarray, X: np.ndarray, Y: np.ndarray,
                    invariance: InvarianceResult | None,
                    plant_box: list[list[float]] | None = None) -> None:
    """Fill the validity region of `r` (PROVED, headline filled) in place: `region`, `r0`,
    `r0_W`, `region_settle_time`, `proved_conditions`, or `region_reason` why there is none.

    Let R, inside X, be forward invariant for x' = f(x) with component ranges inside
    [R_lo, R_hi] (`invariance.hull`), h(R) inside Y (`invariance.output_range`), and
    d_i = min(R_lo_i - X_lo_i, X_hi_i - R_hi_i) (rounded down). Each of the W-bounds
    (`W_BOUNDS`) gives W(t) <= max(W(0), W_inf) while (a)-(d) hold, and |e_i| <= gamma_i W
    with gamma_i = sqrt((P^-1)_ii) (rounded up). If W_inf < w = min_i d_i / gamma_i (the
    smallest W_inf of the applicable W-bounds) and W(0) <= r0_W < w, then for x(0) in R
    xhat stays in X for all t: otherwise at the first exit time t* the conditions hold on
    [0, t*] (x in R by invariance, h(x) in Y, xhat in X), so |e_i(t*)| <= gamma_i max(W(0),
    W_inf) < d_i and xhat(t*) = x(t*) - e(t*) lies in the interior of X, which a first exit
    cannot. So (a) and (b) hold for all t, and (d) too where h(R) lies vbar inside Y
    (|v_j| <= ||v||_2 <= vbar). ||e(0)||_2 <= r0 = r0_W / ||P^(1/2)||_2 gives W(0) <= r0_W.
    The headline B then holds for t >= `region_settle_time` (the best bound's settle time
    from W(0) = r0_W, no later than from the worst start in X); the bound with a metric
    that follows the state also needs R inside its `plant_box`."""
    def no(reason: str) -> None:
        r.region_reason = reason

    if r.status != Status.PROVED or r.headline is None:
        return no("no error bound")
    if invariance is None:
        return no("no plant region was proved forward invariant (the invariance check did "
                  "not run)")
    if invariance.status != Status.PROVED or invariance.hull is None or \
            invariance.region is None:
        return no(f"no plant region inside X was proved forward invariant (invariance "
                  f"{invariance.status.value})")
    hull = np.asarray(invariance.hull, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    if not _inside(hull, X):
        return no("the region proved forward invariant is not inside X")
    out = invariance.output_range
    if out is None or not _inside(np.asarray(out, dtype=np.float64), np.asarray(Y)):
        return no("h over the invariant region may leave Y (condition (b) is not proved)")
    d = [min(_down(hull[i, 0] - X[i, 0]), _down(X[i, 1] - hull[i, 1]))
         for i in range(X.shape[0])]
    gamma = [up_rel(math.sqrt(v)) for v in inverse_diagonal_upper(P)]
    room = min(_down(_down(di) / gi) if di > 0 else 0.0 for di, gi in zip(d, gamma))
    w_bounds = [b for b in (getattr(r, n) for n in W_BOUNDS)
                if b is not None and b.applicable and b.bias is not None and b.gain]
    if not w_bounds:
        return no("no bound of W = ||P^(1/2) e|| applies (dissipation, iss_metric, iss)")
    w_inf = min(up_rel(up_rel(float(b.bias) / float(b.gain))) for b in w_bounds)
    if not (math.isfinite(room) and w_inf < room):
        limits = ", ".join(f"{up_rel(g * w_inf):.3g}" for g in gamma)
        rooms = ", ".join(f"{di:.3g}" for di in d)
        return no(f"the error's limit per component ({limits}) does not fit in the room "
                  f"the invariant region leaves in X ({rooms}): no initial error keeps "
                  "xhat in X by this argument")
    if r.best == "metric" and (plant_box is None
                               or not _inside(hull, np.asarray(plant_box, dtype=np.float64))):
        return no("the bound with the metric M(x) needs the plant in its own box, which the "
                  "invariant region does not fit in")
    r0_W = room * (1.0 - 1e-9)
    r0 = r0_W / metric_constants(P)[1] * (1.0 - NUDGE)
    if not r0 > 0:
        return no("the invariant region leaves no room in X for an initial error")
    start = r0 if r.best == "theorem3" else r0_W
    t = settle_time(r, r.best, start, r.headline)
    text = invariance.region.get("text") or invariance.region.get("kind", "a region")
    r.region = (f"{text}, proved forward invariant, in "
                + " x ".join(f"[{lo:.4g}, {hi:.4g}]" for lo, hi in hull))
    r.r0, r.r0_W = r0, r0_W
    r.region_settle_time = t if math.isfinite(t) else None
    conds = ["a", "b"]
    if r.L_is_local:
        Yv = np.asarray(Y, dtype=np.float64)
        o = np.asarray(out, dtype=np.float64)
        lo_ok = all(o[j, 0] >= math.nextafter(Yv[j, 0] + r.vbar, math.inf)
                    for j in range(len(o)))
        hi_ok = all(o[j, 1] <= _down(Yv[j, 1] - r.vbar) for j in range(len(o)))
        if lo_ok and hi_ok:
            conds.append("d")
    r.proved_conditions = conds
