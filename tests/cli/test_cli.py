"""The command line end to end: exit codes 0/1/2/3, one-line errors, policy from pyproject."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from certify.model import checkpoint
from certify.spec.system import load_system

from ..cli_helpers import FAST_POLICY, A, C, K, run_cli, save_problem
from ..planted import lam_cert_linear, linear_problem, planted_problem


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def test_systems_lists_and_prints(capsys):
    code, out, _ = run_cli(capsys, "systems")
    assert code == 0 and "vdp" in out and "duffing" in out
    code, out, _ = run_cli(capsys, "systems", "vdp")
    assert code == 0 and "x2*(1 - x1**2)" in out
    code, _, err = run_cli(capsys, "systems", "nosuch")
    assert code == 2 and "unknown system 'nosuch'" in err and err.count("\n") == 1


def test_bad_input_is_one_line_and_exit_2(workdir, capsys):
    code, _, err = run_cli(capsys, "run", "missing.ckpt")
    assert code == 2 and "not found" in err and err.count("\n") == 1
    (workdir / "junk.ckpt").write_bytes(b"\x00garbage")
    code, _, err = run_cli(capsys, "run", "junk.ckpt")
    assert code == 2 and err.startswith("certify: error:") and err.count("\n") == 1
    path = save_problem(workdir / "lin.ckpt", linear_problem(A, C, K, lam=0.3))
    code, _, err = run_cli(capsys, "run", path, "--max-boxes", "-3")
    assert code == 2 and "--max-boxes must be an int >= 1; got -3" in err
    code, _, err = run_cli(capsys, "run", path, "--require", "mpdi,nonsense")
    assert code == 2 and "--require must be a list of check names" in err
    code, _, err = run_cli(capsys, "run", path, "--no-such-flag")
    assert code == 2


def test_pyproject_policy_errors(workdir, capsys):
    path = save_problem(workdir / "lin.ckpt", linear_problem(A, C, K, lam=0.3))
    (workdir / "pyproject.toml").write_text("[tool.certify]\nmax_boxes = -3\n")
    code, _, err = run_cli(capsys, "run", path)
    assert code == 2 and "[tool.certify] max_boxes must be an int >= 1; got -3" in err
    (workdir / "pyproject.toml").write_text("[tool.certify]\nmax_boxs = 3\n")
    code, _, err = run_cli(capsys, "run", path)
    assert code == 2 and "unknown key(s) max_boxs" in err


@pytest.mark.slow
def test_linear_ground_truth_certified_exit_0(workdir, capsys):
    lam = 0.3
    problem = linear_problem(A, C, K, lam=lam)
    path = save_problem(workdir / "lin.ckpt", problem)
    # 3 s: longer than one time constant 1/(2 lam_cert) = 1.13 s, so the runs say something
    code, out, _ = run_cli(capsys, "run", path, "--json", "cert.json", "--quiet",
                           "--sim-time", "3")
    assert code == 0, out
    assert out.startswith("CERTIFIED")
    cert = json.loads((workdir / "cert.json").read_text())
    truth = lam_cert_linear(A, C, K)
    rate = cert["checks"]["rate"]
    assert abs(rate["sampled_upper"] - truth) < 1e-6
    assert abs(rate["proved_lower"] - truth) < 1e-6
    assert cert["checks"]["mpdi"]["status"] == "PROVED"
    assert cert["checks"]["mpdi"]["upper"] <= 0
    assert cert["checks"]["bounds"]["status"] == "PROVED"
    assert cert["checks"]["simulation"]["status"] == "PASSED"


@pytest.mark.parametrize("kind", ["corner", "blob"])
@pytest.mark.slow
def test_planted_violation_exit_1(workdir, capsys, kind):
    path = save_problem(workdir / f"{kind}.ckpt", planted_problem(kind))
    code, out, _ = run_cli(capsys, "run", path, "--json", "cert.json", "--skip",
                           "simulation,lipschitz")
    assert code == 1, out
    cert = json.loads((workdir / "cert.json").read_text())
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] == "VIOLATED"
    assert mpdi["counterexamples"] and mpdi["counterexamples"][0]["value"] > 0
    assert "NOT CERTIFIED" in out


@pytest.mark.slow
def test_inconclusive_exit_3_and_allow_unknown(workdir, capsys):
    from training.baseline import save_lmi_baseline

    path = workdir / "lmi.ckpt"
    save_lmi_baseline(path, load_system("vdp"), 2.5)  # true, but needs many sub-boxes
    args = ["run", str(path), "--max-boxes", "1", "--skip", "simulation,lipschitz,rate"]
    code, out, _ = run_cli(capsys, *args, "--json", "cert.json")
    assert code == 3, out
    cert = json.loads((workdir / "cert.json").read_text())
    assert cert["verdict"] == "INCONCLUSIVE"
    assert cert["checks"]["mpdi"]["status"] == "UNKNOWN"
    assert cert["checks"]["mpdi"]["lower"] < 0
    assert "proof budget spent (max_boxes=1 boxes)" in cert["checks"]["mpdi"]["message"]
    assert "raise max_boxes" in cert["checks"]["mpdi"]["message"]
    # a serial CPU run also names the ways to spread the proof
    assert "a GPU (--device cuda) or Dask workers (--workers, --scheduler)" in \
        cert["checks"]["mpdi"]["message"]
    # allow_unknown waives UNKNOWN for the other required checks, never for the MPDI: the
    # certificate itself must be PROVED to certify
    code, out, _ = run_cli(capsys, *args, "--allow-unknown", "--quiet")
    assert code == 3 and out.startswith("INCONCLUSIVE"), out
    assert "must be PROVED" in out
    code, _, _ = run_cli(capsys, "run", str(path), "--skip", "simulation,lipschitz,rate",
                         "--quiet")
    assert code == 0  # with the default budget the same gain is proved


@pytest.mark.slow
def test_train_tiny_then_run(workdir, capsys):
    code, _, err = run_cli(capsys, "train", "vdp", "--preset", "tiny", "-o", "tiny.ckpt",
                           "--quiet")
    assert code == 0, err
    ck = checkpoint.load(workdir / "tiny.ckpt")
    assert ck.problem.system.name == "vdp"
    code, _, err = run_cli(capsys, "train", "vdp", "--hidden", "3,x", "-o", "x.ckpt")
    assert code == 2 and "--hidden" in err
    assert not (workdir / "x.ckpt").exists()
    # the system as an option, as `certify run` takes it: the same checkpoint
    code, _, err = run_cli(capsys, "train", "--system", "vdp", "--preset", "tiny", "-o",
                           "tiny2.ckpt", "--quiet")
    assert code == 0, err
    again = checkpoint.load(workdir / "tiny2.ckpt")
    assert again.problem.system.name == "vdp"
    first, second = ck.problem.network.state_dict(), again.problem.network.state_dict()
    assert first.keys() == second.keys()
    assert all(torch.equal(first[k], second[k]) for k in first)  # same seed, same network


def test_console_script_runs():
    proc = subprocess.run([sys.executable, "-m", "certify.cli.main", "systems"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "vdp" in proc.stdout


@pytest.mark.slow
def test_paper_preset_vdp_not_certified_with_reports(workdir, capsys):
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "vdp.ckpt"
    code, out, _ = run_cli(capsys, "run", str(example), "--json", "r.json", "--junit", "r.xml",
                           "--html", "r.html", "--skip", "simulation")
    assert code == 1
    cert = json.loads((workdir / "r.json").read_text())
    mpdi, nec = cert["checks"]["mpdi"], cert["checks"]["necessary"]
    assert mpdi["status"] == "VIOLATED" and mpdi["lower"] > 5  # the known +7.7 region
    assert mpdi["violating_fraction"] > 0.9
    assert nec["status"] == "VIOLATED"
    assert abs(nec["witness"][0]) < 1e-6 and abs(nec["q_max"] - 6.0) < 1e-9  # 1 - 0 + 2 lam
    assert "q = 6 > 0" in out and "NOT CERTIFIED" in out
    assert cert["checks"]["bounds"]["iss"]["applicable"] is False
    # re-render from the saved certificate without verifying
    code, _, _ = run_cli(capsys, "report", "r.json", "--html", "again.html", "--quiet")
    assert code == 0
    assert (workdir / "again.html").read_text() == (workdir / "r.html").read_text()
    code, _, err = run_cli(capsys, "report", "r.xml", "--html", "x.html")
    assert code == 2 and "not valid JSON" in err
