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
from certify.results import (
    RESULT_TYPES,
    Status,
    result_from_jsonable,
    to_jsonable,
)

SCHEMA_NAME = "certify-certificate"
#: v2: a check may hold a `CheckFailure` record (`"failed": true`) instead of its own
#: result; a required check in ERROR gives INCONCLUSIVE (v1: NOT CERTIFIED). Figure arrays
#: are laid out as in v1, so v1 documents are read unchanged.
SCHEMA_VERSION = 2
READABLE_VERSIONS = (1, 2)

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
    #: arrays for figures (plain float lists); see `certify.figuredata` and the schema.
    figures: FigureData = field(default_factory=FigureData)
    schema: str = SCHEMA_NAME
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        self.figures = FigureData.coerce(self.figures)

    def status_of(self, name: str) -> Status:
        result = self.checks.get(name)
        return Status.SKIPPED if result is None else result.status

    def to_dict(self) -> dict[str, Any]:
        return to_jsonable(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

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
            kwargs = {k: v for k, v in data.items() if k not in ("checks", "figures")}
            # a v1 document is read as it is and re-stamped with the current version
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
        return cls.from_dict(data)


def decide_verdict(checks: dict[str, Any], required: list[str],
                   allow_unknown: bool) -> tuple[str, str]:
    """Verdict and a one-line summary from the required checks' statuses.

    Any required VIOLATED -> NOT CERTIFIED (a counterexample stands on its own); else any
    required ERROR (the check failed internally: nothing was established either way) ->
    INCONCLUSIVE, whatever `allow_unknown` says; else any required UNKNOWN (or SKIPPED, not
    run, NOT APPLICABLE) -> INCONCLUSIVE unless `allow_unknown`; else CERTIFIED. Checks
    that are not required never change the verdict; one in ERROR is named in the summary.
    """
    def status(n: str) -> Status | None:
        return checks[n].status if n in checks else None

    violated = [n for n in required if status(n) == Status.VIOLATED]
    errors = [n for n in required if status(n) == Status.ERROR]
    unknown = [n for n in required if status(n) in (None, Status.UNKNOWN, Status.SKIPPED,
                                                    Status.NOT_APPLICABLE)]
    other_errors = [n for n in checks if n not in required and status(n) == Status.ERROR]
    aside = (f"; not required, ended in ERROR: {', '.join(other_errors)}"
             if other_errors else "")
    if violated:
        return "NOT CERTIFIED", "failed: " + ", ".join(
            f"{n} ({checks[n].status.value})" for n in violated) + aside
    if errors:
        return "INCONCLUSIVE", ("check error: " + ", ".join(errors) + " ended in ERROR "
                                "(internal failure, see its message)"
                                + (f"; not established: {', '.join(unknown)}" if unknown
                                   else "") + aside)
    if unknown and not allow_unknown:
        return "INCONCLUSIVE", "not established: " + ", ".join(unknown) + aside
    note = f" (allowed unknown: {', '.join(unknown)})" if unknown else ""
    return "CERTIFIED", "all required checks proved: " + ", ".join(required) + note + aside


def exit_code(certificate: Certificate) -> int:
    """0 certified, 1 not certified, 3 inconclusive (2 bad input and 4 internal error are
    decided by the command line before or instead of a certificate)."""
    return EXIT_CODES[certificate.verdict]
