"""Models whose graph is easy to misread: read exactly (values and Jacobians equal the model's
to 1e-12 in float64) or refused with one line naming the node; and the import check, which
evaluates the model itself, refuses any network that is not the model's function."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from certify.model import checkpoint
from certify.model.importers import ModelImportError, chain, read_model
from certify.model.importers.crosscheck import check_import
from certify.model.importers.onnx_model import read_onnx
from certify.model.importers.result import finish
from certify.model.importers.torch_model import read_state_dict, read_torchscript
from certify.model.network import GainNetwork
from certify.spec.system import System

from ..cli_helpers import FAST_POLICY, run_cli
from .test_import import LINEAR_SPEC, export, near_linear_gain

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

F64 = torch.float64


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def spec(n: int, p: int) -> str:
    """A spec with n states and p outputs (the dynamics do not matter to an import)."""
    states = [f"x{i}" for i in range(n)]
    return "\n".join([
        'name = "toy"', f"states = {json.dumps(states)}",
        f"outputs = {json.dumps([f'y{j}' for j in range(p)])}",
        f"f = {json.dumps([f'-{s}' for s in states])}",
        f"h = {json.dumps([states[j % n] for j in range(p)])}",
        "[box]", f"X = {[[-1, 1]] * n}", f"Y = {[[-2, 2]] * p}", "[design]", "lam = 0.1", ""])


def imported_via_cli(capsys, model_path: str, n: int, p: int, *flags: str) -> GainNetwork:
    """`certify import MODEL --system SPEC -o out.ckpt`, then the checkpoint's network."""
    Path("spec.toml").write_text(spec(n, p))
    code, out, err = run_cli(capsys, "import", model_path, "--system", "spec.toml", "-o",
                             "out.ckpt", *flags)
    assert code == 0, err
    return checkpoint.load("out.ckpt").problem.network


