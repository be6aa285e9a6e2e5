"""A run that stops early says why: once a required check is VIOLATED the verdict is decided
(with `fail_fast` the other checks are NOT RUN, saying so, never "skipped by the user"); the
wall-clock cap makes a check it cut UNKNOWN, never PROVED, with the cap in its message; and
a violated MPDI with a proved smaller rate names a rate that certifies, never one above the
proved bound."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from certify.checks.base import Check, Context
from certify.checks.registry import cut_by_cap, run_checks
from certify.figuredata import FigureData
from certify.progress import NullProgress
from certify.results import (
    CheckFailure,
    Counterexample,
    MpdiResult,
    ProofStats,
    RateResult,
    Status,
    decide_verdict,
)
from certify.settings import VerifySettings
from certify.verify import smaller_rate_hint


class _Fixed(Check):
    """A check that returns a given result (and counts its runs)."""

    def __init__(self, name: str, result: object) -> None:
        self.name, self._result, self.runs = name, result, 0

    def run(self, context: Context) -> object:
        self.runs += 1
        return self._result


class _Notes(NullProgress):
    def __init__(self) -> None:
        self.notes: list[str] = []

    def note(self, text: str) -> None:
        self.notes.append(text)


def _violated() -> MpdiResult:
    cex = Counterexample(xhat=[0.5, -1.0], y=[0.25], value=0.3, sound_bound=0.29)
    return MpdiResult(Status.VIOLATED, "D is not negative semidefinite at xhat=(0.5, -1), "
                      "y=(0.25) (sound lower bound 0.29)", lower=0.3, upper=None, worst=cex,
                      counterexamples=[cex])


def _context(settings: VerifySettings | None = None, *, fail_fast: bool = False,
             deadline: float | None = None) -> Context:
    return Context(problem=None, settings=settings or VerifySettings(),  # type: ignore[arg-type]
                   progress=_Notes(), figures=FigureData(), required=["mpdi"],
                   fail_fast=fail_fast, deadline=deadline)


def _run(monkeypatch, context: Context, checks: dict[str, Check]) -> dict[str, float]:
    import certify.checks.registry as registry

    monkeypatch.setattr(registry, "get_check", lambda name: checks[name])
    return run_checks(context, names=list(checks))


def test_a_violated_mpdi_decides_and_fail_fast_runs_nothing_more(monkeypatch):
    rate = _Fixed("rate", RateResult(Status.PROVED, "ok", 0.5, 0.6, 0.45))
    context = _context(fail_fast=True)
    _run(monkeypatch, context, {"mpdi": _Fixed("mpdi", _violated()), "rate": rate})
    assert rate.runs == 0
    r = context.results["rate"]
    assert isinstance(r, CheckFailure) and r.status is Status.NOT_RUN
    assert "verdict was already decided" in r.message and "mpdi is VIOLATED" in r.message
    assert "skipped" not in r.message.lower()
    # the progress said so at once, naming the point and its sound lower bound
    (note,) = context.progress.notes
    assert "NOT CERTIFIED" in note and "sound lower bound 0.29" in note
    assert "not run" in note
    verdict, summary = decide_verdict(context.results, context.required, False)
    assert verdict == "NOT CERTIFIED"
    assert "not run, the verdict being decided: rate" in summary


def test_without_fail_fast_the_other_checks_still_run(monkeypatch):
    rate = _Fixed("rate", RateResult(Status.PROVED, "ok", 0.5, 0.6, 0.45))
    context = _context()
    _run(monkeypatch, context, {"mpdi": _Fixed("mpdi", _violated()), "rate": rate})
    assert rate.runs == 1 and context.results["rate"].status is Status.PROVED
    assert "still run" in context.progress.notes[0]


def test_fail_fast_changes_nothing_while_the_verdict_is_open(monkeypatch):
    proved = MpdiResult(Status.PROVED, "proved", lower=-0.1, upper=-0.01)
    rate = _Fixed("rate", RateResult(Status.PROVED, "ok", 0.5, 0.6, 0.5))
    context = _context(fail_fast=True)
    _run(monkeypatch, context, {"mpdi": _Fixed("mpdi", proved), "rate": rate})
    assert rate.runs == 1 and not context.progress.notes


@pytest.mark.parametrize("status", [Status.PROVED, Status.UNKNOWN, Status.PASSED])
def test_a_check_the_cap_cut_is_unknown_and_names_the_cap(status):
    r = RateResult(status, "lam_cert in [0.4, 0.5]", 0.5, 0.5, 0.4,
                   proof=ProofStats(boxes_processed=10, stopped_by_cap=True))
    cut_by_cap(r, _context(VerifySettings(max_seconds=30.0)))
    assert r.status is Status.UNKNOWN
    assert r.message.startswith("stopped by the wall-clock cap --max-seconds 30: ")


def test_the_cap_never_hides_a_counterexample_or_touches_an_uncut_check():
    v = _violated()
    v.proof = ProofStats(stopped_by_cap=True)
    cut_by_cap(v, _context(VerifySettings(max_seconds=5.0)))
    assert v.status is Status.VIOLATED and "cap" not in v.message
    ok = RateResult(Status.PROVED, "fine", 0.5, 0.5, 0.4, proof=ProofStats(boxes_processed=3))
    cut_by_cap(ok, _context(VerifySettings(max_seconds=5.0)))
    assert ok.status is Status.PROVED and ok.message == "fine"


def test_a_check_not_started_before_the_cap_is_not_run_and_unknown(monkeypatch):
    mpdi = _Fixed("mpdi", MpdiResult(Status.PROVED, "proved", lower=-1.0, upper=-0.5))
    context = _context(VerifySettings(max_seconds=1.0), deadline=time.perf_counter() - 1.0)
    _run(monkeypatch, context, {"mpdi": mpdi})
    r = context.results["mpdi"]
    assert mpdi.runs == 0 and r.status is Status.UNKNOWN
    assert "wall-clock cap --max-seconds 1 was reached before it started" in r.message
    verdict, _ = decide_verdict(context.results, context.required, allow_unknown=True)
    assert verdict == "INCONCLUSIVE"  # never CERTIFIED, whatever allow_unknown says


def _rate(lower: float | None, lam: float = 0.5) -> RateResult:
    return RateResult(Status.PROVED if lower else Status.UNKNOWN, "", lam, lam * 1.01, lower)


def test_a_proved_smaller_rate_gives_the_command_that_certifies():
    checks = {"mpdi": _violated(), "rate": _rate(0.458675)}
    hint = smaller_rate_hint(checks, ["mpdi"], 0.5, "runs/vdp net.ckpt", {})
    assert hint == ("the MPDI is violated at the design rate lam = 0.5, but a rate lam_cert "
                    ">= 0.4586 is proved: `certify run 'runs/vdp net.ckpt' --lam 0.4586` "
                    "certifies at that rate")
    with_metric = smaller_rate_hint(checks, ["mpdi"], 0.5, "a.ckpt",
                                    {"metric": {"value": [[2.0, 0.0], [0.0, 1.0]]}})
    assert "--lam 0.4586 --metric '[[2.0, 0.0], [0.0, 1.0]]'" in with_metric


@pytest.mark.parametrize("checks, required", [
    ({"mpdi": _violated(), "rate": _rate(None)}, ["mpdi"]),  # no rate proved
    ({"mpdi": _violated(), "rate": _rate(0.6)}, ["mpdi"]),  # not smaller (cannot be, but)
    ({"mpdi": MpdiResult(Status.PROVED, "", -1.0, -0.5), "rate": _rate(0.4)}, ["mpdi"]),
    ({"mpdi": _violated(), "rate": _rate(0.4),
      "residual": CheckFailure(Status.VIOLATED, "x")}, ["mpdi", "residual"]),
])
def test_no_suggestion_where_a_rate_would_not_certify(checks, required):
    assert smaller_rate_hint(checks, required, 0.5, "a.ckpt", {}) == ""


def test_a_rate_check_not_run_says_how_to_run_it():
    checks = {"mpdi": _violated(), "rate": CheckFailure(Status.NOT_RUN, "not run: decided")}
    hint = smaller_rate_hint(checks, ["mpdi"], 0.5, "a.ckpt", {})
    assert "a smaller rate may certify" in hint and "--json" in hint


@given(lower=st.floats(1e-12, 1e6, allow_nan=False, allow_infinity=False))
def test_the_suggested_rate_is_never_above_the_proved_bound(lower):
    lam = float(np.nextafter(lower, np.inf)) * 1.5
    hint = smaller_rate_hint({"mpdi": _violated(), "rate": _rate(lower, lam)}, ["mpdi"], lam,
                             "a.ckpt", {})
    suggested = float(hint.split("--lam ")[1].split("`")[0])
    assert 0 < suggested <= lower


def test_a_rate_check_not_run_proposes_a_rate_below_the_sampled_cap():
    """Fail fast skips the rate check; a quick sampled cap (the smallest pointwise rate at
    samples) still gives a rate to try, below the cap, and the command that decides it; a cap
    <= 0 says no positive rate holds there."""
    checks = {"mpdi": _violated(), "rate": CheckFailure(Status.NOT_RUN, "not run: decided")}
    hint = smaller_rate_hint(checks, ["mpdi"], 0.5, "a.ckpt", {}, sampled_cap=0.4586)
    tried = float(hint.split("--lam ")[1].split("`")[0])
    assert 0 < tried < 0.4586 and "decides it" in hint and "--json" in hint
    none = smaller_rate_hint(checks, ["mpdi"], 0.5, "a.ckpt", {}, sampled_cap=-0.2)
    assert "no rate > 0 holds at sampled points" in none and "--lam" not in none
