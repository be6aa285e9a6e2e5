"""`certify run` on the user's path: a violated MPDI decides at once (exit 1, the point and
its sound bound named, the rest not run without a report), a proved smaller rate is
suggested and the suggestion certifies, --lam overrides a checkpoint's rate and the
certificate says so, the wall-clock cap gives INCONCLUSIVE (exit 3), and an older
certificate that holds the retired time budgets still renders."""

from __future__ import annotations

import json
import math
import shlex

import pytest

from certify.certificate import Certificate

from ..cli_helpers import FAST_POLICY, A, C, K, run_cli, save_linear
from ..fixtures_certificates import certified_certificate
from ..planted import lam_cert_linear


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


TRUE = lam_cert_linear(A, C, K)  # the linear gain's exact rate


@pytest.mark.slow
def test_a_violated_mpdi_exits_1_at_once_and_says_where(workdir, capsys):
    path = save_linear(workdir / "fast.ckpt", lam=1.2 * TRUE)
    code, out, err = run_cli(capsys, "run", path)
    assert code == 1, err
    assert "verdict decided: NOT CERTIFIED, mpdi is VIOLATED" in err
    assert "sound lower bound" in err and "the other checks are not run" in err
    assert "NOT RUN" in out and "not run, the verdict being decided: " in out
    assert "a smaller rate may certify" in out and "--json" in out


@pytest.mark.slow
def test_the_suggested_rate_certifies(workdir, capsys):
    path = save_linear(workdir / "fast.ckpt", lam=1.2 * TRUE)
    code, out, err = run_cli(capsys, "run", path, "--json", "cert.json", "--quiet",
                             "--skip", "simulation")
    assert code == 1, err
    cert = json.loads((workdir / "cert.json").read_text())
    assert cert["checks"]["rate"]["status"] == "PROVED"  # reports asked: every check ran
    summary = cert["summary"]
    command = shlex.split(summary.split("`")[1])
    assert command[:3] == ["certify", "run", path] and command[3] == "--lam"
    lam = float(command[4])
    assert 0 < lam <= cert["checks"]["rate"]["proved_lower"] <= TRUE
    assert summary in out
    code, out, err = run_cli(capsys, *command[1:], "--quiet")
    assert code == 0, out + err
    assert out.startswith("CERTIFIED")


@pytest.mark.slow
def test_lam_overrides_a_checkpoint_and_is_recorded(workdir, capsys):
    path = save_linear(workdir / "fast.ckpt", lam=0.3)
    code, out, err = run_cli(capsys, "run", path, "--lam", "0.25", "--json", "cert.json",
                             "--skip", "simulation")
    assert code == 0, err
    assert "lam=0.25 (override; checkpoint 0.3)" in err
    cert = Certificate.load(workdir / "cert.json")
    assert cert.lam == 0.25 and cert.checks["rate"].lam_design == 0.25
    assert cert.overrides == {"lam": {"value": 0.25, "checkpoint": 0.3}}
    assert ("design \u03bb", "0.25 (override; checkpoint 0.3)") in cert.settings_rows()


@pytest.mark.slow
def test_the_wall_clock_cap_is_inconclusive_never_certified(workdir, capsys):
    path = save_linear(workdir / "fast.ckpt", lam=0.3)
    code, out, err = run_cli(capsys, "run", path, "--max-seconds", "0.001", "--json",
                             "cert.json")
    assert code == 3, out + err
    cert = json.loads((workdir / "cert.json").read_text())
    assert cert["verdict"] == "INCONCLUSIVE" and cert["settings"]["max_seconds"] == 0.001
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] == "UNKNOWN" and "wall-clock cap --max-seconds 0.001" in mpdi["message"]


def test_an_older_certificate_with_time_budgets_still_renders(tmp_path, capsys):
    data = json.loads(certified_certificate().to_json())
    old = {k: v for k, v in data["settings"].items()
           if k not in ("rate_boxes", "residual_boxes", "lipschitz_boxes", "dissipation_boxes",
                        "max_seconds")}
    old.update(proof_seconds=60.0, rate_seconds=20.0, residual_seconds=10.0,
               lipschitz_seconds=10.0, dissipation_seconds=60.0)
    data["settings"] = old
    (tmp_path / "old.json").write_text(json.dumps(data))
    code, out, err = run_cli(capsys, "report", str(tmp_path / "old.json"), "--html",
                             str(tmp_path / "r.html"), "--junit", str(tmp_path / "r.xml"))
    assert code == 0, err
    html = (tmp_path / "r.html").read_text()
    assert "MPDI proof time budget" in html and "rate time budget" in html
    rows = dict(Certificate.load(tmp_path / "old.json").settings_rows())
    assert rows["rate time budget"] == "20 s" and math.isfinite(float(rows["seed"]))