def assert_same_function(net: GainNetwork, model, n: int, two_inputs: bool) -> None:
    """Values and Jacobians of the imported network equal the model's to 1e-12 (float64),
    inside the spec's box and far outside it."""
    torch.manual_seed(1)
    z = torch.randn(64, net.n + net.p, dtype=F64) * 3

    def call(v: torch.Tensor) -> torch.Tensor:
        out = model(v[:, :n], v[:, n:]) if two_inputs else model(v)
        return out.reshape(v.shape[0], -1)

    value, jac = net.forward_with_jacobian(z)
    with torch.no_grad():
        expected = call(z)
    reference = torch.func.vmap(torch.func.jacrev(lambda v: call(v[None])[0]))(z)
    torch.testing.assert_close(value, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(jac, reference, rtol=0, atol=1e-12)


def refused(capsys, model_path: str, n: int, p: int, *flags: str) -> str:
    Path("spec.toml").write_text(spec(n, p))
    code, out, err = run_cli(capsys, "import", model_path, "--system", "spec.toml", "-o",
                             "out.ckpt", *flags)
    assert code == 2 and err.startswith("certify: error: ") and err.count("\n") == 1, (out, err)
    assert not Path("out.ckpt").exists()
    return err


# ----- operand order -------------------------------------------------------------------------
class Joined(nn.Module):
    """forward(xhat, y) = l2(tanh(l1(cat(order)))), optionally normalising each input first."""

    def __init__(self, n: int, p: int, y_first: bool, normalise: bool) -> None:
        super().__init__()
        torch.manual_seed(n + 10 * p)
        self.l1, self.l2 = nn.Linear(n + p, 6), nn.Linear(6, n)
        self.y_first, self.normalise = y_first, normalise

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if self.normalise:
            xhat, y = (xhat - 0.25) / 1.5, 3.0 * y + 0.5
        z = torch.cat([y, xhat], dim=1) if self.y_first else torch.cat([xhat, y], dim=-1)
        return self.l2(torch.tanh(self.l1(z)))


@pytest.mark.parametrize("how", ("script", "trace", "onnx17"))
@pytest.mark.parametrize("n, p", ((3, 2), (2, 2)))
@pytest.mark.parametrize("normalise", (False, True))
def test_inputs_joined_as_y_then_xhat_are_read_exactly(workdir, capsys, how, n, p, normalise):
    model = Joined(n, p, True, normalise).double().eval()
    path = export(model, workdir / f"m.{how}", how, (torch.zeros(1, n, dtype=F64),
                                                     torch.zeros(1, p, dtype=F64)))
    net = imported_via_cli(capsys, path, n, p)
    assert_same_function(net, model, n, two_inputs=True)


def test_onnx_concat_of_symbolic_widths_in_either_order(tmp_path):
    """Hand-written ONNX with inputs of unknown width: the Concat's operand order decides."""
    rng = np.random.default_rng(3)
    W1, B1, W2, B2 = rng.normal(size=(4, 5)), rng.normal(size=5), rng.normal(size=(5, 2)), \
        rng.normal(size=2)
    for order in (["xhat", "y"], ["y", "xhat"]):
        graph = helper.make_graph(
            [helper.make_node("Concat", order, ["z"], axis=1, name="join"),
             helper.make_node("MatMul", ["z", "W1"], ["m1"], name="mm1"),
             helper.make_node("Add", ["m1", "B1"], ["u"], name="bias1"),
             helper.make_node("Tanh", ["u"], ["h"], name="act"),
             helper.make_node("Gemm", ["h", "W2", "B2"], ["k"], name="out")],
            "g", [helper.make_tensor_value_info(name, TensorProto.DOUBLE, ["batch", name + "_w"])
                  for name in ("xhat", "y")],
            [helper.make_tensor_value_info("k", TensorProto.DOUBLE, ["batch", 2])],
            [numpy_helper.from_array(a, nm) for nm, a in (("W1", W1), ("B1", B1), ("W2", W2),
                                                          ("B2", B2))])
        path = tmp_path / f"{order[0]}.onnx"
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
        net = read_model(path, 2, 2).network()
        z = rng.normal(size=(16, 4))
        joined = z if order[0] == "xhat" else np.concatenate([z[:, 2:], z[:, :2]], axis=1)
        expected = np.tanh(joined @ W1 + B1) @ W2 + B2
        np.testing.assert_allclose(net(torch.as_tensor(z)).numpy(), expected, rtol=0, atol=1e-12)


# ----- a model input used anywhere but as the chain's input ---------------------------------
class InputAsBias(nn.Module):
    """A skip connection written as F.linear's bias: k = W2 tanh(l1(xhat, y)) + y."""

    def __init__(self) -> None:
        super().__init__()
        self.l1, self.W2 = nn.Linear(4, 6), nn.Parameter(torch.randn(2, 6))

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return F.linear(torch.tanh(self.l1(torch.cat([xhat, y], dim=1))), self.W2, y)


class Residual(nn.Module):
    """k = l2(tanh(l1(xhat, y))) + xhat."""

    def __init__(self) -> None:
        super().__init__()
        self.l1, self.l2 = nn.Linear(4, 6), nn.Linear(6, 2)

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.l2(torch.tanh(self.l1(torch.cat([xhat, y], dim=1)))) + xhat


class InputTwice(nn.Module):
    """xhat joined with itself (n = p: the widths cannot tell)."""

    def __init__(self) -> None:
        super().__init__()
        self.l1, self.l2 = nn.Linear(4, 6), nn.Linear(6, 2)

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.l2(torch.tanh(self.l1(torch.cat([xhat, 2.0 * xhat], dim=1))))


@pytest.mark.parametrize("how", ("script", "onnx17"))
@pytest.mark.parametrize("module, message", [
    (InputAsBias, r"uses the model input '(y|y\.1)' \(y\) as its bias: a skip connection|"
                  r"combines the model input 'y' \(y\) with the output of node .*: a skip"),
    (Residual, r"combines the output of node .* with the model input|"
               r"combines the model input '(xhat|xhat\.1)' \(xhat\) with the output of node"),
    (InputTwice, r"concatenates \(xhat, xhat\); only the two model inputs|"
                 r"input 'xhat': has 2 values; the spec needs n\+p = 4"),  # ONNX drops y
])
def test_other_uses_of_a_model_input_are_refused(workdir, capsys, how, module, message):
    model = module().double().eval()
    path = export(model, workdir / f"m.{how}", how, (torch.zeros(1, 2, dtype=F64),
                                                     torch.zeros(1, 2, dtype=F64)))
    err = refused(capsys, path, 2, 2)
    assert re.search(message, err), err
    assert re.search(r"node '[^']+' \(|input 'xhat'", err), err  # the node (or input) named


def test_inputs_named_against_their_position_are_refused(workdir, capsys):
    class Named(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.l1, self.l2 = nn.Linear(5, 4), nn.Linear(4, 3)

        def forward(self, y: torch.Tensor, xhat: torch.Tensor) -> torch.Tensor:
            return self.l2(torch.tanh(self.l1(torch.cat([xhat, y], dim=1))))

    path = export(Named().double(), workdir / "m.pt", "script", ())
    err = refused(capsys, path, 3, 2)
    assert "their names say y comes first" in err and "forward(xhat, y)" in err


# ----- state_dict: where the activations sit -------------------------------------------------
@pytest.mark.parametrize("modules, message", [
    ([nn.Linear(3, 4), nn.Linear(4, 5), nn.Tanh(), nn.Linear(5, 2)],
     "layer '1': Linear layers 0 and 1 are adjacent modules of the nn.Sequential, so no "
     "activation lies between them"),
    ([nn.Linear(3, 4), nn.Tanh(), nn.Dropout(0.1), nn.Linear(4, 2)],
     "layer '3': 2 modules lie between Linear layers 0 and 3, and a state_dict does not say "
     "which of them are activations"),
    ([nn.Tanh(), nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 2)],
     "layer '1': the first Linear layer is module 1 of the nn.Sequential"),
])
def test_state_dict_activation_placement_follows_module_indices(workdir, capsys, modules,
                                                                message):
    path = export(nn.Sequential(*modules).double(), workdir / "sd.pt", "state_dict", ())
    err = refused(capsys, path, 2, 1, "--activation", "tanh", "--structure", "direct")
    assert message in err


def test_state_dict_with_one_module_between_layers_is_read_exactly(workdir, capsys):
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(3, 4), nn.SiLU(), nn.Linear(4, 5), nn.SiLU(),
                          nn.Linear(5, 2)).double().eval()
    path = export(model, workdir / "sd.pt", "state_dict", ())
    net = imported_via_cli(capsys, path, 2, 1, "--activation", "silu", "--structure", "direct")
    assert_same_function(net, model, 2, two_inputs=False)


