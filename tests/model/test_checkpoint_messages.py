"""Broken checkpoints through the real command line: exit 2, one line, in the user's words
(never the ZIP reader's internals such as 'internal miniz error' or '(101)')."""

from __future__ import annotations

import struct
import zipfile

import numpy as np
import pytest

from ..cli_helpers import run_cli, save_linear

INTERNALS = ("miniz", "(101)", "PytorchStreamReader", "Traceback", "central directory")


def _make(kind: str, folder) -> str:
    path = folder / f"{kind}.ckpt"
    if kind == "text":
        path.write_text("these are my notes about the observer\nnot weights\n")
    elif kind == "json":
        path.write_text('{"schema": "certify-certificate", "verdict": "CERTIFIED"}\n')
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        good = save_linear(folder / "good.ckpt")
        data = open(good, "rb").read()
        path.write_bytes(data[: len(data) * 2 // 3])
    elif kind == "random":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8)
                         .tobytes())
    elif kind == "other-zip":
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("photos/cat.jpg", b"\xff\xd8\xff not really a jpeg")
    elif kind == "directory":
        path.mkdir()
    return str(path)


@pytest.mark.parametrize("kind, words", [
    ("text", "not a checkpoint: the file is a text file"),
    ("json", "not a checkpoint: the file is a text file (it looks like JSON"),
    ("empty", "not a checkpoint: the file is empty"),
    ("truncated", "truncated or damaged file"),
    ("random", "not a checkpoint: the file is neither a ZIP archive written by torch.save "
               "nor a pickle"),
    ("other-zip", "not a checkpoint: the file is a ZIP archive without the data.pkl record"),
    ("directory", "is a directory, not a checkpoint file"),
])
def test_broken_checkpoint_named_in_the_users_words(tmp_path, capsys, kind, words):
    path = _make(kind, tmp_path)
    code, out, err = run_cli(capsys, "run", path, "--quiet")
    assert code == 2, err
    assert err.startswith("certify: error: checkpoint ") and err.count("\n") == 1, err
    assert words in err, err
    assert not any(s in err for s in INTERNALS), err
    assert out == ""


def test_zip_with_a_damaged_record_is_named(tmp_path, capsys):
    good = save_linear(tmp_path / "good.ckpt")
    data = bytearray(open(good, "rb").read())
    with zipfile.ZipFile(good) as zf:  # flip a byte inside the pickled record's data
        info = zf.getinfo(next(n for n in zf.namelist() if n.endswith("data.pkl")))
    # the local header's own name and extra lengths (torch pads its extra field to align)
    name_len, extra_len = struct.unpack_from("<HH", data, info.header_offset + 26)
    data[info.header_offset + 30 + name_len + extra_len + 5] ^= 0xFF
    bad = tmp_path / "flipped.ckpt"
    bad.write_bytes(bytes(data))
    code, _, err = run_cli(capsys, "run", str(bad), "--quiet")
    assert code == 2 and err.count("\n") == 1
    assert "damaged file" in err and "fails its checksum" in err, err


def _with_member_version(data: bytes, version: int) -> bytes:
    """The archive with every member's 'version needed to extract' set to `version` (local
    headers and central directory), which zipfile refuses with NotImplementedError."""
    out = bytearray(data)
    for magic, offset in ((b"PK\x03\x04", 4), (b"PK\x01\x02", 6)):
        at = out.find(magic)
        while at >= 0:
            struct.pack_into("<H", out, at + offset, version)
            at = out.find(magic, at + 4)
    return bytes(out)


def test_zip_member_of_an_unknown_version_is_bad_input(tmp_path, capsys):
    """Flipped bytes can make zipfile raise NotImplementedError ('zip file version 13.4'):
    that is a damaged file (exit 2, one line), for checkpoints and for imported TorchScript."""
    good = save_linear(tmp_path / "good.ckpt")
    bad = tmp_path / "version.ckpt"
    bad.write_bytes(_with_member_version(open(good, "rb").read(), 134))
    with pytest.raises(NotImplementedError):  # the input class this test is about
        zipfile.ZipFile(bad).testzip()
    code, out, err = run_cli(capsys, "run", str(bad), "--quiet")
    assert code == 2 and err.count("\n") == 1, err
    assert "damaged file" in err and out == "", err
    model = tmp_path / "model.pt"
    model.write_bytes(bad.read_bytes())
    code, out, err = run_cli(capsys, "import", str(model), "--system", "vdp", "-o",
                             str(tmp_path / "m.ckpt"), "--activation", "tanh")
    assert code == 2 and err.count("\n") == 1, err
    assert not (tmp_path / "m.ckpt").exists()
