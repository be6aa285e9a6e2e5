"""Refusals of models from elsewhere through the real command line: exit 2, one line naming
the node (name and operator), nothing written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from certify.model import checkpoint

from ..cli_helpers import run_cli, save_linear
from ..conftest import LINEAR_SPEC
from .test_import import export, mlp

Z = (torch.zeros(1, 3, dtype=torch.float64),)  # the linear spec: n = 2, p = 1


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.toml").write_text(LINEAR_SPEC)
    return tmp_path


def refused(capsys, *argv) -> str:
    """The one error line of a refused `certify import ... -o out.ckpt` (nothing written)."""
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, (out, err)
    assert err.startswith("certify: error: ") and err.count("\n") == 1, err
    return err


def import_refused(capsys, model: str, *flags: str) -> str:
    err = refused(capsys, "import", model, "--system", "spec.toml", "-o", "out.ckpt", *flags)
    assert not Path("out.ckpt").exists()
    return err


class WithSin(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.seq = mlp("tanh", n=2, p=1, out=2)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.seq(torch.sin(z))


def relu_mlp() -> nn.Sequential:
    return nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2)).double()


def test_relu_is_refused_naming_the_node(workdir, capsys):
    err = import_refused(capsys, export(relu_mlp(), "relu.onnx", "onnx17", Z))
    assert "node '/1/Relu' (Relu): ReLU is not C^1" in err and "Theorem 1" in err
    err = import_refused(capsys, export(relu_mlp(), "relu.pt", "script", Z))
    assert "(aten::relu): ReLU is not C^1" in err


def test_unknown_operator_is_refused_naming_the_node(workdir, capsys):
    err = import_refused(capsys, export(WithSin().double(), "sin.onnx", "onnx17", Z))
    assert "node '/Sin' (Sin): unsupported operator Sin" in err
    err = import_refused(capsys, export(WithSin().double(), "sin.pt", "script", Z))
    assert "(aten::sin): unsupported operation" in err


def test_wrong_shapes_are_refused(workdir, capsys):
    err = import_refused(capsys, export(mlp("tanh", n=3, p=1, out=2), "wide.onnx", "onnx17",
                                        (torch.zeros(1, 4, dtype=torch.float64),)))
    assert "input 'z': has 4 values; the spec needs n+p = 3" in err
    err = import_refused(capsys, export(mlp("tanh", n=2, p=1, out=3), "out3.onnx", "onnx17",
                                        Z))
    assert "node '/4/Gemm' (Gemm): the output has 3 values; the spec needs n = 2" in err
    err = import_refused(capsys, export(mlp("tanh", n=3, p=1, out=2), "wide.pt", "state_dict",
                                        Z), "--activation", "tanh")
    assert "layer '0': the first layer reads 4 values; the spec needs n+p = 3" in err


def test_nan_weight_is_refused_naming_node_and_weight(workdir, capsys):
    model = mlp("tanh", n=2, p=1, out=2)
    with torch.no_grad():
        model[2].weight[1, 3] = float("nan")
    err = import_refused(capsys, export(model, "nan.onnx", "onnx17", Z))
    assert "node '/2/Gemm' (Gemm): weight '2.weight' contains NaN or Inf" in err
    err = import_refused(capsys, export(model, "nan.pt", "state_dict", Z), "--activation", "tanh")
    assert "layer '2': weight '2.weight' contains NaN or Inf" in err


def test_state_dict_needs_a_c1_activation(workdir, capsys):
    path = export(mlp("tanh", n=2, p=1, out=2), "sd.pt", "state_dict", Z)
    assert "give --activation NAME" in import_refused(capsys, path)
    err = import_refused(capsys, path, "--activation", "relu")
    assert "activation 'relu' is refused" in err and "D would be discontinuous" in err
    assert "unknown activation 'mish'" in import_refused(capsys, path, "--activation", "mish")
    code, out, err = run_cli(capsys, "import", path, "--system", "spec.toml",
                             "--activation", "tanh", "--structure", "direct", "-o", "sd.ckpt")
    assert code == 0 and "state_dict, tanh, hidden [6, 5], direct" in out, err


def test_other_graphs_refused(workdir, capsys):
    elu = nn.Sequential(nn.Linear(3, 4), nn.ELU(alpha=0.5), nn.Linear(4, 2)).double()
    err = import_refused(capsys, export(elu, "elu.onnx", "onnx17", Z))
    assert "node '/1/Elu' (Elu): ELU with alpha = 0.5" in err
    stacked = nn.Sequential(nn.Linear(3, 4), nn.Linear(4, 2)).double()
    err = import_refused(capsys, export(stacked, "stacked.onnx", "onnx17", Z))
    assert "(Gemm): reads node '/0/Gemm' (Gemm) directly: two linear layers" in err
    ends = nn.Sequential(nn.Linear(3, 2), nn.Tanh()).double()
    err = import_refused(capsys, export(ends, "ends.onnx", "onnx17", Z))
    assert "node '/1/Tanh' (Tanh): the output passes through an activation" in err
    (workdir / "junk.onnx").write_bytes(b"\x07not a protobuf at all")
    assert "not an ONNX model" in import_refused(capsys, "junk.onnx")


def test_run_needs_system_for_a_model_and_not_for_a_checkpoint(workdir, capsys):
    path = export(mlp("tanh", n=2, p=1, out=2), "m.onnx", "onnx17", Z)
    assert "give --system SPEC" in refused(capsys, "run", path)
    ckpt = save_linear(workdir / "lin.ckpt")
    # --lam and --metric override a checkpoint's own (tests/cli); the model flags do not apply
    assert "--activation: only for a model from elsewhere" in refused(
        capsys, "run", ckpt, "--activation", "tanh")
    assert "is a certify checkpoint: run it without --system" in refused(
        capsys, "run", ckpt, "--system", "spec.toml")
    assert "needs --system SPEC" in refused(capsys, "import", path, "-o", "x.ckpt")


@pytest.mark.slow
def test_refusal_from_a_real_process(workdir):
    path = export(relu_mlp(), "relu.onnx", "onnx17", Z)
    proc = subprocess.run([sys.executable, "-m", "certify", "run", path, "--system",
                           "spec.toml"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "node '/1/Relu' (Relu)" in proc.stderr


@pytest.mark.parametrize("how", ("onnx17", "script", "state_dict"))
def test_damaged_model_files_are_bad_input(workdir, capsys, how):
    """A model file cut short or with flipped bytes (anywhere, including a ZIP's directory)
    is exit 2 with one line, never a crash."""
    path = Path(export(mlp("tanh", n=2, p=1, out=2), "m.bin", how, Z))
    data = path.read_bytes()
    flags = ("--activation", "tanh") if how == "state_dict" else ()
    rng = np.random.default_rng(0)
    variants = [data[: len(data) // 2], data[: len(data) - 30]]
    for _ in range(12):
        flipped = np.frombuffer(data, dtype=np.uint8).copy()
        at = rng.integers(0, len(data), size=8)
        flipped[at] ^= rng.integers(1, 256, size=8).astype(np.uint8)
        variants.append(flipped.tobytes())
    for variant in variants:
        path.write_bytes(variant)
        code, out, err = run_cli(capsys, "import", str(path), "--system", "spec.toml", "-o",
                                 "out.ckpt", *flags)
        assert code in (0, 2) and err.count("\n") == (code == 2), err
        assert code == 2 or Path("out.ckpt").exists()
        Path("out.ckpt").unlink(missing_ok=True)


def test_damaged_zip_names_are_bad_input_for_run_too(workdir, capsys):
    """A ZIP whose directory holds undecodable names (a flipped byte) is refused as damaged by
    the checkpoint reader as well, not an internal error."""
    path = Path(export(mlp("tanh", n=2, p=1, out=2), "m.pt", "state_dict", Z))
    data = bytearray(path.read_bytes())
    name = data.rindex(b"data.pkl")  # a name in the central directory, at the end
    data[name] = 0xE9  # not UTF-8 on its own; the entry is flagged as UTF-8
    path.write_bytes(bytes(data))
    assert "damaged" in refused(capsys, "run", str(path))


# ----- p = 1: the output width does not say what the network outputs -------------------------
@pytest.mark.parametrize("how", ("onnx17", "script", "state_dict"))
def test_structure_is_never_guessed_for_one_output(workdir, capsys, how):
    """n = n*p: k itself or G of k = G (y - h)? Exit 2 with both choices on one line."""
    path = export(mlp("tanh", n=2, p=1, out=2), f"m.{how}", how, Z)
    flags = ("--activation", "tanh") if how == "state_dict" else ()
    err = import_refused(capsys, path, *flags)
    assert "with one output (p = 1)" in err
    assert "(--structure direct)" in err and "(--structure structural)" in err
    for structure in ("direct", "structural"):
        code, out, err = run_cli(capsys, "import", path, "--system", "spec.toml", "-o",
                                 f"{structure}.ckpt", "--structure", structure, *flags)
        assert code == 0 and f", {structure}" in out, err
        assert checkpoint.load(f"{structure}.ckpt").problem.network.structure == structure


@pytest.mark.parametrize("how", ("onnx17", "script"))
def test_structure_recorded_at_export_is_used(workdir, capsys, how):
    """The README's export lines record the structure (ONNX metadata_props, a TorchScript
    extra file); a flag that disagrees, or a value that is neither, is exit 2."""
    path = export(mlp("tanh", n=2, p=1, out=2), f"m.{how}", how, Z, structure="structural")
    code, out, err = run_cli(capsys, "import", path, "--system", "spec.toml", "-o", "m.ckpt")
    assert code == 0 and ", structural" in out, err
    assert checkpoint.load("m.ckpt").problem.network.structure == "structural"
    err = import_refused(capsys, path, "--structure", "direct")
    assert "--structure direct disagrees with the model's metadata (certify.structure = " \
           "structural)" in err
    bad = export(mlp("tanh", n=2, p=1, out=2), f"bad.{how}", how, Z, structure="G")
    assert "metadata certify.structure = 'G'; it must be 'direct' or 'structural'" in \
        import_refused(capsys, bad)
