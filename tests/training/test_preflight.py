"""`certify train`'s pre-flight (training.preflight): a design that the necessary condition
proves infeasible is not trained (exit 5, the reason and the routes, nothing written) unless
`--force`; a system with no constant metric at any rate says so for every preset."""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from certify.checks import necessary
from certify.cli.main import main
from certify.design.metric import undetectable_at_every_rate
from certify.model import checkpoint
from certify.results import NecessaryResult, Status
from certify.spec.system import load_system
from training import command, preflight
from training.command import run_train
from training.preflight import EXIT_INFEASIBLE

from ..cli_helpers import run_cli


def _parse(*argv: str):
    import argparse

    parser = argparse.ArgumentParser()
    command.add_train_arguments(parser)
    return parser.parse_args(list(argv))


def _violated(system, P, lam, **_kw) -> NecessaryResult:
    """What `check_necessary` says of vdp at P = I, lam = 2.5 (its known answer), at once."""
    return NecessaryResult(Status.VIOLATED, "q = 6 > 0 at xhat = (0, 0)", 6.0, None,
                           [0.0, 0.0], [0.0], -0.5, 18.0)


@pytest.fixture
def fake_violation(monkeypatch):
    """The pre-flight sees a violation and the metric SDP is not run (control flow only)."""
    monkeypatch.setattr(necessary, "check_necessary", _violated)
    monkeypatch.setattr(preflight, "routes", lambda *a: ["routes: (stand-in)"])

    def no_training(*_a, **_k):
        raise AssertionError("trained after a proved violation")

    import training.train

    monkeypatch.setattr(training.train, "train", no_training)


def test_a_proved_violation_stops_before_training(fake_violation, tmp_path, capsys):
    out = tmp_path / "vdp.ckpt"
    code = run_train(_parse("vdp", "-o", str(out)))
    err = capsys.readouterr().err
    assert code == EXIT_INFEASIBLE == 5
    assert err.startswith("certify train: stopped before training: the pre-flight proves")
    assert "xhat = (0, 0), y = (0)" in err and "q = 6 > 0" in err
    assert "sound lower bound 5.99" in err  # the witness re-bounded soundly, rounded down
    assert "eps_bar >= 18" in err and "--force trains anyway" in err
    assert not out.exists()


def test_force_trains_anyway_and_says_so(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(necessary, "check_necessary", _violated)
    out = tmp_path / "vdp.ckpt"
    stream = io.StringIO()
    code = run_train(_parse("vdp", "-o", str(out), "--force", "--points", "64", "--hidden",
                            "4", "--adam-iters", "2", "--lbfgs-iters", "2"), stdout=stream)
    assert code == 0 and out.exists()
    err = capsys.readouterr().err
    assert "training anyway (--force)" in err and "fails the MPDI or the boundary" in err
    assert "train adam" in stream.getvalue()


def test_tiny_warns_and_trains(monkeypatch, tmp_path, capsys):
    """Preset tiny is a smoke test: a violation is said (on stderr, also with --quiet), not
    obeyed."""
    monkeypatch.setattr(necessary, "check_necessary", _violated)
    out = tmp_path / "t.ckpt"
    code = run_train(_parse("vdp", "-o", str(out), "--preset", "tiny", "--quiet",
                            "--adam-iters", "1", "--lbfgs-iters", "1"), stdout=io.StringIO())
    assert code == 0 and out.exists()
    assert "preset tiny is a smoke test" in capsys.readouterr().err


def test_help_documents_the_exit_code(capsys):
    assert main(["train", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "5 nothing trained or written: the pre-flight proves" in text
    assert "--force" in text


def test_duffing_has_no_constant_metric_at_any_rate():
    text = undetectable_at_every_rate(load_system("duffing"))
    assert text is not None
    assert "at xhat = (0, 0) the linearisation has the mode 0" in text
    assert "every point of the search grid with x2 = 0" in text
    assert text.endswith("choose a box that excludes the points with x2 = 0")
    assert undetectable_at_every_rate(load_system("vdp")) is None


@pytest.mark.parametrize("preset", ["bound", "certified"])
def test_duffing_design_presets_end_with_the_reason_not_bad_input(preset, tmp_path, capsys):
    out = tmp_path / "d.ckpt"
    code, _, err = run_cli(capsys, "train", "duffing", "--preset", preset, "-o", str(out))
    assert code == EXIT_INFEASIBLE, err
    assert f"preset {preset}: duffing has no certifiable observer of this kind" in err
    assert "not detectable there" in err and "x2 = 0" in err
    assert not out.exists()


@pytest.mark.slow
def test_train_vdp_paper_stops_with_the_reason_and_a_metric_that_passes(tmp_path, capsys):
    """The real thing: `certify train vdp` (preset paper, P = I, lam = 2.5) stops before
    training; the metric it suggests passes the pre-flight and the SDP's routes are named."""
    out = tmp_path / "vdp.ckpt"
    code, stdout, err = run_cli(capsys, "train", "vdp", "-o", str(out))
    assert code == EXIT_INFEASIBLE and not out.exists()
    assert "training vdp" not in stdout  # nothing started
    assert "q = 6 > 0 at xhat = (0, 0), y = (0)" in err
    assert "--preset certified" in err and "--preset bound" in err
    metric = err.split("--metric '", 1)[1].split("'", 1)[0]
    r = necessary.check_necessary(load_system("vdp"), np.array(json.loads(metric)), 2.5)
    assert r.status is Status.PROVED


@pytest.mark.slow
def test_train_vdp_paper_force_trains_a_few_iterations(tmp_path, capsys):
    out = tmp_path / "vdp.ckpt"
    code, stdout, err = run_cli(capsys, "train", "vdp", "-o", str(out), "--force",
                                "--points", "64", "--hidden", "4", "--adam-iters", "3",
                                "--lbfgs-iters", "3")
    assert code == 0, err
    assert "training anyway (--force)" in err and "q = 6 > 0" in err
    ck = checkpoint.load(out)
    assert len(ck.training["history"]["adam"]["total"]) == 3
    assert math.isfinite(ck.training["final"]["total"])
