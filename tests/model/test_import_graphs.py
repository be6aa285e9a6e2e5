"""Hand-written ONNX graphs: the forms other exporters write (MatMul + Add, GELU's factors in
another order) are read as the same network; graphs that are not one chain are refused."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from torch import nn

from certify.model.importers import ModelImportError, read_model

from .test_import import export

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

RNG = np.random.default_rng(7)
W1, B1 = RNG.normal(size=(3, 4)), RNG.normal(size=4)  # MatMul layout: [in, out]
W2, B2 = RNG.normal(size=(4, 2)), RNG.normal(size=2)


def write(path, nodes, output="k", extra=()) -> str:
    """A float64 graph z[batch, 3] -> output, with the two layers' weights as initializers."""
    inits = [numpy_helper.from_array(a, name) for name, a in
             (("W1", W1), ("B1", B1), ("W2", W2), ("B2", B2), *extra)]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("z", TensorProto.DOUBLE, ["batch", 3])],
        [helper.make_tensor_value_info(output, TensorProto.DOUBLE, ["batch", 2])], inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    return str(path)


def scalar(name: str, value: float) -> tuple[str, np.ndarray]:
    return name, np.array(value, dtype=np.float64)


def first_layer() -> list:
    return [helper.make_node("MatMul", ["z", "W1"], ["m1"], name="mm1"),
            helper.make_node("Add", ["m1", "B1"], ["u"], name="bias1")]


def second_layer(h: str) -> list:
    return [helper.make_node("MatMul", [h, "W2"], ["m2"], name="mm2"),
            helper.make_node("Add", ["B2", "m2"], ["k"], name="bias2")]


GELU_REORDERED = [  # (x * 0.5) * (erf(x * 0.7071...) + 1), constants as float32 roundings
    helper.make_node("Mul", ["u", "half"], ["hu"], name="g1"),
    helper.make_node("Mul", ["u", "isqrt2"], ["s"], name="g2"),
    helper.make_node("Erf", ["s"], ["e"], name="g3"),
    helper.make_node("Add", ["e", "one"], ["e1"], name="g4"),
    helper.make_node("Mul", ["hu", "e1"], ["h"], name="g5")]
GELU_CONSTANTS = (scalar("half", 0.5), scalar("one", 1.0),
                  scalar("isqrt2", float(np.float32(1 / np.sqrt(2)))))
SILU = [helper.make_node("Sigmoid", ["u"], ["sg"], name="s1"),
        helper.make_node("Mul", ["sg", "u"], ["h"], name="s2")]


@pytest.mark.parametrize("activation, nodes, extra", [
    ("tanh", [helper.make_node("Tanh", ["u"], ["h"], name="act")], ()),
    ("silu", SILU, ()),
    ("gelu", GELU_REORDERED, GELU_CONSTANTS),
])
def test_matmul_add_and_reordered_patterns(tmp_path, activation, nodes, extra):
    path = write(tmp_path / "m.onnx", first_layer() + nodes + second_layer("h"), extra=extra)
    imported = read_model(path, 2, 1, structure="direct")
    assert imported.activation == activation and imported.hidden == [4]
    assert np.array_equal(imported.layers[0].W, W1.T) and np.array_equal(imported.layers[1].b, B2)


def test_matmul_add_network_values(tmp_path):
    path = write(tmp_path / "m.onnx", first_layer() + [
        helper.make_node("Tanh", ["u"], ["h"], name="act")] + second_layer("h"))
    net = read_model(path, 2, 1, structure="direct").network()
    z = RNG.normal(size=(8, 3))
    expected = np.tanh(z @ W1 + B1) @ W2 + B2
    np.testing.assert_allclose(net(torch.as_tensor(z)).numpy(), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("nodes, extra, message", [
    ([helper.make_node("Tanh", ["u"], ["h"], name="act"),
      helper.make_node("MatMul", ["h", "W2"], ["dead"], name="dead"),
      helper.make_node("Identity", ["u"], ["k"], name="out")], (),
     "node 'mm1' (MatMul): its output or input is shared with another branch"),
    ([helper.make_node("Tanh", ["u"], ["h"], name="act"),
      helper.make_node("MatMul", ["h", "W2"], ["a"], name="head"),
      helper.make_node("MatMul", ["z", "Wskip"], ["b"], name="skip"),
      helper.make_node("Add", ["a", "b"], ["k"], name="sum")],
     (("Wskip", RNG.normal(size=(3, 2))),),
     "node 'skip' (MatMul): reads an earlier layer's output"),
    ([helper.make_node("Mul", ["u", "half"], ["h"], name="scale")] + second_layer("h")[:1]
     + [helper.make_node("Identity", ["m2"], ["k"], name="out")], (scalar("half", 0.5),),
     "node 'scale' (Mul): the elementwise operations ending here are not a supported "
     "activation"),
    (GELU_REORDERED[:3] + [helper.make_node("Add", ["e", "one"], ["e1"], name="g4"),
                           helper.make_node("Mul", ["hu", "e1"], ["h"], name="g5")]
     + second_layer("h"), (scalar("half", 0.5), scalar("one", 1.0), scalar("isqrt2", 0.7)),
     "node 'g5' (Mul): the elementwise operations ending here are not a supported"),
    ([helper.make_node("Tanh", ["u"], ["h"], name="act"),
      helper.make_node("MatMul", ["h", "W2"], ["m2"], name="mm2"),
      helper.make_node("Add", ["m2", "Bbad"], ["k"], name="bias2")],
     (("Bbad", np.array([1.0, np.inf])),), "node 'bias2' (Add): weight 'Bbad' contains NaN"),
])
def test_graphs_that_are_not_a_supported_chain_are_refused(tmp_path, nodes, extra, message):
    path = write(tmp_path / "m.onnx", first_layer() + nodes, extra=extra)
    with pytest.raises(ModelImportError, match=re.escape(message)):
        read_model(path, 2, 1, structure="direct")


def test_torchscript_dropout_in_eval_mode_is_a_no_op(tmp_path):
    model = nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Dropout(0.1), nn.Linear(4, 2))
    model = model.double().eval()
    imported = read_model(export(model, tmp_path / "d.pt", "script", ()), 2, 1,
                          structure="direct")
    assert imported.hidden == [4]
    model.train()
    with pytest.raises(ModelImportError, match=r"\(aten::dropout\): dropout in training mode"):
        read_model(export(model, tmp_path / "t.pt", "script", ()), 2, 1, structure="direct")


