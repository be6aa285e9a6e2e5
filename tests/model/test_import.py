"""Models trained elsewhere: torch -> ONNX / TorchScript / state_dict -> certify gives the same
gain (values and Jacobians within 1e-12 in float64) and the same certificate as a native
checkpoint; every activation pattern the exporters write is recognised."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from torch import nn

from certify.model import checkpoint
from certify.model.importers import read_model
from certify.model.importers.result import supported_activations
from certify.model.network import GainNetwork
from certify.spec.system import System

from ..cli_helpers import FAST_POLICY, run_cli
from ..conftest import SPEC_3X2

TORCH_ACTIVATIONS = {"tanh": nn.Tanh, "sigmoid": nn.Sigmoid, "softplus": nn.Softplus,
                     "silu": nn.SiLU, "elu": nn.ELU, "gelu": nn.GELU}
ACTIVATIONS = sorted(TORCH_ACTIVATIONS)
EXPORTERS = ("onnx17", "onnx20", "script", "trace", "state_dict")


def mlp(activation: str, n: int = 3, p: int = 2, out: int | None = None, seed: int = 0
        ) -> nn.Sequential:
    """A float64 gain MLP z = (xhat, y) -> out, two hidden layers."""
    torch.manual_seed(seed)
    act = TORCH_ACTIVATIONS[activation]
    return nn.Sequential(nn.Linear(n + p, 6), act(), nn.Linear(6, 5), act(),
                         nn.Linear(5, n * p if out is None else out)).double().eval()


def export(model: nn.Module, path, how: str, inputs: tuple[torch.Tensor, ...],
           structure: str | None = None) -> str:
    """Write `model` the way a user's training script would (with `structure`, recorded as
    the README says: ONNX metadata_props, a TorchScript extra file)."""
    path = str(path)
    if how.startswith("onnx"):
        names = ["z"] if len(inputs) == 1 else ["xhat", "y"]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(model, inputs, path, dynamo=False, opset_version=int(how[4:]),
                              input_names=names, output_names=["k"],
                              dynamic_axes={name: {0: "batch"} for name in names})
        if structure is not None:
            import onnx

            proto = onnx.load(path)
            onnx.helper.set_model_props(proto, {"certify.structure": structure})
            onnx.save(proto, path)
    elif how in ("script", "trace"):
        module = torch.jit.script(model) if how == "script" else torch.jit.trace(model, inputs)
        extra = {} if structure is None else {"certify.structure": structure}
        torch.jit.save(module, path, _extra_files=extra)
    else:
        torch.save(model.state_dict(), path)
    return path


def reference_jacobian(model: nn.Module, z: torch.Tensor) -> torch.Tensor:
    return torch.func.vmap(torch.func.jacrev(lambda v: model(v.unsqueeze(0))[0]))(z)


@pytest.mark.parametrize("how", EXPORTERS)
@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.slow
def test_imported_gain_equals_torch(tmp_path, activation, how):
    model = mlp(activation)
    z0 = torch.zeros(1, 5, dtype=torch.float64)
    path = export(model, tmp_path / "model.bin", how, (z0,))
    imported = read_model(path, 3, 2, activation=activation if how == "state_dict" else None)
    assert (imported.activation, imported.structure, imported.hidden) == (
        activation, "structural", [6, 5])
    linears = [m for m in model if isinstance(m, nn.Linear)]
    for layer, ref in zip(imported.layers, linears, strict=True):  # bit for bit
        assert np.array_equal(layer.W, ref.weight.detach().numpy())
        assert np.array_equal(layer.b, ref.bias.detach().numpy())
    net = imported.network()
    z = torch.randn(64, 5, dtype=torch.float64) * 2
    value, jac = net.forward_with_jacobian(z)
    with torch.no_grad():
        expected = model(z)
    torch.testing.assert_close(value, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(jac, reference_jacobian(model, z), rtol=0, atol=1e-12)


class TwoInputs(nn.Module):
    """forward(xhat, y) = seq(cat(xhat, y)), reshaped to [batch, n, p] (structural G)."""

    def __init__(self, seq: nn.Sequential, n: int, p: int) -> None:
        super().__init__()
        self.seq, self.n, self.p = seq, n, p

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.seq(torch.cat([xhat, y], dim=1)).reshape(-1, self.n, self.p)


@pytest.mark.parametrize("how", ("onnx17", "script"))
def test_two_inputs_concatenated_and_output_reshaped(tmp_path, how):
    model = TwoInputs(mlp("tanh"), 3, 2).double().eval()
    inputs = (torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 2, dtype=torch.float64))
    imported = read_model(export(model, tmp_path / "m.bin", how, inputs), 3, 2)
    xhat, y = torch.randn(16, 3, dtype=torch.float64), torch.randn(16, 2, dtype=torch.float64)
    value = imported.network()(torch.cat([xhat, y], dim=1)).reshape(-1, 3, 2)
    torch.testing.assert_close(value, model(xhat, y).detach(), rtol=0, atol=1e-12)


def test_every_registered_activation_is_importable():
    """Each activation certify can verify has its torch module here (and so its ONNX and
    TorchScript forms are tested); a new one in certify.model.activations needs a line above."""
    assert set(supported_activations()) == set(TORCH_ACTIVATIONS)


# ----- the same certificate as a native checkpoint ------------------------------------------
LINEAR_SPEC = """
name = "linear"
states = ["x1", "x2"]
outputs = ["y"]
f = ["x2", "-2*x1 - 3*x2"]
h = ["x1"]
[box]
X = [[-1, 1], [-1, 1]]
Y = [[-1, 1]]
[design]
lam = 0.3
"""


def near_linear_gain(activation: str, eps: float = 0.05) -> GainNetwork:
    """For tanh: N(z) ~ K (y - x1) with K = (1, -2) through tanh(eps (y - x1)) / eps, plus two
    small random units, a contracting observer of the linear spec (lam_cert ~ 0.44 > 0.3).
    For other activations the same weights (certified or not, the numbers must agree)."""
    torch.manual_seed(3)
    net = GainNetwork(2, 1, (3,), activation=activation).double()
    with torch.no_grad():
        net.layers[0].weight.mul_(0.3)
        net.layers[0].weight[0] = torch.tensor([-eps, 0.0, eps])
        net.layers[0].bias.zero_()
        net.layers[1].weight.mul_(0.01)
        net.layers[1].weight[:, 0] = torch.tensor([1.0, -2.0]) / eps
    return net.requires_grad_(False)


def as_sequential(net: GainNetwork, activation: str) -> nn.Sequential:
    """The same gain as the plain nn.Sequential a user's training script would export."""
    modules: list[nn.Module] = []
    for i, layer in enumerate(net.layers):
        linear = nn.Linear(layer.in_features, layer.out_features).double()
        linear.load_state_dict(layer.state_dict())
        modules += [linear] if i == len(net.layers) - 1 else [linear,
                                                              TORCH_ACTIVATIONS[activation]()]
    return nn.Sequential(*modules).eval()


