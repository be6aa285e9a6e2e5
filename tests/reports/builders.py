"""Certificates for the report tests, built on `tests.fixtures_certificates`: a current
headline (the dissipation bound is the best), no bound at all, a bound proved at the proved
rate under a failed certificate, and one resting on a contraction nobody proved."""

from __future__ import annotations

import dataclasses

from certify.certificate import Certificate
from certify.results import (
    BoundResult,
    DissipationResult,
    RateResult,
    Status,
    decide_verdict,
)

from ..fixtures_certificates import (
    certified_certificate,
    inconclusive_certificate,
    violated_vdp_certificate,
)

HALF_DIAGONAL = (2.5 ** 2 + 3.5 ** 2) ** 0.5  # X of `certified_certificate`


def _dissipation_bound(ultimate: float, vbar: float) -> BoundResult:
    return BoundResult(name="dissipation", applicable=True,
                       reason="proved V' <= -0.9 V + 11.2 ||v||^2 over X x Y",
                       rate=0.9, gain=2.63, bias=ultimate,
                       bias_per_unit_noise=ultimate / vbar, formula="sqrt(mu/alpha) ...")


def headline_certificate(*, vacuous: bool = False) -> Certificate:
    """`certified_certificate` with the headline fields a current bounds check fills: the
    joint dissipation bound (its check PROVED) is the best, ultimate 1.1374 (useful) or
    29.3 (vacuous)."""
    cert = certified_certificate()
    b = cert.checks["bounds"]
    ultimate = 29.3 if vacuous else 1.1374
    cert.checks["dissipation"] = DissipationResult(
        Status.PROVED, "V' <= -0.9 V + 11.2 ||v||^2 proved over X x Y", alpha=0.9, mu=11.2,
        vertices=4, boxes=812, seconds=3.2)
    cert.checks["bounds"] = dataclasses.replace(
        b, dissipation=_dissipation_bound(ultimate, b.vbar), best="dissipation",
        ultimate=ultimate, headline=ultimate * 1.1, settle_time=3.0417,
        per_component=[0.3561 * ultimate / 1.1374, 1.1374 * ultimate / 1.1374],
        box_half_diagonal=HALF_DIAGONAL, vacuous=vacuous,
        message=("||e|| <= ... (valid but vacuous: larger than the box)" if vacuous
                 else "||e|| <= ... (useful: the box's half-diagonal is 4.3)"))
    return cert


def no_bound_certificate() -> Certificate:
    """The bounds check ended NOT APPLICABLE: lam_cert <= 0, so no bound exists."""
    cert = certified_certificate()
    b = cert.checks["bounds"]
    cert.checks["bounds"] = dataclasses.replace(
        b, status=Status.NOT_APPLICABLE,
        message="no error bound exists: lam_cert = -0.2 <= 0: no contraction was certified",
        lam_cert=None)
    return cert


def _recheck(cert: Certificate) -> Certificate:
    cert.verdict, cert.summary = decide_verdict(
        cert.checks, cert.required, bool((cert.settings or {}).get("allow_unknown")))
    return cert


def proved_rate_certificate(lam_cert: float = 0.45861) -> Certificate:
    """NOT CERTIFIED: the MPDI is violated at the design rate 2.5, but the rate check proved
    lam_cert >= `lam_cert`, and the bounds check built the ISS bound on it (PROVED)."""
    cert = violated_vdp_certificate()
    rate = RateResult(Status.PROVED, f"lam_cert in [{lam_cert}, 0.52] (design lam 2.5)",
                      lam_design=2.5, sampled_upper=0.52, proved_lower=lam_cert, seconds=3.0)
    iss = BoundResult(name="iss", applicable=True, reason=f"lam_cert = {lam_cert} > 0",
                      rate=2 * lam_cert, gain=1.0, bias=1.3371,
                      bias_per_unit_noise=1.3371 / 0.15, formula="...")
    b = cert.checks["bounds"]
    cert.checks["rate"] = rate
    cert.checks["bounds"] = dataclasses.replace(
        b, status=Status.PROVED, message="||e|| <= 1.48 for noise <= 0.15 after t >= 4.2 s",
        lam_cert=lam_cert, iss=iss, best="iss", ultimate=1.3371, headline=1.3371 * 1.1,
        settle_time=4.13, per_component=[1.3371, 1.3371], box_half_diagonal=13 ** 0.5,
        vacuous=False)
    return _recheck(cert)


def unproved_basis_certificate() -> Certificate:
    """INCONCLUSIVE, with a bounds result (as a foreign or older certificate may hold) that
    says PROVED although neither the rate check nor the MPDI proved a contraction."""
    cert = inconclusive_certificate()
    iss = BoundResult(name="iss", applicable=True, reason="lam_cert = 0.3 > 0", rate=0.6,
                      gain=1.2, bias=0.91, bias_per_unit_noise=18.2, formula="...")
    b = cert.checks["bounds"]
    cert.checks["bounds"] = dataclasses.replace(
        b, status=Status.PROVED, message="||e|| <= 1.01 ...", lam_cert=0.3, iss=iss,
        best="iss", ultimate=0.91, headline=1.001, settle_time=2.0,
        per_component=[0.9, 0.91], box_half_diagonal=2 ** 0.5, vacuous=False)
    return _recheck(cert)
