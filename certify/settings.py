"""Verification settings, each declared once: `VerifySettings` and its declarations.

Every field of `VerifySettings` is declared by `setting(...)`: its default, its rule (the
values it takes: `Count`, `Number`, `Switch`, `Checks`, `Device`, `Address`), its help text,
the option of `certify run` that sets it (if any) and the label and unit the reports'
settings rows show; its `[tool.certify]` key is its name. The options of `certify run`
(`certify.cli.parser`), the config reader (`certify.cli.config`), `make_settings`/`validate`
and the settings rows (`settings_rows`) are made from `DECLARATIONS`, so a setting is added,
renamed or documented here alone.

Budgets count work, never seconds: each proof has a budget of boxes (`max_boxes` for the
MPDI, `rate_boxes`, `residual_boxes`, `lipschitz_boxes`, `dissipation_boxes`,
`metric_boxes`, `invariance_boxes`), so a
checkpoint gets the same certificate on a busy machine as on a quiet one. `max_seconds`, off
by default, caps the wall clock of a whole run; a proof it stops is UNKNOWN and says so.
The per-proof seconds of older versions (`RETIRED`) are refused with their replacement.

Values enter from options, `[tool.certify]` or the Python API and are validated once, here,
with one error shape: ``[tool.certify] max_boxes must be an int >= 1; got -3``.
Checks never mutate settings; the certificate echoes them.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any

from certify.errors import SettingsError

#: the checks `verify()` runs (each is `CHECK` in certify/checks/<name>.py), in this order
#: unless one needs another's result (see certify.checks.registry). The MPDI, the
#: certificate, comes first: once it is VIOLATED the verdict is decided
#: (`certify.checks.registry.run_checks`)
CHECK_NAMES = ("mpdi", "necessary", "rate", "residual", "lipschitz", "dissipation",
               "metric_bound", "invariance", "bounds", "simulation")
#: the check that is the certificate: always run, always required, whatever the policy says
#: (a policy may add checks beside it, never drop it; see `validate`)
CERTIFICATE_CHECK = "mpdi"
#: a local Dask cluster may have at most this many processes per CPU this process may use
#: (more only compete for the same cores while each still pays its start-up)
WORKERS_PER_CPU = 2
#: the simulated seconds when sim_time is not set (before any extension for a slow bound)
DEFAULT_SIM_TIME = 10.0
#: the largest box budget taken: beyond it a budget only hides a typo (a proof bounds at
#: most millions of boxes a second, so this is days of work)
MAX_BUDGET_BOXES = 10**12
#: `max_boxes` where the device is a GPU and neither the options nor [tool.certify] name it:
#: 16x the CPU's, as its proof rounds (`certify.arith.device.PROOF_BATCH`)
GPU_MAX_BOXES = 32_000_000


# ----- rules: the values a setting takes ----------------------------------------------------
def _is_number(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


@dataclass(frozen=True)
class Count:
    """An int from `low` (to `high`, when given)."""

    low: int
    high: int | None = None

    def problem(self, v: Any) -> str | None:
        if isinstance(v, bool) or not isinstance(v, int) or v < self.low:
            return f"an int >= {self.low}"
        if self.high is not None and v > self.high:
            return f"an int <= {self.high:.0e} (a budget no proof reaches)"
        return None

    def from_text(self, text: str) -> int:
        """An option's text as an int: digits (with _ separators) or an integral number
        written with an exponent (2e6); ValueError with the reason otherwise."""
        try:
            return int(text.replace("_", ""))
        except ValueError:
            pass
        try:
            v = float(text)
        except ValueError:
            raise ValueError(f"not an integer: {text!r}") from None
        if not math.isfinite(v) or v != int(v):
            raise ValueError(f"not an integer: {text!r}")
        if self.high is not None and v > self.high:
            raise ValueError(f"at most {self.high:.0e}; got {text!r}")
        return int(v)

    def coerce(self, v: Any) -> Any:
        return v


@dataclass(frozen=True)
class Number:
    """A finite number > `low` (`strict`) or >= `low`; None too where `optional`."""

    low: float
    strict: bool = True
    optional: bool = False

    def problem(self, v: Any) -> str | None:
        if v is None and self.optional:
            return None
        if not _is_number(v) or (v <= self.low if self.strict else v < self.low):
            return f"a number {'>' if self.strict else '>='} {self.low:g}"
        return None

    def from_text(self, text: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"not a number: {text!r}") from None

    def coerce(self, v: Any) -> Any:
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v


@dataclass(frozen=True)
class Switch:
    """true or false (an option without a value turns it on)."""

    def problem(self, v: Any) -> str | None:
        return None if isinstance(v, bool) else "true or false"

    def coerce(self, v: Any) -> Any:
        return v


@dataclass(frozen=True)
class Checks:
    """A list of check names (`CHECK_NAMES`); a comma-separated string is split."""

    def problem(self, v: Any) -> str | None:
        if not isinstance(v, tuple) or any(c not in CHECK_NAMES for c in v):
            return f"a list of check names from {list(CHECK_NAMES)}"
        return None

    def coerce(self, v: Any) -> Any:
        if isinstance(v, str):
            return split_names(v)
        if isinstance(v, list):
            return tuple(x for item in v for x in (split_names(item) if isinstance(item, str)
                                                   else (item,)))
        return v


@dataclass(frozen=True)
class Device:
    """A torch device name: cpu, cuda or cuda:N."""

    def problem(self, v: Any) -> str | None:
        ok = isinstance(v, str) and (v in ("cpu", "cuda") or (v.startswith("cuda:")
                                                              and v[5:].isdigit()))
        return None if ok else "'cpu' or 'cuda' (or 'cuda:N')"

    def coerce(self, v: Any) -> Any:
        return v


@dataclass(frozen=True)
class Address:
    """A Dask scheduler address ('' for none): checked in full by `check_scheduler_address`."""

    def problem(self, v: Any) -> str | None:
        if not isinstance(v, str) or any(c.isspace() for c in v.strip()):
            return "an address like 'tcp://host:8786'"
        return None

    def coerce(self, v: Any) -> Any:
        return v


def split_names(text: str) -> tuple[str, ...]:
    """'a, b,c' -> ('a', 'b', 'c')."""
    return tuple(x.strip() for x in text.split(",") if x.strip())


# ----- the declaration ----------------------------------------------------------------------
@dataclass(frozen=True)
class Declaration:
    """Everything said about one setting (see the module docstring)."""

    name: str  # the field of VerifySettings and the [tool.certify] key
    default: Any
    rule: Any  # Count | Number | Switch | Checks | Device | Address
    help: str  # the option's help text, without the default
    label: str  # the name the reports' settings rows show
    unit: str = ""  # after the value in those rows (" s", " boxes")
    flag: str | None = None  # the option of `certify run`; None: [tool.certify] only
    metavar: str | None = None
    none: str = "none"  # how a value of None reads in the rows (`Number(optional=True)`)

    def text(self, value: Any) -> str:
        """`value` as the reports' settings rows show it, with the unit."""
        if value is None:
            return self.none
        if isinstance(value, bool):
            return "yes" if value else "no"
        if isinstance(value, (list, tuple)):
            return ", ".join(map(str, value)) or "none"
        if isinstance(value, int):
            return f"{value:,}{self.unit}"
        if isinstance(value, float):
            return f"{value:g}{self.unit}"
        return (str(value) or self.none) + (self.unit if value else "")

    def default_text(self) -> str:
        return self.text(self.default)


