"""Solver faults (issue 8.3): degenerate and extreme networks, and a failing interior-point
solver, end in a verified bound or a check ERROR/UNKNOWN with its reason, never a crash that
looks like a verdict (exit 1)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from certify.design import lipsdp
from certify.model.problem import Problem
from certify.results import Status

from ..cli_helpers import FAST_POLICY, A, C, K, run_cli, save_problem
from ..planted import linear_problem

# the Lipschitz check beside the MPDI, which always runs (it is the certificate) on a short
# budget: the verdict is the MPDI's, the Lipschitz result is what these tests read
ONLY_LIPSCHITZ = ("--require", "mpdi,lipschitz", "--skip",
                  "simulation,rate,residual,necessary,bounds", "--max-boxes", "20000")


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def _network_problem(output_scale: float | None) -> Problem:
    """The linear ground truth plus random hidden layers; output layer zero or scaled."""
    pr = linear_problem(A, C, K, lam=0.3, hidden=(6, 6))
    net = pr.network.double()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen))
            layer.bias.copy_(torch.randn(layer.bias.shape, generator=gen))
        out = net.layers[-1]
        if output_scale is None:
            out.weight.zero_()
            out.bias.zero_()
        else:
            out.weight.mul_(output_scale)
    return Problem(pr.system, net, pr.lam, pr.P)


@pytest.mark.slow
def test_zero_output_layer_gives_the_exact_constant_and_certifies(workdir, capsys):
    path = save_problem(workdir / "zero.ckpt", _network_problem(None))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--skip", "simulation")
    assert code == 0, out + err
    lip = json.loads((workdir / "c.json").read_text())["checks"]["lipschitz"]
    exact = float(np.linalg.norm(K, 2))
    assert lip["status"] == "PROVED" and lip["solver"]["solver"] == "closed-form"
    assert exact <= lip["lipsdp"] <= exact * (1 + 1e-12)


@pytest.mark.slow
def test_huge_output_layer_does_not_overflow(workdir, capsys):
    path = save_problem(workdir / "huge.ckpt", _network_problem(1e155))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", *ONLY_LIPSCHITZ)
    assert code in (0, 1, 3), out + err  # the MPDI's verdict; no crash
    lip = json.loads((workdir / "c.json").read_text())["checks"]["lipschitz"]
    assert lip["status"] == "PROVED" and lip["lipsdp_verified"]
    assert 1e150 < lip["sampled"] <= lip["value"] < 1e160
    assert "scaled by" in lip["solver"]["message"]


@pytest.mark.slow
def test_ipm_failure_falls_back_to_clarabel_and_is_rechecked(workdir, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise torch.linalg.LinAlgError("linalg.eigh: The algorithm failed to converge")

    monkeypatch.setattr(lipsdp, "lipsdp_pdip", broken)
    path = save_problem(workdir / "net.ckpt", _network_problem(1.0))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", *ONLY_LIPSCHITZ)
    assert code in (0, 1, 3), out + err  # the MPDI's verdict; no crash
    lip = json.loads((workdir / "c.json").read_text())["checks"]["lipschitz"]
    assert lip["status"] == "PROVED" and lip["lipsdp_verified"]
    assert lip["solver"]["solver"] == "CLARABEL" and "fallback after" in lip["solver"]["message"]


@pytest.mark.slow
def test_both_solvers_failing_is_a_reason_not_a_crash(workdir, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("simulated solver fault")

    monkeypatch.setattr(lipsdp, "lipsdp_pdip", broken)
    monkeypatch.setattr(lipsdp, "_lipsdp_clarabel", broken)
    res = lipsdp.lipsdp_neuron([np.ones((3, 1))], np.ones((1, 3)))
    assert res.status is Status.ERROR and res.value is None
    assert "interior point failed" in res.message and "Clarabel" in res.message
    path = save_problem(workdir / "net.ckpt", _network_problem(1.0))
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", *ONLY_LIPSCHITZ)
    assert code in (0, 1, 3), out + err  # the MPDI's verdict; no crash
    lip = json.loads((workdir / "c.json").read_text())["checks"]["lipschitz"]
    assert "simulated solver fault" in lip["message"] and "Traceback" not in err


def test_power_of_two_scaling_is_exact_and_scaled_back():
    gen = np.random.default_rng(0)
    Ws = [gen.standard_normal((4, 1)), gen.standard_normal((4, 4))]
    Wo = gen.standard_normal((2, 4))
    base = lipsdp.lipsdp_neuron(Ws, Wo)
    big = lipsdp.lipsdp_neuron([np.ldexp(Ws[0], 300), Ws[1]], np.ldexp(Wo, 400))
    assert base.status is Status.PROVED and big.status is Status.PROVED
    assert big.value == pytest.approx(np.ldexp(base.value, 700), rel=1e-6)
