"""Fault isolation through the real command line: a check that raises is that check's ERROR,
the others still run, the reports are still written, the gate says INCONCLUSIVE (exit 3)
when the check was required; an exception outside every check is exit 4 with one line."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

import certify.checks.bounds as bounds_mod
import certify.checks.lipschitz as lipschitz_mod
import certify.checks.simulation as simulation_mod
import certify.verify as verify_mod
from certify.certificate import Certificate
from certify.results import CheckFailure, SimulationResult, Status, decide_verdict

from ..cli_helpers import FAST_POLICY, run_cli, save_linear


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def _overflow(*args, **kwargs):
    # what sdp.py raised on a network with huge weights: float(norm) ** 2
    raise OverflowError("(34, 'Numerical result out of range')")


def _junit_cases(path) -> dict[str, ET.Element]:
    root = ET.parse(path).getroot()
    return {c.get("name"): c for c in root.iter("testcase")}


@pytest.mark.slow
def test_required_check_that_raises_is_error_others_run_exit_3(workdir, capsys, monkeypatch):
    monkeypatch.setattr(lipschitz_mod, "check_lipschitz", _overflow)
    path = save_linear(workdir / "lin.ckpt")
    code, out, err = run_cli(capsys, "run", path, "--require", "mpdi,lipschitz",
                             "--json", "c.json", "--junit", "c.xml", "--html", "c.html")
    assert code == 3, (out, err)
    assert "Traceback" not in err and "Traceback" not in out
    cert = json.loads((workdir / "c.json").read_text())
    assert cert["verdict"] == "INCONCLUSIVE"
    assert "lipschitz ended in ERROR" in cert["summary"]
    lip = cert["checks"]["lipschitz"]
    assert lip["status"] == "ERROR" and lip["failed"] is True
    assert lip["error_type"] == "OverflowError"
    assert "OverflowError: (34, 'Numerical result out of range')" in lip["message"]
    # every other check still ran and reached its own verdict
    assert cert["checks"]["mpdi"]["status"] == "PROVED"
    assert cert["checks"]["rate"]["status"] == "PROVED"
    assert cert["checks"]["residual"]["status"] == "PROVED"
    # bounds used L: it ran without it (the joint dissipation bound needs no L, so a bound
    # is still proved), and says which input was unavailable
    assert cert["checks"]["bounds"]["status"] == "PROVED"
    assert cert["checks"]["bounds"]["best"] == "dissipation"
    assert not cert["checks"]["bounds"]["iss"]["applicable"]
    assert "inputs unavailable: lipschitz (ERROR)" in cert["checks"]["bounds"]["message"]
    # the reports were written; JUnit shows the crash as an <error>, never a <failure>
    cases = _junit_cases(workdir / "c.xml")
    assert cases["lipschitz"].find("error") is not None
    assert cases["lipschitz"].find("failure") is None
    assert cases["lipschitz"].find("error").get("type") == "ERROR"
    assert "OverflowError" in (workdir / "c.html").read_text()
    # the JSON reads back with the failure record in place of the result
    back = Certificate.load(workdir / "c.json")
    assert isinstance(back.checks["lipschitz"], CheckFailure)
    assert back.checks["lipschitz"].error_type == "OverflowError"


@pytest.mark.slow
def test_error_in_a_check_that_is_not_required_does_not_decide(workdir, capsys, monkeypatch):
    monkeypatch.setattr(lipschitz_mod, "check_lipschitz", _overflow)
    path = save_linear(workdir / "lin.ckpt")
    code, out, err = run_cli(capsys, "run", path, "--quiet")
    assert code == 0, (out, err)
    assert out.startswith("CERTIFIED") and "not required, ended in ERROR: lipschitz" in out


@pytest.mark.slow
def test_check_whose_needs_failed_is_not_applicable(workdir, capsys, monkeypatch):
    monkeypatch.setattr(bounds_mod, "check_bounds", _overflow)
    path = save_linear(workdir / "lin.ckpt")
    code, _, err = run_cli(capsys, "run", path, "--json", "c.json", "--require",
                           "mpdi,simulation")
    assert code == 3, err
    cert = json.loads((workdir / "c.json").read_text())
    assert cert["checks"]["bounds"]["status"] == "ERROR"
    sim = cert["checks"]["simulation"]
    assert sim["status"] == "NOT APPLICABLE" and sim["failed"] is True
    assert sim["message"].startswith("not applicable: needs bounds, which ended in ERROR")
    assert "not established: simulation" in cert["summary"]


@pytest.mark.slow
def test_simulation_breach_of_a_proved_bound_is_never_certified(workdir, capsys, monkeypatch):
    def breach(problem, bounds, settings, *, progress=None, certified):
        assert certified  # everything the bound needs was proved
        return SimulationResult(Status.ERROR, "PROVED certificate breached by simulation")

    monkeypatch.setattr(simulation_mod, "check_simulation", breach)
    path = save_linear(workdir / "lin.ckpt")
    code, _, _ = run_cli(capsys, "run", path, "--json", "c.json", "--allow-unknown")
    assert code == 3
    cert = json.loads((workdir / "c.json").read_text())
    assert "simulation" in cert["required"] and cert["verdict"] == "INCONCLUSIVE"


@pytest.mark.parametrize("debug", [False, True])
@pytest.mark.slow
def test_escape_outside_every_check_is_exit_4_in_one_line(workdir, capsys, monkeypatch, debug):
    def boom(*args, **kwargs):
        raise ValueError("figure grid has the wrong shape")

    monkeypatch.setattr(verify_mod, "report_maps", boom)
    path = save_linear(workdir / "lin.ckpt")
    argv = ["run", path, "--json", "c.json", "--junit", "c.xml", "--quiet"]
    code, out, err = run_cli(capsys, *argv, *(["--debug"] if debug else []))
    assert code == 4
    line = ("certify: internal error in step 'figures': ValueError: figure grid has the wrong "
            "shape")
    if debug:
        assert "Traceback (most recent call last)" in err and line in err
    else:
        assert err == line + " (re-run with --debug for the traceback)\n"
    assert out == ""  # no verdict is printed for a crash
    assert not (workdir / "c.json").exists()  # no certificate, nothing half-written
    # CI's test view shows the crash: one <error> case naming the step, no <failure>
    cases = _junit_cases(workdir / "c.xml")
    assert list(cases) == ["figures"]
    error = cases["figures"].find("error")
    assert error is not None and error.get("type") == "ValueError"
    assert "figure grid has the wrong shape" in error.get("message")
    assert cases["figures"].find("failure") is None


@pytest.mark.slow
def test_escape_while_writing_reports_names_the_step(workdir, capsys, monkeypatch):
    import reports.render

    monkeypatch.setattr(reports.render, "render_reports", _overflow)  # what `run` calls
    path = save_linear(workdir / "lin.ckpt")
    code, _, err = run_cli(capsys, "run", path, "--junit", "c.xml", "--quiet")
    assert code == 4
    assert err.startswith("certify: internal error in step 'reports': OverflowError")
    assert err.count("\n") == 1


def test_policy_required_error_is_inconclusive_even_when_unknown_is_allowed():
    ok = SimulationResult(Status.PROVED, "")
    err = CheckFailure(Status.ERROR, "internal error: ValueError: x", "ValueError")
    bad = SimulationResult(Status.VIOLATED, "")
    assert decide_verdict({"mpdi": ok, "rate": err}, ["mpdi", "rate"], True)[0] == \
        "INCONCLUSIVE"
    assert decide_verdict({"mpdi": bad, "rate": err}, ["mpdi", "rate"], False)[0] == \
        "NOT CERTIFIED"
    verdict, summary = decide_verdict({"mpdi": ok, "rate": err}, ["mpdi"], False)
    assert verdict == "CERTIFIED" and "not required, ended in ERROR: rate" in summary


def test_certificate_schema_v1_is_read_and_unknown_versions_refused(tmp_path):
    from .. import fixtures_certificates as F

    data = F.certified_certificate().to_dict()
    data["schema_version"] = 1
    v1 = Certificate.from_dict(json.loads(json.dumps(data)))
    assert v1.verdict == "CERTIFIED" and v1.figures.mpdi_map is not None
    data["schema_version"] = 99
    with pytest.raises(Exception, match="schema version 99 is not supported"):
        Certificate.from_dict(data)