def test_structure_for_p_1_and_activation_that_disagrees(tmp_path):
    path = write(tmp_path / "m.onnx", first_layer() + [
        helper.make_node("Tanh", ["u"], ["h"], name="act")] + second_layer("h"))
    with pytest.raises(ModelImportError, match=r"with one output \(p = 1\) the 2 values .* "
                                               r"\(--structure direct\) or .*"
                                               r"\(--structure structural\); say which"):
        read_model(path, 2, 1)  # n = n*p = 2: never guessed
    assert read_model(path, 2, 1, structure="direct").structure == "direct"
    structural = read_model(path, 2, 1, structure="structural")
    assert structural.structure == "structural"
    assert structural.network().architecture()["structure"] == "structural"
    with pytest.raises(ModelImportError, match=r"uses tanh \(node 'act' \(Tanh\)\); "
                                               "--activation sigmoid disagrees"):
        read_model(path, 2, 1, activation="sigmoid", structure="direct")
    assert read_model(path, 2, 1, activation="Tanh", structure="direct").activation == "tanh"


def test_transposed_weight_initializer(tmp_path):
    """Transpose of a weight initializer (as some exporters write) -> MatMul reads W."""
    nodes = [helper.make_node("Transpose", ["W1t"], ["W1r"], name="tr", perm=[1, 0]),
             helper.make_node("MatMul", ["z", "W1r"], ["m1"], name="mm1"),
             helper.make_node("Add", ["m1", "B1"], ["u"], name="bias1"),
             helper.make_node("Tanh", ["u"], ["h"], name="act")] + second_layer("h")
    path = write(tmp_path / "m.onnx", nodes, extra=(("W1t", W1.T.copy()),))
    imported = read_model(path, 2, 1, structure="direct")
    assert np.array_equal(imported.layers[0].W, W1.T)
    with pytest.raises(ModelImportError, match=r"node 'tr2' \(Transpose\): its operand"):
        read_model(write(tmp_path / "bad.onnx", first_layer() + [
            helper.make_node("Transpose", ["u"], ["h"], name="tr2")] + second_layer("h")), 2, 1,
            structure="direct")


class HandWritten(nn.Module):
    """A gain written with parameters and matmuls instead of nn.Linear."""

    def __init__(self) -> None:
        super().__init__()
        self.W1 = nn.Parameter(torch.as_tensor(W1.T.copy()))  # [out, in]
        self.b1 = nn.Parameter(torch.as_tensor(B1))
        self.W2 = nn.Parameter(torch.as_tensor(W2.T.copy()))
        self.b2 = nn.Parameter(torch.as_tensor(B2))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = torch.nn.functional.silu(z @ self.W1.t() + self.b1)
        return torch.matmul(h, self.W2.T) + self.b2


def test_torchscript_written_by_hand(tmp_path):
    model = HandWritten().double()
    imported = read_model(export(model, tmp_path / "h.pt", "script", ()), 2, 1,
                          structure="direct")
    assert imported.activation == "silu" and imported.hidden == [4]
    z = torch.as_tensor(RNG.normal(size=(8, 3)))
    torch.testing.assert_close(imported.network()(z), model(z).detach(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("op, inputs, message", [
    ("Div", ["one", "z"], "node 'pre' (Div): divides by the input or by zero"),
    ("Div", ["z", "zero"], "node 'pre' (Div): divides by the input or by zero"),
    ("Sub", ["z", "three"], "node 'pre' (Sub): constant 'three' of shape [2] does not match"),
    ("Tanh", ["z"], "node 'pre' (Tanh): acts on the model input before any linear layer"),
])
def test_input_operations_that_are_not_a_normalisation(tmp_path, op, inputs, message):
    nodes = [helper.make_node(op, inputs, ["zn"], name="pre"),
             helper.make_node("MatMul", ["zn", "W1"], ["m1"], name="mm1"),
             helper.make_node("Add", ["m1", "B1"], ["u"], name="bias1"),
             helper.make_node("Tanh", ["u"], ["h"], name="act")] + second_layer("h")
    extra = (scalar("one", 1.0), scalar("zero", 0.0), ("three", np.array([1.0, 2.0])))
    with pytest.raises(ModelImportError, match=re.escape(message)):
        read_model(write(tmp_path / "m.onnx", nodes, extra=extra), 2, 1, structure="direct")
