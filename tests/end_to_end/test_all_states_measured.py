"""Systems whose states are all measured (h = x, n = p): ker dh = {0}, so the necessary
condition is vacuous (there is no q), and every consumer of q (the pre-flight, its
presenter, the report's maps, training's pre-flight) must take that in its stride:
`certify check` passes saying why, `certify run` decides and writes its JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from certify.checks.necessary import CHECK, check_necessary
from certify.design.manifold import manifold_quantity
from certify.model import checkpoint
from certify.model.network import GainNetwork
from certify.results import Status
from certify.spec.system import System

from ..cli_helpers import run_cli

#: Van der Pol with both states measured
FULL = """
name = "vdp_full"
description = "Van der Pol, both states measured"
states = ["x1", "x2"]
outputs = ["y1", "y2"]
f = ["x2", "-x1 + x2*(1 - x1**2)"]
h = ["x1", "x2"]

[box]
X = [[-2.0, 2.0], [-3.0, 3.0]]
Y = [[-2.0, 2.0], [-3.0, 3.0]]

[design]
lam = 0.5
"""

#: the same with a nonlinear output map of full column rank (d(x2^3 + x2)/dx2 >= 1)
FULL_NONLINEAR = FULL.replace('h = ["x1", "x2"]', 'h = ["x1", "x2**3 + x2"]').replace(
    "[-3.0, 3.0]]\n\n[design]", "[-30.0, 30.0]]\n\n[design]")

SMALL_RUN = ("--grid-points", "3000", "--max-boxes", "20000",
             "--adversarial-starts", "4", "--sim-time", "0.5", "--no-config")


def full_system() -> System:
    return System.from_text(FULL, origin="test")


def test_preflight_is_vacuous_and_proved():
    r = check_necessary(full_system(), np.eye(2), 0.5)
    assert r.status is Status.PROVED
    assert r.message.startswith("vacuous: all states are measured")
    assert r.q_max == -math.inf and r.witness is None
    shown = CHECK.present(r, type("Cert", (), {"lam": 0.5, "P": np.eye(2).tolist()})())
    assert shown.sampled.value is None and "every state is measured" in shown.sampled.missing
    assert shown.proved.value is None


def test_q_is_minus_infinity_everywhere():
    x = torch.tensor([[0.0, 0.0], [1.5, -2.0]], dtype=torch.float64)
    q = manifold_quantity(full_system(), np.eye(2), 0.5, x)
    assert q.tolist() == [-math.inf, -math.inf]


def test_nonlinear_full_rank_output_is_vacuous_at_samples_only():
    system = System.from_text(FULL_NONLINEAR, origin="test")
    r = check_necessary(system, np.eye(2), 0.5, grid_points=2000)
    assert r.status is Status.UNKNOWN  # the rank is sampled, not proved
    assert "full column rank at all" in r.message and r.q_max == -math.inf


def test_check_command_says_vacuous(tmp_path, capsys):
    spec = tmp_path / "full.toml"
    spec.write_text(FULL)
    code, out, _ = run_cli(capsys, "check", str(spec), "--no-synthesis")
    assert code == 0, out
    assert "vacuous: all states are measured" in out and "passes the pre-flight" in out


def linear_full_state(path) -> str:
    """k = 20 (y - xhat): D = He{Jf} - 20 I + lam I < 0 on the box (|Jf| <= 13 there)."""
    system = full_system()
    net = GainNetwork(2, 2, (4,), structure="direct", K=20.0 * torch.eye(2, dtype=torch.float64))
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.zero_()
            layer.bias.zero_()
    checkpoint.save(path, system=system, network=net.double(), lam=0.5, P=np.eye(2))
    return str(path)


@pytest.mark.slow
def test_run_certifies_a_linear_gain_and_writes_json(tmp_path, capsys):
    ckpt = linear_full_state(tmp_path / "full.ckpt")
    out_json = tmp_path / "full.json"
    code, out, err = run_cli(capsys, "run", ckpt, "--json", str(out_json), *SMALL_RUN)
    assert code == 0, out + err
    data = json.loads(out_json.read_text())
    assert data["verdict"] == "CERTIFIED"
    assert data["checks"]["necessary"]["status"] == "PROVED"
    assert data["checks"]["necessary"]["message"].startswith("vacuous")


@pytest.mark.slow
def test_train_tiny_then_run_decides(tmp_path, capsys):
    spec = tmp_path / "full.toml"
    spec.write_text(FULL)
    ckpt, out_json = tmp_path / "tiny.ckpt", tmp_path / "tiny.json"
    code, out, err = run_cli(capsys, "train", str(spec), "--preset", "tiny", "-o", str(ckpt),
                             "--adam-iters", "5", "--lbfgs-iters", "5", "--quiet")
    assert code == 0, out + err
    code, out, err = run_cli(capsys, "run", str(ckpt), "--json", str(out_json), *SMALL_RUN)
    assert code in (0, 1, 3), out + err  # a verdict, never the internal error (4)
    assert json.loads(out_json.read_text())["checks"]["necessary"]["status"] == "PROVED"
