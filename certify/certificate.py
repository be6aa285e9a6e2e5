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
from certify.results import (
    RESULT_TYPES,
    Status,
    from_jsonable,
    to_jsonable,
)

SCHEMA_NAME = "certify-certificate"
SCHEMA_VERSION = 1

#: Verdicts, and the exit code of `certify run` for each.
EXIT_CODES = {"CERTIFIED": 0, "NOT CERTIFIED": 1, "INCONCLUSIVE": 3}


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
    #: arrays for figures (plain lists), keyed by figure name; see the schema document.
    figures: dict[str, Any] = field(default_factory=dict)
    schema: str = SCHEMA_NAME
    schema_version: int = SCHEMA_VERSION

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
        if data.get("schema_version") != SCHEMA_VERSION:
            raise CertifyError(f"certificate schema version {data.get('schema_version')!r} is "
                               f"not supported (this certify reads {SCHEMA_VERSION})")
        checks = {}
        for name, raw in (data.get("checks") or {}).items():
            if name not in RESULT_TYPES:
                raise CertifyError(f"certificate has an unknown check '{name}'")
            checks[name] = from_jsonable(RESULT_TYPES[name], raw)
        kwargs = {k: v for k, v in data.items() if k != "checks"}
        try:
            return cls(checks=checks, **kwargs)
        except TypeError as exc:
            raise CertifyError(f"malformed certificate ({exc})") from None

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

    Any required VIOLATED or ERROR -> NOT CERTIFIED; else any required UNKNOWN (or
    SKIPPED) -> INCONCLUSIVE unless `allow_unknown`; else CERTIFIED.
    """
    failed = [n for n in required if n in checks and checks[n].status in
              (Status.VIOLATED, Status.ERROR)]
    unknown = [n for n in required if n not in checks or checks[n].status in
               (Status.UNKNOWN, Status.SKIPPED)]
    if failed:
        return "NOT CERTIFIED", "failed: " + ", ".join(
            f"{n} ({checks[n].status.value})" for n in failed)
    if unknown and not allow_unknown:
        return "INCONCLUSIVE", "not established: " + ", ".join(unknown)
    note = f" (allowed unknown: {', '.join(unknown)})" if unknown else ""
    return "CERTIFIED", "all required checks proved: " + ", ".join(required) + note


def exit_code(certificate: Certificate) -> int:
    """0 certified, 1 not certified, 3 inconclusive (2 is for bad input, raised earlier)."""
    return EXIT_CODES[certificate.verdict]


def _num(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, float) and value != value:
        return "NaN"
    return f"{value:.{digits}g}" if isinstance(value, (int, float)) else str(value)


def summary_rows(certificate: Certificate) -> list[dict[str, str]]:
    """One row per check: name, status, sampled side, proved side, what it means."""
    rows = []
    labels = {
        "necessary": ("pre-flight q on manifold", "q_max", "q_upper"),
        "mpdi": ("MPDI max lam_max(D)", "lower", "upper"),
        "rate": ("certified rate lam_cert", "sampled_upper", "proved_lower"),
        "residual": ("BC residual eps_bar", "sampled", "upper"),
        "lipschitz": ("Lipschitz L in y", "sampled", "value"),
    }
    for name, result in certificate.checks.items():
        label, lo_key, hi_key = labels.get(name, (name, None, None))
        sampled = _num(getattr(result, lo_key, None)) if lo_key else ""
        proved = _num(getattr(result, hi_key, None)) if hi_key else ""
        if name == "bounds" and getattr(result, "iss", None) is not None:
            sampled, proved = "", _num(result.iss.bias) if result.iss.applicable else "—"
            label = f"ISS error bound at vbar={result.vbar:g}"
        if name == "simulation":
            ratios = [r.max_ratio for r in result.runs if r.max_ratio is not None]
            sampled = _num(max(ratios)) if ratios else "—"
            label = "simulation error/bound"
        rows.append({"check": name, "label": label, "status": result.status.value,
                     "sampled": sampled, "proved": proved, "message": result.message,
                     "required": "yes" if name in certificate.required else ""})
    return rows
