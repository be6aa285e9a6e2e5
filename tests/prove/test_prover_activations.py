"""The prover on non-tanh gains, end to end through `certify run`.

- a linear injection K plus a small random MLP (silu, gelu) with margin: CERTIFIED (exit 0);
- a planted violation that only SiLU's negative slope creates (k_1 = -a silu(s (xhat_1 - c)):
  dk_1/dxhat_1 = -a s silu'(.) is positive, up to 0.0998 a s, in a slab left of c = 1/4):
  NOT CERTIFIED (exit 1) with a sound witness, recomputed independently; the same weights
  with tanh (tanh' > 0, so the term only helps) are CERTIFIED.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from certify.model import activations
from certify.model.network import GainNetwork
from certify.model.problem import Problem

from ..cli_helpers import FAST_POLICY, run_cli, save_problem
from ..planted import lam_cert_linear, linear_system

pytestmark = pytest.mark.slow

A = np.array([[0.0, 1.0], [-2.0, -3.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [-2.0]])
LAM_CERT = lam_cert_linear(A, C, K)  # of the linear part alone (closed form)
F64 = torch.float64


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def _random_mlp(act: str, lam: float, scale: float = 0.05, seed: int = 0) -> Problem:
    system = linear_system(A, C, lam=lam)
    torch.manual_seed(seed)
    net = GainNetwork(2, 1, (6, 6), K=torch.as_tensor(K), activation=act).double()
    with torch.no_grad():
        net.layers[-1].weight.mul_(scale)
    return Problem(system, net, lam, np.eye(2))


def _slab(act: str, lam: float, a: float = 0.125, s: float = 200.0, c: float = 0.25
          ) -> Problem:
    """k = -a f(s (xhat_1 - c)) e_1 + K (y - C xhat) (a, s, c exact in float32)."""
    system = linear_system(A, C, lam=lam)
    net = GainNetwork(2, 1, (1,), K=torch.as_tensor(K), activation=act).double()
    with torch.no_grad():
        net.layers[0].weight.copy_(torch.tensor([[s, 0.0, 0.0]]))
        net.layers[0].bias.fill_(-s * c)
        net.layers[1].weight.copy_(torch.tensor([[-a], [0.0]]))
        net.layers[1].bias.zero_()
    return Problem(system, net, lam, np.eye(2))


def _run(workdir, capsys, problem: Problem, skip: str = "simulation"
         ) -> tuple[int, dict, str]:
    path = save_problem(workdir / "g.ckpt", problem)
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--skip", skip)
    assert "Traceback" not in err, err
    return code, json.loads((workdir / "c.json").read_text()), out + err


@pytest.mark.parametrize("act", ["silu", "gelu"])
def test_contracting_gain_with_a_non_tanh_mlp_is_certified(workdir, capsys, act):
    code, cert, text = _run(workdir, capsys, _random_mlp(act, LAM_CERT - 0.1))
    assert cert["network"]["activation"] == act
    assert code == 0 and cert["verdict"] == "CERTIFIED", text
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] == "PROVED" and mpdi["upper"] < 0
    assert cert["checks"]["lipschitz"]["status"] == "PROVED"  # local bound through the prover


def test_violation_from_silus_negative_slope_is_found_with_a_sound_witness(workdir, capsys):
    problem = _slab("silu", LAM_CERT - 0.05)
    code, cert, text = _run(workdir, capsys, problem, "simulation,rate")
    assert code == 1 and cert["verdict"] == "NOT CERTIFIED", text
    mpdi = cert["checks"]["mpdi"]
    assert mpdi["status"] == "VIOLATED"
    cex = mpdi["counterexamples"][0]
    assert 0 < cex["sound_bound"] <= cex["value"]
    # independent recomputation: dk_1/dxhat_1 = -a s silu'(s (x1 - c)) by autograd
    x1 = torch.tensor(cex["xhat"][0], dtype=F64, requires_grad=True)
    (dsilu,) = torch.autograd.grad(torch.nn.functional.silu(200.0 * (x1 - 0.25)), x1)
    J = torch.as_tensor(A - K @ C)
    J[0, 0] += -0.125 * float(dsilu)
    D = 0.5 * (J + J.T) + 2.0 * problem.lam * torch.eye(2, dtype=F64)
    assert float(torch.linalg.eigvalsh(D)[-1]) == pytest.approx(cex["value"], rel=1e-9)
    assert cex["xhat"][0] < 0.25  # left of c, where silu' < 0
    # the same weights with tanh only add contraction: certified
    code, cert, text = _run(workdir, capsys, _slab("tanh", LAM_CERT - 0.05), "simulation,rate")
    assert code == 0 and cert["checks"]["mpdi"]["status"] == "PROVED", text


@pytest.mark.parametrize("act", activations.names())
def test_nan_weight_is_unknown_for_every_activation(act):
    """NaN never decides: a NaN weight leaves every box unproved, and no point VIOLATED."""
    from certify.prove.mpdi import prove_mpdi
    from certify.results import Status

    problem = _random_mlp(act, LAM_CERT - 0.1)
    with torch.no_grad():
        problem.network.layers[1].weight[0, 0] = float("nan")
    out = prove_mpdi(problem, max_boxes=64)
    assert out.status is Status.UNKNOWN and out.stats.proved_volume_fraction == 0.0
