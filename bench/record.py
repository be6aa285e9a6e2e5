"""Where the benchmarks' JSON lines go: printed, and appended to a results file.

Every bench script reports through `emit(record)`: the record is printed as one JSON line
(as before) and appended, tagged with its run, to `bench/results/<script>.jsonl`, which
`bench/performance_page.py` reads to write `docs/performance.md`. The tag is the same for
every line of one process:

- `run`: when this module was first imported in the process (UTC, ISO 8601, seconds: at the
  script's start, or at its first record where the script imports it then), the key the
  page groups by;
- `commit`: `git describe --always --dirty` of the checkout (`null` outside git);
- `script`: the bench script's file stem;
- `host`: the machine's name and CPU count, so numbers from different machines are not
  read side by side;
- `load`: the 1-minute load average when the run started (wall seconds of a run on a
  loaded machine are long; CPU seconds move less).

`CERTIFY_BENCH_RECORD` redirects the file (a path) or turns recording off (`0` or empty).
The printed line is the record alone, without the tag.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
_STARTED = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
_LOAD = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
_TAG: dict | None = None


def _commit() -> str | None:
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"],
                             cwd=Path(__file__).resolve().parent, capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def script_name() -> str:
    """The running bench script's stem (`run` for `python bench/run.py`)."""
    return Path(sys.argv[0]).stem or "python"


def run_tag() -> dict:
    """The tag of this process's run (computed once)."""
    global _TAG
    if _TAG is None:
        _TAG = {"run": _STARTED.isoformat(), "commit": _commit(), "script": script_name(),
                "host": f"{platform.node()} ({os.cpu_count()} CPUs)", "load": _LOAD}
    return _TAG


def record_path() -> Path | None:
    """The file this process appends to, or None when recording is off."""
    env = os.environ.get("CERTIFY_BENCH_RECORD")
    if env is not None:
        return Path(env) if env not in ("", "0") else None
    return RESULTS / f"{script_name()}.jsonl"


def emit(record: dict) -> None:
    """Print `record` as one JSON line; append it with the run's tag to the results file."""
    print(json.dumps(record), flush=True)
    path = record_path()
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps({**run_tag(), **record}) + "\n")