def _numbers(path) -> dict:
    """A certificate's content without run times (durations, rates, closed volume over
    time), dates and where it was read from (the input's name, also inside the commands a
    message suggests, reads `<input>`)."""
    cert = json.loads((path).read_text())
    source = cert["checkpoint"]["path"]

    def strip(obj):
        if isinstance(obj, dict):
            return {k: strip(v) for k, v in obj.items()
                    if not k.endswith(("seconds", "per_second", "_history"))}
        if isinstance(obj, list):
            return [strip(v) for v in obj]
        if isinstance(obj, str):
            return obj.replace(f"certify run {source} ", "certify run <input> ")
        return obj

    for key in ("timings", "created", "checkpoint"):
        cert.pop(key)
    return strip(cert)


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.slow
def test_certificate_numbers_equal_native_checkpoint(tmp_path, monkeypatch, capsys,
                                                     activation):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    (tmp_path / "spec.toml").write_text(LINEAR_SPEC)
    system = System.from_text(LINEAR_SPEC, origin="test")
    net = near_linear_gain(activation)
    checkpoint.save(tmp_path / "native.ckpt", system=system, network=net, lam=system.lam)
    export(as_sequential(net, activation), tmp_path / "model.onnx", "onnx17",
           (torch.zeros(1, 3, dtype=torch.float64),), structure="direct")  # p = 1: recorded
    flags = ("--max-boxes", "400", "--skip", "simulation")
    native_code, _, err = run_cli(capsys, "run", "native.ckpt", "--json", "native.json", *flags)
    assert native_code in (0, 1, 3), err
    code, _, err = run_cli(capsys, "run", "model.onnx", "--system", "spec.toml", "--json",
                           "onnx.json", *flags)
    assert code == native_code, err
    code, out, err = run_cli(capsys, "import", "model.onnx", "--system", "spec.toml",
                             "-o", "imported.ckpt")
    assert code == 0 and "imported.ckpt" in out, err
    code, _, err = run_cli(capsys, "run", "imported.ckpt", "--json", "imported.json", *flags)
    assert code == native_code, err
    native = _numbers(tmp_path / "native.json")
    if activation == "tanh":
        assert native["verdict"] == "CERTIFIED" and native["checks"]["mpdi"]["status"] == "PROVED"
    assert _numbers(tmp_path / "onnx.json") == native
    assert _numbers(tmp_path / "imported.json") == native
    onnx_cert = json.loads((tmp_path / "onnx.json").read_text())
    assert onnx_cert["checkpoint"]["path"] == "model.onnx"
    loaded = checkpoint.load(tmp_path / "imported.ckpt")
    assert loaded.training["imported_from"]["format"] == "onnx"
    assert loaded.training["imported_from"]["sha256"] == onnx_cert["checkpoint"]["sha256"]


