"""Data-only checkpoints: save and load with a format name and version.

A checkpoint is `torch.save` of a dict of tensors and plain containers, loaded with
`weights_only=True`, so loading never runs code. Everything is validated on load; any
problem raises `CheckpointError` with one line naming it (exit code 2 on the CLI).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import pickle
import re
import warnings
import zipfile
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch

from certify.errors import CertifyError, CheckpointError
from certify.files import atomic_write_bytes
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.spec.system import System, validate_lam, validate_metric

FORMAT_NAME = "certify-checkpoint"
FORMAT_VERSION = 1
_REQUIRED = ("format", "format_version", "system_spec", "lam", "P", "architecture",
             "state_dict")


# What zipfile raises for a damaged archive: bad records, undecodable names (ValueError), a
# version or compression method it does not implement (NotImplementedError, e.g. after flipped
# bytes in a member header), an "encrypted" flag (RuntimeError), a cut-short stream (EOFError).
ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError,
              NotImplementedError, RuntimeError)


def versions() -> dict[str, str]:
    """Versions of certify and the libraries whose numbers it depends on."""
    out = {}
    for pkg in ("certify", "torch", "numpy", "scipy", "sympy", "cvxpy", "clarabel"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class Checkpoint:
    """A loaded checkpoint: the problem plus its provenance."""

    problem: Problem
    path: str
    sha256: str
    training: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    created: str = ""


def _to_plain(obj: Any) -> Any:
    """Training records to types that `weights_only=True` accepts."""
    if isinstance(obj, dict):
        return {str(k): _to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return torch.as_tensor(obj)
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if obj is None or isinstance(obj, (str, int, float, bool, torch.Tensor)):
        return obj
    return str(obj)


def save(path: str | Path, *, system: System, network: GainNetwork, lam: float,
         P: Any = None, training: dict[str, Any] | None = None,
         metric: PolyMetric | None = None) -> str:
    """Write a checkpoint atomically; returns its sha256. `metric`: a metric that follows the
    state, stored under `state_metric` in its plain-data form (`PolyMetric.to_dict`, which
    carries its own format version); checkpoints without it load as before."""
    P_arr = validate_metric(system.P if P is None else P, system.n, "checkpoint")
    lam = validate_lam(lam, "checkpoint: lam")
    state = {k: v.detach().to(torch.float64).clone() for k, v in network.state_dict().items()}
    payload = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "system_name": system.name,
        "system_spec": system.source,
        "lam": float(lam),
        "P": torch.as_tensor(P_arr, dtype=torch.float64),
        "architecture": network.architecture(),
        "state_dict": state,
        "training": _to_plain(training or {}),
        **({"state_metric": metric.to_dict()} if metric is not None else {}),
        "versions": versions(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    import io

    buf = io.BytesIO()
    torch.save(payload, buf)
    atomic_write_bytes(path, buf.getvalue())
    return hashlib.sha256(buf.getvalue()).hexdigest()


_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a ZIP entry, or an empty archive
_SNIFF_BYTES = 4096


def _looks_like_text(head: bytes) -> bool:
    """Whether the first bytes of a file are text (UTF-8, no NUL, mostly printable)."""
    if b"\x00" in head:
        return False
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 3:  # not just a character cut at the end of the sample
            return False
        text = head[:exc.start].decode("utf-8")
    printable = sum(ch.isprintable() or ch in "\r\n\t\f" for ch in text)
    return printable >= 0.95 * max(len(text), 1)


def _text_hint(head: bytes) -> str:
    start = head.lstrip()[:1]
    if start in (b"{", b"["):
        return " (it looks like JSON; a saved certificate is re-rendered with 'certify report')"
    if b"states" in head and b"=" in head:
        return " (it looks like a system spec; train a checkpoint with 'certify train')"
    return ""


def unreadable_reason(path: Path) -> str | None:
    """Why `path` cannot be a checkpoint, in the user's words; None if it may be one.

    Looks at the bytes before torch does, so that a text file, an empty or truncated file, a
    ZIP archive of something else or random bytes are named as such, not by the internals of
    the ZIP reader ("internal miniz error", "(101)").
    """
    size = path.stat().st_size
    if size == 0:
        return "not a checkpoint: the file is empty"
    with open(path, "rb") as fh:
        head = fh.read(_SNIFF_BYTES)
    if head.startswith(_ZIP_MAGIC):
        try:
            archive = zipfile.ZipFile(path)
        except ZIP_ERRORS:
            return (f"truncated or damaged file: the ZIP archive that torch.save writes has no "
                    f"end record ({size} bytes; was a download or copy cut short?)")
        with archive:
            names = archive.namelist()
            if not any(n == "data.pkl" or n.endswith("/data.pkl") for n in names):
                listed = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
                return (f"not a checkpoint: the file is a ZIP archive without the data.pkl "
                        f"record that torch.save writes (it holds {listed or 'nothing'})")
            try:
                broken = archive.testzip()
            except ZIP_ERRORS:
                broken = "?"
            if broken is not None:
                return (f"damaged file: the ZIP archive's record {broken!r} fails its "
                        "checksum or is cut short")
        return None
    if head.startswith(b"\x80"):
        return None  # a pickle (torch's legacy format): torch.load decides, data-only
    if _looks_like_text(head):
        return "not a checkpoint: the file is a text file" + _text_hint(head)
    return ("not a checkpoint: the file is neither a ZIP archive written by torch.save nor a "
            f"pickle (it starts with bytes {head[:8].hex(' ')})")


def _refusal(exc: Exception) -> str:
    """The reason torch's weights-only loader refused a pickle, in a few words."""
    detail = str(exc).split("WeightsUnpickler error:", 1)[-1].strip().splitlines()
    first = next((line.strip() for line in detail if line.strip()), "")
    named = re.match(r"Unsupported global: GLOBAL (\S+)", first)
    return (f"it references {named.group(1)}, which only code could rebuild" if named
            else "it holds Python objects that only code could rebuild")