def setting(default: Any, rule: Any, *, help: str, label: str, unit: str = "",
            flag: str | None = None, metavar: str | None = None, none: str = "none") -> Any:
    """A field of `VerifySettings` with its declaration (`Declaration`, less the name)."""
    spec = dict(default=default, rule=rule, help=help, label=label, unit=unit, flag=flag,
                metavar=metavar, none=none)
    return field(default=default, metadata={"declaration": spec})


#: the rule of every box budget. The default budgets sit above what the shipped examples'
#: proofs need to finish, and where a proof does not finish (it spends its budget) near the
#: work the former per-proof seconds allowed on a quiet machine (`bench/box_budgets.py`
#: shows both per example)
_BOXES = Count(1, MAX_BUDGET_BOXES)


@dataclass(frozen=True)
class VerifySettings:
    """How `certify run` checks a checkpoint (what is checked lives in `Problem`)."""

    grid_points: int = setting(
        1_000_000, Count(1), flag="--grid-points", metavar="N", label="grid points \u2265",
        help="points of the dense grid over X x Y, at least")
    float32_screen: bool = setting(
        True, Switch(), label="float32 screen of the grids",
        help="sweep the MPDI and rate grids in float32, re-check the candidates in float64")
    adversarial_starts: int = setting(
        64, Count(0), flag="--adversarial-starts", metavar="N", label="ascent starts",
        help="starts of the gradient ascent on lam_max(D)")
    adversarial_steps: int = setting(100, Count(0), label="ascent steps",
                                     help="steps of each gradient ascent")
    top_counterexamples: int = setting(5, Count(0), label="counterexamples kept",
                                       help="distinct worst points kept from the search")
    max_boxes: int = setting(
        2_000_000, _BOXES, flag="--max-boxes", label="MPDI proof budget", unit=" boxes",
        metavar="N", help=f"box budget of the MPDI proof; {GPU_MAX_BOXES:,} on a GPU when not "
                          "given")
    rate_boxes: int = setting(
        250_000, _BOXES, flag="--rate-boxes", label="rate proof budget", unit=" boxes",
        metavar="N", help="box budget of the proved rate lam_cert, branch and bound and MPDI "
                          "decisions together")
    residual_boxes: int = setting(
        100_000, _BOXES, flag="--residual-boxes", label="residual bound budget",
        unit=" boxes", metavar="N", help="box budget of each bound of the boundary residual")
    lipschitz_boxes: int = setting(
        100_000, _BOXES, flag="--lipschitz-boxes", label="dk/dy bound budget", unit=" boxes",
        metavar="N", help="box budget of each local bound of ||dk/dy||")
    dissipation_boxes: int = setting(
        400_000, _BOXES, flag="--dissipation-boxes", label="dissipation proof budget",
        unit=" boxes", metavar="N",
        help="box budget of the dissipation certificate (all its proofs)")
    metric_boxes: int = setting(
        300_000, _BOXES, flag="--metric-boxes", label="metric proof budget", unit=" boxes",
        metavar="N",
        help="box budget of the stages with a metric that follows the state (all of them)")
    invariance_boxes: int = setting(
        200_000, _BOXES, flag="--invariance-boxes", label="invariance proof budget",
        unit=" boxes", metavar="N",
        help="box budget of the forward invariance of a plant region (all regions tried)")
    max_seconds: float | None = setting(
        None, Number(0.0, optional=True), flag="--max-seconds", label="wall-clock cap",
        unit=" s", metavar="S", none="none",
        help="cap on the whole run's wall clock: a proof it stops is UNKNOWN and says so; "
             "off by default: the box budgets give the same certificate on any machine")
    noise: float = setting(
        0.15, Number(0.0, strict=False), flag="--noise", metavar="V",
        label="noise bound \u2016v(t)\u2016 \u2264",
        help="bound on the measurement noise ||v(t)||_2 of the error bounds")
    sim_time: float | None = setting(
        None, Number(0.0, optional=True), flag="--sim-time", metavar="S", label="simulated time",
        unit=" s", none="automatic",
        help=f"simulated seconds; automatic when not given: {DEFAULT_SIM_TIME:g}, longer when "
             "the proved bound is slow")
    sim_dt: float = setting(2e-3, Number(0.0), label="simulation step", unit=" s",
                            help="integration step of the simulation")
    sim_initial_conditions: int = setting(6, Count(1), label="simulated starts",
                                          help="simulated runs per noise kind")
    seed: int = setting(0, Count(0), flag="--seed", metavar="N", label="seed",
                        help="random seed of the grids, ascents and simulation")
    required: tuple[str, ...] = setting(
        (CERTIFICATE_CHECK,), Checks(), flag="--require", metavar="CHECKS",
        label="required checks",
        help=f"checks that must pass (repeat the option or separate by commas); "
             f"{CERTIFICATE_CHECK} (the certificate) is always one of them; from: "
             f"{', '.join(CHECK_NAMES)}")
    allow_unknown: bool = setting(
        False, Switch(), flag="--allow-unknown", label="unknown allowed",
        help="an UNKNOWN required check other than the MPDI does not fail the gate (the MPDI "
             "must be PROVED to certify; ERROR always fails)")
    skip: tuple[str, ...] = setting(
        (), Checks(), flag="--skip", metavar="CHECKS", label="skipped checks",
        help=f"checks not to run (repeat the option or separate by commas; never "
             f"{CERTIFICATE_CHECK}, the certificate); from: "
             f"{', '.join(c for c in CHECK_NAMES if c != CERTIFICATE_CHECK)}")
    device: str = setting(
        "cpu", Device(), flag="--device", metavar="DEVICE", label="device",
        help="torch device: cpu, cuda or cuda:N. The MPDI grid, the falsifier and the "
             "branch-and-bound proofs (MPDI, rate, residual, dk/dy) run there; the "
             "simulation, LipSDP and the pre-flight stay on the CPU")
    workers: int = setting(
        1, Count(1), flag="--workers", metavar="N", label="local workers",
        help="run the grid and the proofs on a local Dask cluster of N processes (1: in "
             f"this process; at most {WORKERS_PER_CPU} per CPU)")
    scheduler: str = setting(
        "", Address(), flag="--scheduler", metavar="ADDRESS", label="Dask scheduler",
        none="none", help="run them on a running Dask cluster, e.g. tcp://host:8786 "
                          "(dask-jobqueue on SLURM/PBS, Kubernetes)")

    def __post_init__(self) -> None:
        validate(self, source="settings")


