"""Verification settings: one frozen dataclass, its constraints declared beside it.

Values enter from flags, `[tool.certify]` (see `certify.cli.config`) or the Python API and are
validated once, here, with one error shape:
``[tool.certify] max_boxes must be an int >= 1; got -3``.
Checks never mutate settings; the certificate echoes them.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

from certify.errors import SettingsError

#: the checks `verify()` runs (each is `CHECK` in certify/checks/<name>.py), in this order
#: unless one needs another's result (see certify.checks.registry)
CHECK_NAMES = ("necessary", "mpdi", "rate", "residual", "lipschitz", "dissipation",
               "metric_bound", "bounds", "simulation")
#: the check that is the certificate: always run, always required, whatever the policy says
#: (a policy may add checks beside it, never drop it; see `validate`)
CERTIFICATE_CHECK = "mpdi"
#: a local Dask cluster may have at most this many processes per CPU this process may use
#: (more only compete for the same cores while each still pays its start-up)
WORKERS_PER_CPU = 2


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
    dissipation_seconds: float = 60.0  # budget of the joint dissipation certificate (all proofs)
    noise: float = 0.15  # vbar: bound on ||v(t)||_2 of the measurement noise
    # simulated seconds; None: automatic (DEFAULT_SIM_TIME, extended when the proved bound is
    # slow: `certify.checks.simulation.plan_horizon`); a number is kept as given
    sim_time: float | None = None
    sim_dt: float = 2e-3
    sim_initial_conditions: int = 6
    seed: int = 0
    required: tuple[str, ...] = ("mpdi",)  # checks whose failure means exit 1; mpdi always
    allow_unknown: bool = False  # treat an UNKNOWN required check as a pass (exit 0)
    skip: tuple[str, ...] = ()  # checks not run at all (never mpdi)
    device: str = "cpu"  # torch device of the grid, falsifier and proofs ("cpu", "cuda")
    workers: int = 1  # Dask worker processes of a local cluster (1: serial, no cluster;
    # at most `max_local_workers()`)
    scheduler: str = ""  # address of a running Dask scheduler (wins over workers)

    def __post_init__(self) -> None:
        validate(self, source="settings")


_INT_MIN = {
    "grid_points": 1, "adversarial_starts": 0, "adversarial_steps": 0, "top_counterexamples": 0,
    "max_boxes": 1, "sim_initial_conditions": 1, "seed": 0, "workers": 1,
}
_POS_FLOAT = {"proof_seconds", "rate_seconds", "residual_seconds", "lipschitz_seconds",
              "dissipation_seconds", "sim_time", "sim_dt"}
_NONNEG_FLOAT = {"noise"}
#: of those, the ones where None means "automatic"
_OPTIONAL = {"sim_time"}

#: the simulated seconds when sim_time is not set (before any extension for a slow bound)
DEFAULT_SIM_TIME = 10.0


#: `max_boxes` where the device is a GPU and neither the options nor [tool.certify] name it:
#: 16x the CPU's, as its proof rounds (`certify.arith.device.PROOF_BATCH`): a GPU bounds boxes
#: fast enough (`bench/device_check.py`) that the CPU's 2M would end a proof long before the
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
        if v is None and name in _OPTIONAL:
            continue
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and v == v and v < float("inf")
        if not ok or (v <= 0 if name in _POS_FLOAT else v < 0):
            raise _fail(source, name, "a number > 0" if name in _POS_FLOAT else "a number >= 0", v)
    for name in ("required", "skip"):
        v = getattr(s, name)
        if not isinstance(v, tuple) or any(c not in CHECK_NAMES for c in v):
            raise _fail(source, name, f"a list of check names from {list(CHECK_NAMES)}", v)
    if CERTIFICATE_CHECK not in s.required:
        raise SettingsError(f"{source} required must include {CERTIFICATE_CHECK}: the MPDI is "
                            "the certificate and cannot be dropped (list other checks beside "
                            f"it, e.g. {[CERTIFICATE_CHECK, 'residual']}); got {list(s.required)}")
    if CERTIFICATE_CHECK in s.skip:
        raise SettingsError(f"{source} skip cannot include {CERTIFICATE_CHECK}: the MPDI is the "
                            "certificate and always runs (bound its time with proof_seconds or "
                            f"max_boxes instead); got {list(s.skip)}")
    for name in ("allow_unknown", "float32_screen"):
        if not isinstance(getattr(s, name), bool):
            raise _fail(source, name, "true or false", getattr(s, name))
    if not isinstance(s.device, str) or not (
            s.device in ("cpu", "cuda") or (s.device.startswith("cuda:")
                                            and s.device[5:].isdigit())):
        raise _fail(source, "device", "'cpu' or 'cuda' (or 'cuda:N')", s.device)
    if not isinstance(s.scheduler, str) or any(c.isspace() for c in s.scheduler.strip()):
        raise _fail(source, "scheduler", "an address like 'tcp://host:8786'", s.scheduler)
    if s.scheduler.strip():
        check_scheduler_address(s.scheduler.strip(), source)
    elif s.workers > max_local_workers():
        cap = max_local_workers()
        raise SettingsError(f"{source} workers must be at most {cap} ({WORKERS_PER_CPU} per "
                            f"CPU, {cap // WORKERS_PER_CPU} here: more local processes only "
                            "compete for them; for more, run a Dask cluster and give its "
                            f"address, --scheduler); got {s.workers}")


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def max_local_workers() -> int:
    """The largest `workers` a local Dask cluster may have: `WORKERS_PER_CPU` per usable CPU."""
    return WORKERS_PER_CPU * usable_cpus()


def check_scheduler_address(address: str, source: str = "settings") -> None:
    """Refuse a malformed Dask scheduler address before anything connects.

    Parsed by Dask's own rules (`distributed.comm`: the scheme must be a known transport and an
    IP transport needs host:port with a port in 1..65535); whether anything answers there is
    for the connection to find out. Without dask installed nothing is checked here (the
    executor then says how to install it).
    """
    try:
        from distributed.comm import registry
        from distributed.comm.addressing import parse_address
    except ImportError:  # pragma: no cover - dask is an optional extra
        return
    need = "a Dask scheduler address like 'tcp://host:8786'"
    try:
        scheme, location = parse_address(address)
        backend = registry.get_backend(scheme)
    except (ValueError, TypeError) as exc:
        raise SettingsError(f"{source} scheduler must be {need} ({exc}); "
                            f"got {address!r}") from None
    try:
        host, port = backend.get_address_host_port(location)
    except NotImplementedError:  # not an IP transport (inproc, ucx): nothing more to check
        return
    except (ValueError, TypeError) as exc:
        raise SettingsError(f"{source} scheduler must be {need} ({exc}); "
                            f"got {address!r}") from None
    if not host or not 0 < int(port) < 65536:
        raise SettingsError(f"{source} scheduler must be {need} (host and a port in "
                            f"1..65535); got {address!r}")


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


def required_checks(settings: VerifySettings) -> list[str]:
    """The checks whose failure fails the gate: the settings' `required`, with the MPDI (the
    certificate) first should they lack it (validated settings never do)."""
    required = list(settings.required)
    return required if CERTIFICATE_CHECK in required else [CERTIFICATE_CHECK, *required]