def _read(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} not found")
    if path.is_dir():
        raise CheckpointError(f"checkpoint {path} is a directory, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} is not a regular file")
    try:
        problem = unreadable_reason(path)
    except OSError as exc:
        raise CheckpointError(f"checkpoint {path} cannot be read ({exc.strerror or exc})"
                              ) from None
    if problem is not None:
        raise CheckpointError(f"checkpoint {path}: {problem}")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols: not the user's
            warnings.simplefilter("ignore")
            data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"checkpoint {path}: not a data-only checkpoint: {_refusal(exc)}"
                              "; loading it would run code, so it is refused") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError, KeyError,
            AttributeError, TypeError, IndexError) as exc:
        raise CheckpointError(f"checkpoint {path}: damaged file: PyTorch cannot read it "
                              f"({type(exc).__name__}); copy or download it again") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
        raise CheckpointError(f"checkpoint {path} is not a certify checkpoint "
                              f"(format name missing or not '{FORMAT_NAME}')")
    return data


def load(path: str | Path) -> Checkpoint:
    """Load and validate a checkpoint (never runs code); returns a `Checkpoint`."""
    path = Path(path)
    data = _read(path)
    version = data.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format version {version!r}; this "
                              f"certify reads version {FORMAT_VERSION}")
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks field(s) {', '.join(missing)}")
    spec = data["system_spec"]
    if not isinstance(spec, str):
        raise CheckpointError(f"checkpoint {path}: embedded system spec is not text")
    try:
        system = System.from_text(spec, origin=f"checkpoint {path.name}: embedded spec")
    except CertifyError as exc:
        raise CheckpointError(str(exc)) from None
    arch = data["architecture"]
    try:
        if (arch["n"], arch["p"]) != (system.n, system.p):
            raise ValueError(f"network is for n={arch['n']}, p={arch['p']} but the system has "
                             f"n={system.n}, p={system.p}")
        net = GainNetwork.from_architecture(arch).double()
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: bad architecture ({exc})") from None
    state = data["state_dict"]
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path}: state_dict is not a dict")
    expected = net.state_dict()
    if set(state) != set(expected):
        extra = sorted(set(state) - set(expected))
        lacking = sorted(set(expected) - set(state))
        raise CheckpointError(f"checkpoint {path}: weights do not match the architecture "
                              f"(missing {lacking or 'none'}, unexpected {extra or 'none'})")
    for key, ref in expected.items():
        value = state[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != tuple(ref.shape):
            got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise CheckpointError(f"checkpoint {path}: weight '{key}' has shape {got}, the "
                                  f"architecture needs {list(ref.shape)}")
        if not torch.all(torch.isfinite(value)):
            raise CheckpointError(f"checkpoint {path}: weight '{key}' contains NaN or Inf")
    net.load_state_dict({k: v.to(torch.float64) for k, v in state.items()})
    try:
        P = validate_metric(torch.as_tensor(data["P"]).numpy(), system.n, f"checkpoint {path}")
    except CertifyError as exc:
        raise CheckpointError(str(exc)) from None
    try:
        lam = validate_lam(data["lam"], f"checkpoint {path}: lam")
    except CertifyError as exc:
        raise CheckpointError(str(exc)) from None
    training = data.get("training") or {}
    metric = None
    if data.get("state_metric") is not None:
        try:
            metric = PolyMetric.from_dict(data["state_metric"], system.n)
        except CertifyError as exc:
            raise CheckpointError(f"checkpoint {path}: state_metric: {exc}") from None
    return Checkpoint(problem=Problem(system=system, network=net, lam=lam, P=P, metric=metric),
                      path=str(path), sha256=sha256_file(path),
                      training=training if isinstance(training, dict) else {},
                      versions=dict(data.get("versions") or {}),
                      created=str(data.get("created", "")))