# ----- the end-to-end consequence ------------------------------------------------------------
class YFirst(nn.Module):
    """forward(xhat, y) = l2(tanh(l1(cat([y, xhat])))) with a contracting gain's weights as
    stored: read in the wrong order it would be that gain; as it computes, it is another."""

    def __init__(self, good: GainNetwork) -> None:
        super().__init__()
        self.l1, self.l2 = nn.Linear(3, 3).double(), nn.Linear(3, 2).double()
        self.l1.load_state_dict(good.layers[0].state_dict())
        self.l2.load_state_dict(good.layers[1].state_dict())

    def forward(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.l2(torch.tanh(self.l1(torch.cat([y, xhat], dim=1))))


@pytest.mark.slow
def test_a_misreadable_model_gets_the_verdict_of_what_it_computes(workdir, capsys):
    """The stored weights are a CERTIFIED gain; the model applies them to (y, xhat), which
    violates the MPDI. certify must give the verdict of the function the model computes (the
    same as a native checkpoint of it), not CERTIFIED."""
    (workdir / "spec.toml").write_text(LINEAR_SPEC)
    system = System.from_text(LINEAR_SPEC, origin="test")
    good = near_linear_gain("tanh")
    computed = GainNetwork(2, 1, (3,)).double()
    with torch.no_grad():
        W = good.layers[0].weight
        computed.layers[0].weight.copy_(torch.cat([W[:, 1:], W[:, :1]], dim=1))  # (x, y) order
        computed.layers[0].bias.copy_(good.layers[0].bias)
        computed.layers[1].load_state_dict(good.layers[1].state_dict())
    checkpoint.save("computed.ckpt", system=system, network=computed, lam=system.lam)
    export(YFirst(good), "model.pt", "script", (), structure="direct")
    flags = ("--max-boxes", "400", "--skip", "simulation", "--quiet")
    native_code, _, err = run_cli(capsys, "run", "computed.ckpt", *flags)
    code, out, err = run_cli(capsys, "run", "model.pt", "--system", "spec.toml", "--json", "-",
                             *flags)
    assert code == native_code == 1, err
    assert json.loads(out)["verdict"] == "NOT CERTIFIED"


# ----- the import check itself ---------------------------------------------------------------
def two_layer_model(dtype: torch.dtype = F64) -> nn.Sequential:
    torch.manual_seed(4)
    return nn.Sequential(nn.Linear(5, 8), nn.Tanh(), nn.Linear(8, 8), nn.Tanh(),
                         nn.Linear(8, 3)).to(dtype).eval()


def reading(path, how: str):
    if how == "state_dict":
        return read_state_dict(path)
    return (read_onnx if how.startswith("onnx") else read_torchscript)(path, 3, 2)


def misread(model, layer: int, W=None, b=None):
    layers = list(model.layers)
    layers[layer] = replace(layers[layer], W=layers[layer].W if W is None else W,
                            b=layers[layer].b if b is None else b)
    return replace(model, layers=layers, notes=[])


BOX = np.array([[-1.0, 1.0]] * 3 + [[-2.0, 2.0]] * 2)


@pytest.mark.parametrize("how", ("onnx17", "script", "state_dict"))
@pytest.mark.parametrize("dtype", (F64, torch.float32))
def test_import_check_refuses_any_other_function_naming_the_layer(tmp_path, how, dtype):
    """The exact reading passes; a swapped pair of input columns, a dropped bias or a weight
    changed far below any plausible misreading (1e-9 in float64, 1e-3 in float32) is refused,
    naming the first layer whose output differs; a change of one rounding passes."""
    model = two_layer_model(dtype)
    path = export(model, tmp_path / f"m.{how}", how, (torch.zeros(1, 5, dtype=dtype),))
    found = reading(path, how)
    exact = finish(found.layers, "tanh", n=3, p=2, structure=None, source_format=how,
                   path=str(path), sha256="")
    reference = found.reference("tanh")
    assert "agree" in check_import(exact, reference, BOX)
    first, second = exact.layers[0], exact.layers[1]
    small = 1e-9 if dtype == F64 else 1e-3
    W = second.W.copy()
    W[2, 3] *= 1 + small
    cases = [(0, first.W[:, [1, 0, 2, 3, 4]], None, first.where),
             (1, None, np.zeros_like(second.b), second.where),
             (1, W, None, second.where)]
    for index, W, b, where in cases:
        with pytest.raises(ModelImportError, match=re.escape(where) + r": the imported "
                           r"network's values differ from the model's"):
            check_import(misread(exact, index, W, b), reference, BOX)
    W = second.W.copy()
    W[2, 3] = np.nextafter(W[2, 3], np.inf)
    check_import(misread(exact, 1, W), reference, BOX)


def test_import_check_compares_jacobians(tmp_path):
    """A runtime whose derivatives disagree with its values (as a misread derivative would) is
    refused even though the values agree."""
    model = two_layer_model()
    path = export(model, tmp_path / "m.pt", "script", ())
    exact = read_model(path, 3, 2, box=BOX)
    reference = read_torchscript(path, 3, 2).reference("tanh")

    class Skewed:
        what, dtype, deviation = reference.what, reference.dtype, reference.deviation
        values, tensors = reference.values, reference.tensors

        def jacobians(self, z):
            jac = reference.jacobians(z)
            jac[:, 1, 4] *= 1 + 1e-8
            return jac

    with pytest.raises(ModelImportError, match=r"Jacobians \(entry \[1, 4\]; the values agree\)"):
        check_import(exact, Skewed(), BOX)


def test_a_reader_bug_is_caught_by_the_import_check(workdir, capsys, monkeypatch):
    """The safety net from the outside: with the reader's column reordering broken (as it
    once was), `certify import` of a (y, xhat) model exits 2 naming the first layer."""
    model = Joined(3, 2, True, False).double().eval()
    path = export(model, "m.onnx", "onnx17", (torch.zeros(1, 3, dtype=F64),
                                              torch.zeros(1, 2, dtype=F64)))
    monkeypatch.setattr(chain.ChainBuilder, "z_columns", lambda self, order: np.arange(5))
    err = refused(capsys, path, 3, 2)
    assert "node '/l1/Gemm' (Gemm): the imported network's values differ from the model's" in err
