"""The `bounds` check: the error bounds of METHOD §3.6-3.7 from the other checks' proved numbers.

The formulas, curves and the headline live in `certify.prove.error_bound`; this module reads
the rate, residual, Lipschitz and dissipation results, assembles the `BoundsResult` and says
it in words. Status words: PROVED (a bound holds); NOT APPLICABLE when lam_cert <= 0 and no
dissipation inequality was proved (no contraction, so no bound exists at all); UNKNOWN when an
input is not finite or not a valid bound; SKIPPED when an input was not established. A proved
headline larger than half the diagonal of X is true but says little: the result is marked
`vacuous` and its message says "valid but vacuous: larger than the box".
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from certify.arith.text import upper_text
from certify.checks.base import Check, Context
from certify.errors import SettingsError
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity, error_headline, validity_sentence
from certify.prove.error_bound import (
    HEADLINE_MARGIN,
    box_half_diagonal,
    describe_missing,
    dissipation_bound,
    fill_headline,
    iss_bound,
    metric_bound,
    metric_constants,
    settle_time,
    theorem3_bound,
    up_rel,
    validity_conditions,
    validity_region,
    worst_start,
)
from certify.results import (
    BoundResult,
    BoundsResult,
    DissipationResult,
    InvarianceResult,
    MetricBoundResult,
    Status,
)


def check_bounds(problem: Problem, *, lam_cert: float | None, eps_bar: float | None,
                 L: float | None, vbar: float, eps_bar_P: float | None = None,
                 L_P: float | None = None, L_is_local: bool = False,
                 dissipation: DissipationResult | None = None,
                 metric: MetricBoundResult | None = None,
                 invariance: InvarianceResult | None = None) -> BoundsResult:
    """Theorem 3 (as stated), the ISS bound and its metric variant at noise level `vbar`.

    All inputs must be sound: `lam_cert` a proved lower bound on the rate (metric
    `problem.P`), `eps_bar`, `L` (and `eps_bar_P`, `L_P`) proved upper bounds. PROVED when the
    ISS bound is applicable; NOT APPLICABLE when lam_cert <= 0 (no bound exists); SKIPPED
    when an input was not established (None); UNKNOWN when one is not finite or negative.
    A proved ultimate bound above half the diagonal of X is flagged `vacuous`. With a plant
    region proved forward invariant (`invariance`), the result also holds the validity
    region: the initial errors for which conditions (a)-(b) are proved for all t
    (`certify.prove.error_bound.validity_region`).
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
        r = describe_missing(nm, v, what)
        if r:
            (missing if v is None else invalid).append(r)
    common = invalid + missing

    theorem3 = theorem3_bound(P, lam, eps, Lf, vbar, common)
    iss_formula = ("||e(t)|| <= (e^(-2 lam t) W0 + (1 - e^(-2 lam t)) ||P^(1/2)||_2 "
                   "(eps_bar + L vbar)/(2 lam)) / sqrt(lam_min(P)), W0 = ||P^(1/2) e0||, "
                   "lam = lam_cert")
    iss = iss_bound("iss", lam, None if eps is None else up_rel(sqrtP_norm * eps),
               None if Lf is None else up_rel(sqrtP_norm * Lf), vbar, lam_min, common,
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
                r = describe_missing(nm, v, "the metric variant")
                if r:
                    mcommon.append(r)
        if epsP is None and eps is not None:
            epsP = up_rel(sqrtP_norm * eps)
            notes.append("eps_bar_P <= ||P^(1/2)|| eps_bar")
        if LP is None and Lf is not None:
            LP = up_rel(sqrtP_norm * Lf)
            notes.append("L_P <= ||P^(1/2)|| L")
        what = "eps_bar_P and L_P" + (f" (using {', '.join(notes)})" if notes else "")
        iss_metric = iss_bound("iss_metric", lam, epsP, LP, vbar, lam_min, mcommon, what,
                          metric_formula)

    c = None
    if iss.applicable:
        c = sqrtP_norm * (eps + Lf * vbar)  # type: ignore[operator]
    validity = validity_conditions(problem, vbar=vbar, L_is_local=L_is_local, c=c, lam=lam)
    joint = dissipation_bound(dissipation, vbar, lam_min)

    half_diagonal = box_half_diagonal(problem)
    r = BoundsResult(status=Status.SKIPPED, message="", vbar=vbar, lam_cert=lam, eps_bar=eps,
                     L=Lf, theorem3=theorem3, iss=iss, iss_metric=iss_metric,
                     validity=validity, kappa_P=kappa, L_is_local=bool(L_is_local),
                     box_half_diagonal=half_diagonal, dissipation=joint)
    if metric is not None:  # after the dissipation bound's settle time, in stages
        X = np.asarray(problem.system.X, dtype=np.float64)
        t1 = None
        if joint is not None and joint.applicable:
            t1 = settle_time(r, "dissipation", worst_start(joint, P, X),
                             up_rel(HEADLINE_MARGIN * float(joint.bias)))
        r.metric = metric_bound(metric, joint, t1)
        if r.metric is not None and r.metric.applicable:
            r.validity.append(f"(e) for the bound with the metric M(x), from t >= {t1:.3g} s on: "
                              f"{r.metric.reason}; its paths stay where it was proved.")
    applicable = [b for b in r.bounds() if b.applicable]
    if applicable:
        fill_headline(r, P, np.asarray(problem.system.X, dtype=np.float64))
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
        validity_region(r, P, np.asarray(problem.system.X, dtype=np.float64),
                        np.asarray(problem.system.Y, dtype=np.float64), invariance,
                        plant_box=None if metric is None else metric.plant_box)
        if r.region:
            proved = ", ".join(f"({c})" for c in r.proved_conditions)
            r.validity.insert(0, f"Proved for a set of starts: {validity_sentence(r, False)}. "
                              f"There conditions {proved} hold for all t by proof; elsewhere "
                              "the conditions below are assumptions.")
            valid = f"Validity: {validity_sentence(r, False)}."
        else:
            valid = (f"Valid only under conditions (a)-(d) (not proved for any set of starts: "
                     f"{r.region_reason}).")
        r.message = (f"||e|| <= {upper_text(r.headline)} for noise <= {vbar:g} {when} "
                     f"({size}); ultimate bounds (t -> infinity): {parts}"
                     + (f", per component |e_i| <= {limits}" if limits else "")
                     + f"; Theorem 3 as stated: {t3}. {valid}")
    elif no_rate and not [x for x in invalid if not x.startswith("lam_cert")]:
        r.status = Status.NOT_APPLICABLE
        r.message = "no error bound exists: " + "; ".join(common)
    else:
        # the inputs' reasons, and those of the bounds that need none of them (dissipation,
        # metric): e.g. a bound that exceeds the float range at a huge noise level
        own = [f"{b.name}: {b.reason}" for b in (r.dissipation, r.metric)
               if b is not None and not b.applicable]
        why = common + own
        r.status = Status.UNKNOWN if invalid or not common else Status.SKIPPED
        r.message = "no error bound: " + "; ".join(why)
    return r


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
    uses = ("rate", "residual", "lipschitz", "dissipation", "metric_bound", "invariance")

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
            dissipation=joint, metric=context.result("metric_bound"),
            invariance=context.result("invariance"))

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
        if head.proved:
            no_region = getattr(r, "region_reason", "") or "not computed"
            numbers += [Quantity("validity region", getattr(r, "region", "") or None,
                                 no_region),
                        Quantity("initial error r0 (||e(0)|| <=)", getattr(r, "r0", None),
                                 no_region, sig=6, bound="lower"),
                        Quantity("initial error in the P-norm (||P^(1/2) e(0)|| <=)",
                                 getattr(r, "r0_W", None), no_region, sig=6, bound="lower"),
                        Quantity("settle time from r0", getattr(r, "region_settle_time", None),
                                 no_region, sig=6, bound="upper")]
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
                      Quantity("From", head.source_text()),
                      Quantity("Conditions proved", head.validity_text() or None,
                               getattr(r, "region_reason", "") or "not computed")]
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