#: every setting's declaration, in the order of `VerifySettings`
DECLARATIONS: tuple[Declaration, ...] = tuple(
    Declaration(name=f.name, **f.metadata["declaration"])
    for f in dataclasses.fields(VerifySettings))
DECLARED = {d.name: d for d in DECLARATIONS}
FIELD_NAMES = tuple(DECLARED)

#: settings of older versions that are refused, with what replaces them: the per-proof
#: seconds (a certificate that depended on the machine's speed) became box budgets
RETIRED = {
    "proof_seconds": "max_boxes", "rate_seconds": "rate_boxes",
    "residual_seconds": "residual_boxes", "lipschitz_seconds": "lipschitz_boxes",
    "dissipation_seconds": "dissipation_boxes",
}
#: how the rows of an older certificate name the retired settings it holds
RETIRED_LABELS = {
    "proof_seconds": ("MPDI proof time budget", " s"), "rate_seconds": ("rate time budget", " s"),
    "residual_seconds": ("residual time budget", " s"),
    "lipschitz_seconds": ("dk/dy time budget", " s"),
    "dissipation_seconds": ("dissipation time budget", " s"),
}


def flag_of(name: str) -> str:
    """The option of setting (or retired setting) `name`: '--max-boxes', '--proof-seconds'."""
    decl = DECLARED.get(name)
    if decl is not None and decl.flag:
        return decl.flag
    return "--" + name.replace("_", "-")


