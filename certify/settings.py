"""Verification settings: one frozen dataclass, its constraints declared beside it.

Values enter from flags, `[tool.certify]` (see `certify.config`) or the Python API and are
validated once, here, with one error shape:
``[tool.certify] max_boxes must be an int >= 1; got -3``.
Checks never mutate settings; the certificate echoes them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from certify.errors import SettingsError

#: the checks `verify()` runs (each is `CHECK` in certify/checks/<name>.py), in this order
#: unless one needs another's result (see certify.checks.registry)
CHECK_NAMES = ("necessary", "mpdi", "rate", "residual", "lipschitz", "bounds", "simulation")


@dataclass(frozen=True)
class VerifySettings:
    """How `certify run` checks a checkpoint (what is checked lives in `Problem`)."""

    grid_points: int = 1_000_000  # dense grid size over X x Y (at least this many points)
    float32_screen: bool = True  # sweep the grid in float32, re-check candidates in float64
    adversarial_starts: int = 64  # multi-start gradient ascent on lam_max(D)
    adversarial_steps: int = 100
    top_counterexamples: int = 5
    proof_seconds: float = 60.0  # branch-and-bound budget for the MPDI proof
    max_boxes: int = 2_000_000  # B&B budget in sub-boxes (GPU_MAX_BOXES: see make_settings)
    rate_seconds: float = 20.0  # budget for the proved lam_cert (branch and bound, then decisions)
    residual_seconds: float = 10.0
    lipschitz_seconds: float = 10.0
    noise: float = 0.15  # vbar: bound on ||v(t)||_2 of the measurement noise
    sim_time: float = 10.0
    sim_dt: float = 2e-3
    sim_initial_conditions: int = 6
    seed: int = 0
    required: tuple[str, ...] = ("mpdi",)  # checks whose failure means exit 1
    allow_unknown: bool = False  # treat an UNKNOWN required check as a pass (exit 0)
    skip: tuple[str, ...] = ()  # checks not run at all
    device: str = "cpu"  # torch device of the grid, falsifier and proofs ("cpu", "cuda")
    workers: int = 1  # Dask worker processes of a local cluster (1: serial, no cluster)
    scheduler: str = ""  # address of a running Dask scheduler (wins over workers)

    def __post_init__(self) -> None:
        validate(self, source="settings")


_INT_MIN = {
    "grid_points": 1, "adversarial_starts": 0, "adversarial_steps": 0, "top_counterexamples": 0,
    "max_boxes": 1, "sim_initial_conditions": 1, "seed": 0, "workers": 1,
}
_POS_FLOAT = {"proof_seconds", "rate_seconds", "residual_seconds", "lipschitz_seconds",
              "sim_time", "sim_dt"}
_NONNEG_FLOAT = {"noise"}


#: `max_boxes` where the device is a GPU and neither the options nor [tool.certify] name it:
#: 16x the CPU's, as its proof rounds (`certify.device.PROOF_BATCH`); an H100 bounds about
#: 400k boxes/s on the issue-9 instances, so 2M would end a proof within seconds of the
#: `proof_seconds` a user gave
GPU_MAX_BOXES = 32_000_000


def _fail(source: str, name: str, need: str, value: Any) -> SettingsError:
    return SettingsError(f"{source} {name} must be {need}; got {value!r}")


def validate(s: VerifySettings, source: str = "settings") -> None:
    """Check every field against its constraint; raise one `SettingsError` line."""
    for name, lo in _INT_MIN.items():
        v = getattr(s, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise _fail(source, name, f"an int >= {lo}", v)
    for name in _POS_FLOAT | _NONNEG_FLOAT:
        v = getattr(s, name)
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and v == v and v < float("inf")
        if not ok or (v <= 0 if name in _POS_FLOAT else v < 0):
            raise _fail(source, name, "a number > 0" if name in _POS_FLOAT else "a number >= 0", v)
    for name in ("required", "skip"):
        v = getattr(s, name)
        if not isinstance(v, tuple) or any(c not in CHECK_NAMES for c in v):
            raise _fail(source, name, f"a list of check names from {list(CHECK_NAMES)}", v)
    for name in ("allow_unknown", "float32_screen"):
        if not isinstance(getattr(s, name), bool):
            raise _fail(source, name, "true or false", getattr(s, name))
    if not isinstance(s.device, str) or not (
            s.device in ("cpu", "cuda") or (s.device.startswith("cuda:")
                                            and s.device[5:].isdigit())):
        raise _fail(source, "device", "'cpu' or 'cuda' (or 'cuda:N')", s.device)
    if not isinstance(s.scheduler, str) or any(c.isspace() for c in s.scheduler.strip()):
        raise _fail(source, "scheduler", "an address like 'tcp://host:8786'", s.scheduler)


FIELD_NAMES = tuple(f.name for f in dataclasses.fields(VerifySettings) if f.init)


def make_settings(values: dict[str, Any], source: str = "settings") -> VerifySettings:
    """Build settings from a mapping, refusing unknown keys with the list of known ones."""
    unknown = sorted(set(values) - set(FIELD_NAMES))
    if unknown:
        raise SettingsError(f"{source}: unknown setting(s) {', '.join(unknown)} "
                            f"(known: {', '.join(FIELD_NAMES)})")
    clean = dict(values)
    for key in ("required", "skip"):
        if key in clean and isinstance(clean[key], (list, str)):
            v = clean[key]
            clean[key] = tuple(x.strip() for x in v.split(",") if x.strip()) \
                if isinstance(v, str) else tuple(v)
    for key in _POS_FLOAT | _NONNEG_FLOAT:
        if isinstance(clean.get(key), int) and not isinstance(clean.get(key), bool):
            clean[key] = float(clean[key])
    if "max_boxes" not in clean and str(clean.get("device", "")).startswith("cuda"):
        clean["max_boxes"] = GPU_MAX_BOXES
    try:
        settings = VerifySettings(**clean)
    except SettingsError as exc:
        raise SettingsError(str(exc).replace("settings ", f"{source} ", 1)) from None
    return settings
