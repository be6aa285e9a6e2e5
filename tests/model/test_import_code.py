"""A TorchScript file is code: certify runs none of it while reading. A file whose
`__setstate__` prints or loops forever (torch.jit.load would run it) is refused with one line
on stderr, nothing on stdout, and no hang; so are forward hooks, prints and loops in forward,
and archives with two members of one name. Run as real processes (`--json -` on stdout)."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from ..conftest import LINEAR_SPEC
from .test_import import mlp

pytestmark = pytest.mark.slow

MARK = "RAN-CODE-FROM-THE-FILE"
STATE = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, bool]


class Stateful(nn.Module):
    """A valid gain (n = 2, p = 1) with custom serialisation: torch.jit.load calls the
    scripted `__setstate__` while it opens the file."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.W1 = nn.Parameter(torch.randn(4, 3, dtype=torch.float64))
        self.b1 = nn.Parameter(torch.randn(4, dtype=torch.float64))
        self.W2 = nn.Parameter(torch.randn(2, 4, dtype=torch.float64))
        self.b2 = nn.Parameter(torch.randn(2, dtype=torch.float64))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return F.linear(torch.tanh(F.linear(z, self.W1, self.b1)), self.W2, self.b2)

    @torch.jit.export
    def __getstate__(self) -> STATE:
        return (self.W1, self.b1, self.W2, self.b2, self.training)


class Prints(Stateful):
    @torch.jit.export
    def __setstate__(self, state: STATE) -> None:
        print("RAN-CODE-FROM-THE-FILE")
        self.W1, self.b1, self.W2, self.b2 = state[0], state[1], state[2], state[3]
        self.training = state[4]


class Hangs(Stateful):
    @torch.jit.export
    def __setstate__(self, state: STATE) -> None:
        while True:
            pass
        self.W1, self.b1, self.W2, self.b2 = state[0], state[1], state[2], state[3]
        self.training = state[4]


class PrintsInForward(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.seq = mlp("tanh", n=2, p=1, out=2)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        print("RAN-CODE-FROM-THE-FILE")
        return self.seq(z)


class LoopsInForward(PrintsInForward):
    def forward(self, z: torch.Tensor) -> torch.Tensor:
        i = 0
        while i >= 0:
            i += 1
        return self.seq(z)


def _scale(module: nn.Module, inputs: tuple[torch.Tensor], output: torch.Tensor
           ) -> torch.Tensor:
    return output * 2.0


def _same(module: nn.Module, inputs: tuple[torch.Tensor]) -> tuple[torch.Tensor]:
    return inputs


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.toml").write_text(LINEAR_SPEC)
    return tmp_path


def certify_run(model: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """`certify run MODEL --system spec.toml --json -` as a real process. `timeout` is a
    safety net only (far above the seconds a refusal takes): a hang fails the test, never
    passes it."""
    return subprocess.run([sys.executable, "-m", "certify", "run", model, "--system",
                           "spec.toml", "--structure", "direct", "--json", "-"],
                          capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def assert_refused_quietly(proc: subprocess.CompletedProcess, *words: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == "" and MARK not in proc.stderr
    assert proc.stderr.startswith("certify: error: ") and proc.stderr.count("\n") == 1
    for word in words:
        assert word in proc.stderr, proc.stderr


def test_a_setstate_that_prints_is_refused_without_running(workdir):
    torch.jit.script(Prints()).save("prints.pt")
    premise = subprocess.run([sys.executable, "-c", "import torch; torch.jit.load('prints.pt')"],
                             capture_output=True, text=True, timeout=600)
    assert MARK in premise.stdout  # loading it really runs the file's code
    assert_refused_quietly(certify_run("prints.pt"), "defines __setstate__",
                           "torch.jit.load runs when the file is opened")


def test_a_setstate_that_never_returns_does_not_hang(workdir):
    torch.jit.script(Hangs()).save("hangs.pt")
    assert_refused_quietly(certify_run("hangs.pt"), "defines __setstate__")


def test_getstate_alone_is_refused(workdir):
    torch.jit.script(Stateful()).save("stateful.pt")
    assert_refused_quietly(certify_run("stateful.pt"), "defines __getstate__")


@pytest.mark.parametrize("module, words", [
    (PrintsInForward, ("(prim::Print): unsupported operation",)),
    (LoopsInForward, ("(prim::Loop): unsupported operation",)),
])
def test_code_in_forward_is_refused_before_anything_runs_it(workdir, module, words):
    torch.jit.script(module().double()).save("model.pt")
    assert_refused_quietly(certify_run("model.pt"), *words)


@pytest.mark.parametrize("kind", ("hook", "pre_hook"))
def test_forward_hooks_are_refused(workdir, kind):
    """`module(x)` runs hooks besides forward's graph (a root hook is not in it at all)."""
    model = mlp("tanh", n=2, p=1, out=2)
    if kind == "hook":
        model.register_forward_hook(_scale)
    else:
        model.register_forward_pre_hook(_same)
    torch.jit.script(model).save("hooked.pt")
    assert_refused_quietly(certify_run("hooked.pt"), "forward hooks")


def test_duplicate_archive_members_are_refused(workdir):
    """Two members of one name could be resolved differently by torch's reader and Python's
    zipfile (one of them clean, the other not): refused before either reads code."""
    torch.jit.script(mlp("tanh", n=2, p=1, out=2)).save("model.pt")
    with zipfile.ZipFile("model.pt") as archive:
        code = next(n for n in archive.namelist() if "/code/" in n and n.endswith(".py"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about the duplicate name it writes
        with zipfile.ZipFile("model.pt", "a") as archive:
            archive.writestr(code, b"# a second copy\n")
    assert_refused_quietly(certify_run("model.pt"), "two members named")


def test_a_clean_torchscript_file_certifies_with_only_json_on_stdout(workdir):
    """The accepted path for contrast: stdout is exactly the certificate."""
    Path("pyproject.toml").write_text("[tool.certify]\ngrid_points = 2000\n"
                                      "adversarial_starts = 2\n")
    torch.jit.script(mlp("tanh", n=2, p=1, out=2)).save("model.pt")
    proc = subprocess.run([sys.executable, "-m", "certify", "run", "model.pt", "--system",
                           "spec.toml", "--structure", "direct", "--json", "-", "--quiet",
                           "--max-boxes", "200", "--skip", "simulation"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode in (0, 1, 3), proc.stderr
    cert = json.loads(proc.stdout)
    assert cert["checkpoint"]["path"] == "model.pt"