def test_lam_and_metric_flags_override_the_spec(tmp_path, capsys):
    (tmp_path / "spec.toml").write_text(SPEC_3X2)
    path = export(mlp("tanh"), tmp_path / "m.onnx", "onnx17",
                  (torch.zeros(1, 5, dtype=torch.float64),))
    out = str(tmp_path / "m.ckpt")
    P = "[[1, 0, 0], [0, 2, 0], [0, 0, 3]]"
    code, _, err = run_cli(capsys, "import", path, "--system", str(tmp_path / "spec.toml"),
                           "--lam", "1.5", "--metric", P, "-o", out)
    assert code == 0, err
    problem = checkpoint.load(out).problem
    assert problem.lam == 1.5 and np.array_equal(problem.P, np.diag([1.0, 2.0, 3.0]))
    code, _, err = run_cli(capsys, "import", path, "--system", str(tmp_path / "spec.toml"),
                           "-o", out)
    problem = checkpoint.load(out).problem
    assert code == 0 and problem.lam == 0.5 and problem.P[0, 1] == 0.1



STATE_METRIC = """
[design.state_metric]
exponents = [[0, 0], [2, 0], [1, 1]]
coefficients = [[[2, 0.5], [0.5, 1]], [[0.1, 0], [0, 0.05]], [[0, 0.2], [0.2, 0]]]
"""


def test_a_spec_metric_that_follows_the_state_travels_with_the_import(tmp_path, capsys):
    """[design.state_metric] in the spec: the imported checkpoint holds that polynomial,
    number for number; a malformed one is refused with one line naming the table (exit 2)
    and nothing is written."""
    (tmp_path / "spec.toml").write_text(LINEAR_SPEC + STATE_METRIC)
    path = export(mlp("tanh", n=2, p=1), tmp_path / "m.onnx", "onnx17",
                  (torch.zeros(1, 3, dtype=torch.float64),), structure="direct")
    out = str(tmp_path / "m.ckpt")
    code, _, err = run_cli(capsys, "import", path, "--system", str(tmp_path / "spec.toml"),
                           "-o", out)
    assert code == 0, err
    metric = checkpoint.load(out).problem.metric
    assert metric is not None and metric.exponents.tolist() == [[0, 0], [2, 0], [1, 1]]
    assert metric.coefficients[2, 0, 1] == 0.2 and metric.coefficients[0, 0, 0] == 2.0
    bad = STATE_METRIC.replace("[[0, 0.2], [0.2, 0]]", "[[0, 0.2], [0.3, 0]]")
    (tmp_path / "bad.toml").write_text(LINEAR_SPEC + bad)
    code, _, err = run_cli(capsys, "import", path, "--system", str(tmp_path / "bad.toml"),
                           "-o", str(tmp_path / "bad.ckpt"))
    assert code == 2 and "[design.state_metric]" in err and "symmetric" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "bad.ckpt").exists()


class Normalised(nn.Module):
    """A gain trained on normalised inputs: seq((z - mean) / std), per input or joined."""

    def __init__(self, seq: nn.Sequential, two_inputs: bool) -> None:
        super().__init__()
        self.seq, self.two_inputs = seq, two_inputs
        mean, std = [0.3, -0.2, 0.1, 0.5, -0.4], [2.0, 0.7, 1.3, 0.9, 3.0]
        for name, value in (("mean", mean), ("std", std), ("mean_x", mean[:3]),
                            ("std_x", std[:3]), ("mean_y", mean[3:]), ("std_y", std[3:])):
            self.register_buffer(name, torch.tensor(value, dtype=torch.float64))

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if self.two_inputs:
            xs = (xhat - self.mean_x) / self.std_x
            ys = 2.0 * (y - self.mean_y) / self.std_y
            return self.seq(torch.cat([xs, ys], dim=1))
        return self.seq((torch.cat([xhat, y], dim=1) - self.mean) / self.std)


@pytest.mark.parametrize("how", ("onnx17", "script"))
@pytest.mark.parametrize("two_inputs", (False, True))
def test_input_normalisation_is_folded_into_the_first_layer(tmp_path, how, two_inputs):
    model = Normalised(mlp("tanh"), two_inputs).eval()
    inputs = (torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 2, dtype=torch.float64))
    imported = read_model(export(model, tmp_path / "m.bin", how, inputs), 3, 2)
    assert imported.hidden == [6, 5] and any("normalisation folded" in n for n in imported.notes)
    xhat, y = torch.randn(32, 3, dtype=torch.float64), torch.randn(32, 2, dtype=torch.float64)
    value, jac = imported.network().forward_with_jacobian(torch.cat([xhat, y], dim=1))
    with torch.no_grad():
        expected = model(xhat, y)
    torch.testing.assert_close(value, expected, rtol=0, atol=1e-12)
    reference = torch.func.vmap(torch.func.jacrev(
        lambda v: model(v[None, :3], v[None, 3:])[0]))(torch.cat([xhat, y], dim=1))
    torch.testing.assert_close(jac, reference, rtol=0, atol=1e-12)
