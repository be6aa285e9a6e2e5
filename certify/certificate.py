"""The Certificate: verdict, every check's result, settings, provenance; JSON; exit code.

Schema (version `SCHEMA_VERSION`) is documented in `docs/certificate-schema.md`. Reports
are pure functions of a Certificate, so a saved JSON can be re-rendered without verifying.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from certify.errors import CertifyError
from certify.figuredata import FigureData
from certify.presentation import ErrorHeadline, Presentation, error_headline
from certify.results import (
    RESULT_TYPES,
    Status,
    result_from_jsonable,
    to_jsonable,
)
from certify.settings import settings_rows

SCHEMA_NAME = "certify-certificate"
#: v2: a check may hold a `CheckFailure` record (`"failed": true`) instead of its own
#: result; a required check in ERROR gives INCONCLUSIVE (v1: NOT CERTIFIED).
#: v3: figure arrays at figure size (`certify.figuredata`: maps of at most 41 x 41 points,
#: 4 significant digits, merged prover boxes with `leaf_counts`); simulated series thinned
#: to at most 150 samples that keep every run's extremes; the simulated states `x`, `xhat`
#: written only on request (`trajectories`). v1 and v2 documents are read as they are, their
#: figure arrays brought to figure size on reading.
#: v3 also carries, optionally, the top-level "error_bound": the headline of the bounds check
#: (`certify.presentation.ErrorHeadline.to_dict`), derived from `checks.bounds` on writing
#: and ignored on reading (documents without it are read the same).
#: v4: settings with box budgets (`max_boxes`, `rate_boxes`, ...; `max_seconds`) where v3 had
#: the time budgets `proof_seconds`, ... (a v3 document's settings are shown as they are);
#: the top-level `overrides` (design values given instead of the checkpoint's; {} in older
#: documents); a check's result may carry `proof` (its proofs' `ProofStats`, with
#: `stopped_by_cap`), and a check may be NOT RUN (the verdict was decided before it).
SCHEMA_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 4)
#: lines of the JSON text are kept within this many characters where a list allows it
JSON_WIDTH = 100

#: Verdicts, and the exit code of `certify run` for each.
EXIT_CODES = {"CERTIFIED": 0, "NOT CERTIFIED": 1, "INCONCLUSIVE": 3}
#: Exit codes that are not verdicts: bad input or usage, and an internal error (a crash).
EXIT_BAD_INPUT = 2
EXIT_INTERNAL_ERROR = 4


@dataclass
class Certificate:
    """Everything `certify run` established about one checkpoint."""

    verdict: str  # "CERTIFIED" | "NOT CERTIFIED" | "INCONCLUSIVE"
    summary: str  # one line, for humans
    checks: dict[str, Any]  # check name -> result dataclass (see certify.results)
    required: list[str]
    settings: dict[str, Any]
    system: dict[str, Any]  # System.summary()
    lam: float
    P: list[list[float]]
    network: dict[str, Any]  # architecture + structure
    checkpoint: dict[str, Any]  # path, sha256, created, training summary
    versions: dict[str, str]
    timings: dict[str, float]
    created: str = ""
    #: design values the user gave instead of the checkpoint's (`certify run --lam/--metric`):
    #: {"lam": {"value": 0.45, "checkpoint": 0.5}, "metric": {...}}; {} for none (and in
    #: documents written before overrides existed)
    overrides: dict[str, Any] = field(default_factory=dict)
    #: arrays for figures (plain float lists); see `certify.figuredata` and the schema.
    figures: FigureData = field(default_factory=FigureData)
    schema: str = SCHEMA_NAME
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        # figure arrays at figure size here, so that reports drawn from this object and
        # from its saved JSON are the same
        self.figures = FigureData.coerce(self.figures).compact()

    def status_of(self, name: str) -> Status:
        result = self.checks.get(name)
        return Status.SKIPPED if result is None else result.status

    def title(self, name: str) -> str:
        """The report title of check `name` (its name when this certify does not know it)."""
        from certify.checks.registry import get_check  # the checks import torch: on demand

        try:
            return get_check(name).title or name
        except KeyError:
            return name

    def presentation(self, name: str) -> Presentation | None:
        """What the reports show for check `name`, from its presenter (`Check.present`);
        None when it did not run or this certify does not know it. The renderers read the
        checks only through this method and `title`."""
        from certify.checks.registry import presentation  # the checks import torch: on demand

        r = self.checks.get(name)
        return None if r is None else presentation(name, r, self)

    def settings_rows(self) -> list[tuple[str, str]]:
        """The rows of the reports' settings table: each override of the checkpoint's design
        ("lam", "0.45 (override; checkpoint 0.5)"), then every setting by the label and unit
        of its declaration (`certify.settings.settings_rows`; an older document's keys as
        they are)."""
        rows = []
        for name, label in (("lam", "design \u03bb"), ("metric", "metric P")):
            o = (self.overrides or {}).get(name)
            if isinstance(o, dict):
                rows.append((label, f"{_plain(o.get('value'))} (override; checkpoint "
                                    f"{_plain(o.get('checkpoint'))})"))
        return rows + settings_rows(self.settings)

    def error_headline(self) -> ErrorHeadline:
        """The error bound as the second headline after the verdict (or why there is none),
        from the bounds check's result and the system's state names; what it rests on from
        the other checks and the verdict (`certify.presentation.headline_basis`)."""
        return error_headline(self.checks.get("bounds"), (self.system or {}).get("states"),
                              checks=self.checks, verdict=self.verdict, lam=self.lam)

    def to_dict(self, *, trajectories: bool = False) -> dict[str, Any]:
        """The JSON form; each simulated run's states `x` and `xhat` only with
        `trajectories` (they are drawn only on request; empty lists otherwise). After the
        verdict and summary comes "error_bound", the error headline (`error_headline`)."""
        full = to_jsonable(self)
        data: dict[str, Any] = {}
        for key, value in full.items():
            data[key] = value
            if key == "summary":
                data["error_bound"] = to_jsonable(self.error_headline().to_dict())
        sim = data["checks"].get("simulation")
        if not trajectories and isinstance(sim, dict):
            for run in sim.get("runs") or []:
                if isinstance(run, dict):
                    run["x"], run["xhat"] = [], []
        return data

    def to_json(self, *, trajectories: bool = False) -> str:
        """The certificate as JSON text a person can open: one key per line, number lists
        wrapped at `JSON_WIDTH` characters (`format_json`); see `to_dict`."""
        return format_json(self.to_dict(trajectories=trajectories))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Certificate:
        if not isinstance(data, dict) or data.get("schema") != SCHEMA_NAME:
            raise CertifyError("not a certify certificate (schema name missing)")
        version = data.get("schema_version")
        if version not in READABLE_VERSIONS:
            raise CertifyError(f"certificate schema version {version!r} is not supported "
                               f"(this certify reads versions "
                               f"{', '.join(map(str, READABLE_VERSIONS))})")
        try:
            checks = {}
            for name, raw in (data.get("checks") or {}).items():
                if name not in RESULT_TYPES:
                    raise CertifyError(f"certificate has an unknown check '{name}'")
                checks[name] = result_from_jsonable(name, raw)
            # "error_bound" is derived from the bounds check: recomputed, never read
            kwargs = {k: v for k, v in data.items()
                      if k not in ("checks", "figures", "error_bound")}
            # an older document is read as it is and re-stamped with the current version
            kwargs["schema_version"] = SCHEMA_VERSION
            return cls(checks=checks, figures=FigureData.coerce(data.get("figures")),
                       **kwargs)
        except (TypeError, KeyError, ValueError, AttributeError) as exc:
            raise CertifyError(f"malformed certificate ({type(exc).__name__}: {exc})") from None

    @classmethod
    def load(cls, path: str | Path) -> Certificate:
        path = Path(path)
        if not path.is_file():
            raise CertifyError(f"certificate {path} not found")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise CertifyError(f"certificate {path} is not valid JSON ({exc})") from None
        try:
            return cls.from_dict(data)
        except CertifyError as exc:  # name the file the message is about
            raise CertifyError(f"{path}: {exc}") from None


def _plain(value: Any) -> str:
    """A number or matrix of an override, as given."""
    if isinstance(value, float):
        return f"{value:g}"
    return json.dumps(value) if isinstance(value, list) else str(value)


def format_json(data: Any, width: int = JSON_WIDTH) -> str:
    """JSON text of plain data (finite floats; NaN/Inf already spelled as strings): objects
    one key per line, indented one space per level; a list that fits on its line stays on
    it; a longer list of scalars is wrapped at `width` characters; any other list has one
    element per line. `json.loads` gives `data` back."""
    def scalar(v: Any) -> str:
        return json.dumps(v, allow_nan=False)

    def fmt(o: Any, ind: int) -> str:
        pad, inner = " " * ind, " " * (ind + 1)
        if isinstance(o, dict):
            if not o:
                return "{}"
            return ("{\n" + ",\n".join(f"{inner}{scalar(str(k))}: {fmt(v, ind + 1)}"
                                        for k, v in o.items()) + "\n" + pad + "}")
        if not isinstance(o, list):
            return scalar(o)
        if not any(isinstance(v, dict) for v in o):
            flat = json.dumps(o, separators=(", ", ": "), allow_nan=False)
            if ind + len(flat) <= width:
                return flat
        if o and not any(isinstance(v, (dict, list)) for v in o):
            lines, line = [], ""
            for item in map(scalar, o):
                if line and ind + 1 + len(line) + len(item) + 2 > width:
                    lines.append(line + ",")
                    line = item
                else:
                    line = f"{line}, {item}" if line else item
            lines.append(line)
            return "[" + ("\n" + inner).join(lines) + "]"
        return "[\n" + ",\n".join(inner + fmt(v, ind + 1) for v in o) + "\n" + pad + "]"

    return fmt(data, 0)


def exit_code(certificate: Certificate) -> int:
    """0 certified, 1 not certified, 3 inconclusive (2 bad input and 4 internal error are
    decided by the command line before or instead of a certificate)."""
    return EXIT_CODES[certificate.verdict]