def retired_message(name: str, source: str, *, as_flag: bool = False) -> str:
    """One line refusing a retired setting and naming its replacement."""
    new = RETIRED[name]
    old, repl = (flag_of(name), flag_of(new)) if as_flag else (name, new)
    cap = "--max-seconds" if as_flag else "max_seconds"
    where = f"{source} " if source else ""
    return (f"{where}{old} was replaced by {repl}, a budget of boxes: the same certificate on "
            f"any machine (for a wall-clock cap on the whole run, {cap})")


def validate(s: VerifySettings, source: str = "settings") -> None:
    """Check every field against its rule and the rules between fields; raise one
    `SettingsError` line."""
    for decl in DECLARATIONS:
        value = getattr(s, decl.name)
        need = decl.rule.problem(value)
        if need is not None:
            raise SettingsError(f"{source} {decl.name} must be {need}; got {value!r}")
    if CERTIFICATE_CHECK not in s.required:
        raise SettingsError(f"{source} required must include {CERTIFICATE_CHECK}: the MPDI is "
                            "the certificate and cannot be dropped (list other checks beside "
                            f"it, e.g. {[CERTIFICATE_CHECK, 'residual']}); got {list(s.required)}")
    if CERTIFICATE_CHECK in s.skip:
        raise SettingsError(f"{source} skip cannot include {CERTIFICATE_CHECK}: the MPDI is the "
                            "certificate and always runs (bound its work with max_boxes "
                            f"instead); got {list(s.skip)}")
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


def make_settings(values: dict[str, Any], source: str = "settings") -> VerifySettings:
    """Build settings from a mapping (each value brought to its declaration's type: an int
    to a float, a comma-separated string to check names), refusing unknown and retired keys
    with one line."""
    retired = sorted(set(values) & set(RETIRED))
    if retired:
        raise SettingsError(retired_message(retired[0], source))
    unknown = sorted(set(values) - set(FIELD_NAMES))
    if unknown:
        raise SettingsError(f"{source}: unknown setting(s) {', '.join(unknown)} "
                            f"(known: {', '.join(FIELD_NAMES)})")
    clean = {k: DECLARED[k].rule.coerce(v) for k, v in values.items()}
    if "max_boxes" not in clean and str(clean.get("device", "")).startswith("cuda"):
        clean["max_boxes"] = GPU_MAX_BOXES
    try:
        settings = VerifySettings(**clean)
    except SettingsError as exc:
        raise SettingsError(str(exc).replace("settings ", f"{source} ", 1)) from None
    return settings


def settings_rows(values: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The reports' settings rows of a certificate's settings: (label, value with its unit),
    declared settings in declaration order, then any other key (an older certificate's, a
    retired one with its old label) as it is."""
    values = dict(values or {})
    rows = [(d.label, d.text(values.pop(d.name))) for d in DECLARATIONS if d.name in values]
    for key, value in values.items():
        label, unit = RETIRED_LABELS.get(key, (key, ""))
        text = (", ".join(map(str, value)) if isinstance(value, (list, tuple))
                else "none" if value is None else f"{value:g}{unit}"
                if isinstance(value, float) else f"{value}{unit}")
        rows.append((label, text))
    return rows


def required_checks(settings: VerifySettings) -> list[str]:
    """The checks whose failure fails the gate: the settings' `required`, with the MPDI (the
    certificate) first should they lack it (validated settings never do)."""
    required = list(settings.required)
    return required if CERTIFICATE_CHECK in required else [CERTIFICATE_CHECK, *required]


#: the declared defaults, as settings (the budgets a prover uses when its caller gives none)
DEFAULTS = VerifySettings()
