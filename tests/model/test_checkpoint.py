"""Checkpoints: round trip, and every malformed case refused with one line (never running code)."""

from __future__ import annotations

import io
import os
import pickle
import zipfile

import pytest
import torch

from certify.errors import CheckpointError
from certify.model import checkpoint
from certify.spec.system import System, load_system

from ..conftest import SPEC_3X2, random_network


@pytest.fixture
def saved(tmp_path, system3):
    net = random_network(3, 2, structure="structural", seed=2)
    path = tmp_path / "three.ckpt"
    digest = checkpoint.save(path, system=system3, network=net, lam=0.7,
                             training={"seed": 3, "history": {"loss": [3.0, 2.0]}})
    return path, net, digest


def test_round_trip(saved, system3):
    path, net, digest = saved
    ck = checkpoint.load(path)
    assert ck.sha256 == digest
    assert ck.problem.lam == 0.7
    assert ck.problem.system.name == "three" and ck.problem.network.structure == "structural"
    assert ck.training["history"]["loss"] == [3.0, 2.0]
    assert "torch" in ck.versions
    x = torch.rand(5, 3, dtype=torch.float64)
    y = torch.rand(5, 2, dtype=torch.float64)
    z = torch.cat([x, y], 1)
    torch.testing.assert_close(ck.problem.network(z), net(z))
    torch.testing.assert_close(ck.problem.network.K, net.K)
    assert ck.problem.P.tolist() == system3.P.tolist()


def _rewrite(path, mutate):
    data = torch.load(path, weights_only=True)
    mutate(data)
    buf = io.BytesIO()
    torch.save(data, buf)
    path.write_bytes(buf.getvalue())


def _set(key, value):
    return lambda d: d.__setitem__(key, value)


def _nan_weight(d):
    d["state_dict"]["layers.0.weight"][0, 0] = float("nan")


def _inf_weight(d):
    d["state_dict"]["layers.1.bias"][0] = float("inf")


def _bad_shape(d):
    d["state_dict"]["layers.0.weight"] = torch.zeros(7, 7, dtype=torch.float64)


def _missing_weight(d):
    del d["state_dict"]["layers.1.bias"]


@pytest.mark.parametrize("mutate,fragment", [
    (_set("format_version", 99), "format version 99"),
    (_set("format", "something-else"), "not a certify checkpoint"),
    (_nan_weight, "'layers.0.weight' contains NaN or Inf"),
    (_inf_weight, "'layers.1.bias' contains NaN or Inf"),
    (_bad_shape, "has shape [7, 7], the architecture needs"),
    (_missing_weight, "missing ['layers.1.bias']"),
    (_set("system_spec", SPEC_3X2.replace('"-2*c + a*b"', '"-2*c + a.b"')), "attribute access"),
    (_set("system_spec", "name = ["), "not valid TOML"),
    (_set("lam", float("nan")), "lam must be a finite number > 0"),
    (_set("P", torch.tensor([[1.0, 5.0, 0], [5.0, 1.0, 0], [0, 0, 1]])), "positive definite"),
    (lambda d: d.pop("architecture"), "lacks field(s) architecture"),
])
def test_malformed_checkpoints_refused(saved, mutate, fragment):
    path, _, _ = saved
    _rewrite(path, mutate)
    with pytest.raises(CheckpointError) as err:
        checkpoint.load(path)
    assert fragment in str(err.value)
    assert "\n" not in str(err.value)


def test_missing_and_garbage_files(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        checkpoint.load(tmp_path / "nope.ckpt")
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"this is not a checkpoint at all")
    with pytest.raises(CheckpointError, match="not"):
        checkpoint.load(junk)
    truncated = tmp_path / "trunc.ckpt"
    net = random_network(2, 1)
    checkpoint.save(truncated, system=load_system("vdp"), network=net, lam=2.5)
    truncated.write_bytes(truncated.read_bytes()[:200])
    with pytest.raises(CheckpointError):
        checkpoint.load(truncated)
    plain = tmp_path / "plain.ckpt"
    torch.save({"weights": torch.zeros(3)}, plain)
    with pytest.raises(CheckpointError, match="not a certify checkpoint"):
        checkpoint.load(plain)


class _Payload:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


@pytest.mark.parametrize("container", ["raw-pickle", "torch-zip"])
def test_crafted_pickle_is_refused_without_running(tmp_path, container):
    target = tmp_path / "pwned"
    path = tmp_path / "evil.ckpt"
    if container == "raw-pickle":
        path.write_bytes(pickle.dumps({"format": "certify-checkpoint", "x": _Payload(target)}))
    else:
        torch.save({"format": "certify-checkpoint", "x": _Payload(target)}, path)
        assert zipfile.is_zipfile(path)
    with pytest.raises(CheckpointError, match="not a data-only checkpoint"):
        checkpoint.load(path)
    assert not target.exists()


def test_save_is_atomic_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "out.ckpt"
    path.write_bytes(b"previous")

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(path, system=load_system("vdp"), network=random_network(2, 1), lam=2.5)
    assert path.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.ckpt"]


def test_network_architecture_mismatch_with_system(tmp_path):
    path = tmp_path / "mismatch.ckpt"
    checkpoint.save(path, system=System.from_text(SPEC_3X2), network=random_network(3, 2), lam=1)

    def swap(d):
        d["system_spec"] = load_system("vdp").source

    _rewrite(path, swap)
    with pytest.raises(CheckpointError, match="network is for n=3, p=2"):
        checkpoint.load(path)
