"""Write docs/performance.md from the JSON lines the benchmarks recorded.

Every bench script reports through `bench/record.py`, which appends each JSON line, tagged
with its run (`run`: the UTC start of the process, `commit`, `script`, `host`), to
`bench/results/<script>.jsonl`. This script reads those files (or the files named on the
command line), keeps the newest run of each script only (of `bench/compare.py` and
`bench/prove_suite.py`, the newest record of each row over all runs: `ROW_KEYS`), and
writes one table per kind of record (the record's `bench` field, else the script), one row
per record: numbers as the
bench printed them (floats to 4 significant digits), no narrative. Bench scripts without a
recorded run are listed as not run in this generation.

The page is for reading: a table wider than `MAX_COLUMNS` is split into several, each
repeating the columns that name the row; text longer than `MAX_TEXT` becomes a numbered note
under the table; paths are shown relative to the checkout, or by their file name when they
lie elsewhere (a build machine's temporary directories mean nothing to a reader); a field
that only says where a tree was checked out (`path`) is left out.

    python bench/performance_page.py                      # bench/results/ -> docs/performance.md
    python bench/performance_page.py FILE.jsonl ... -o -  # chosen files, page on stdout

To refresh a section, run its bench (e.g. `python bench/verify.py`), then this script.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
RESULTS = BENCH / "results"
PAGE = ROOT / "docs" / "performance.md"

#: fields of the run's tag, shown once per section rather than in every row
TAG = ("run", "commit", "script", "host", "load")
#: fields that only say where something was checked out on the machine that ran the bench
WHERE = {"path"}
#: columns of one table at most (the columns that name a row count too)
MAX_COLUMNS = 8
#: columns that name a row, repeated in each part of a split table
KEY_COLUMNS = 2
#: a text cell longer than this becomes a note under its table
MAX_TEXT = 48
#: an absolute path in a text: its directories and its file name
PATH = re.compile(r"(?<![\w.)\]])(/[\w.+-]+)+/([\w.+-]+)")
#: modules in bench/ that are not benchmarks (helpers, this script, the recipe of a shipped
#: example)
NOT_BENCHES = {"record", "instances", "performance_page", "vdp_metric_learned"}
#: series too long for a table cell (they stay in the JSON lines)
LONG = {"volume_history", "argmax", "runs_s", "counterexample", "figure", "png_bytes",
        "final", "statuses", "verdicts"}
#: scripts whose rows are named by these fields: the page keeps the newest record of each
#: row over all runs (a run that re-measures some rows replaces those only)
ROW_KEYS = {"compare": ("system", "design"), "prove_suite": ("instance", "summary")}
#: what each script measures, one line (the script's docstring says how)
WHAT = {
    "run": "`certify run` end to end as a user meets it, wall and CPU seconds, and start-up",
    "verify": "grid points per second of lam_max(D), planted violations, LipSDP, verify()",
    "lipsdp": "LipSDP-Neuron with its LMI re-check, the metric SDP and the joint-LMI observer",
    "prove": "the branch-and-bound prover on a true 5x30 instance; planted violations",
    "frontier": "the driver's batch choice (candidate pools vs a full scan) by frontier size",
    "reports": "seconds to render each report, and the size of the JSON certificate",
    "train": "paper-preset training",
    "prove_suite": "the prover on families of random networks (depth x width, n states)",
    "scale": "MPDI proofs against n; serial vs Dask workers; the paper arithmetic of workers",
    "budget": "whether time budgets hold on slow networks",
    "curvature": "the verification-aware training term: cost per step, proof sizes",
    "device_check": "box bounds on a GPU against the CPU and sampled values",
    "expr": "the compiled spec evaluators, per call",
    "parse": "the spec parser on hostile expressions; the built-ins",
    "remainder_gap": "the prover's Jacobian remainder against a sampled best-affine one",
    "tree_size": "the box count a complete MPDI proof needs (random-descent estimate)",
    "same_numbers": "certificates of two checkouts compared number for number",
    "compare": "learned gain vs LMI baseline vs paper preset (the README's design table)",
    "simulation": "the simulation check per shipped example, and a zero-gain observer's run",
}


def read_runs(paths: list[Path]) -> dict[str, list[dict]]:
    """script -> the records of its newest run (by the `run` tag; lines without one are
    skipped, as are lines that are not JSON objects)."""
    by_script: dict[str, list[dict]] = {}
    for path in paths:
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict) and "run" in rec:
                by_script.setdefault(rec.get("script") or path.stem, []).append(rec)
    newest = {}
    for script, recs in by_script.items():
        if script in ROW_KEYS:
            newest[script] = newest_rows(recs, ROW_KEYS[script])
            continue
        last = max(r["run"] for r in recs)
        newest[script] = [r for r in recs if r["run"] == last]
    return newest


def newest_rows(recs: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """The newest record of each row (the values of `keys`) over all runs, in the order the
    rows first appeared: a run that re-measured some rows replaces only those."""
    order: dict[tuple, int] = {}
    best: dict[tuple, dict] = {}
    for r in recs:
        k = tuple(r.get(key) for key in keys)
        order.setdefault(k, len(order))
        if k not in best or r["run"] >= best[k]["run"]:
            best[k] = r
    return [best[k] for k in sorted(best, key=order.__getitem__)]


def flatten(rec: dict, prefix: str = "") -> dict:
    """Scalar fields of `rec`, nested objects as dotted keys; long series left out."""
    out: dict = {}
    for key, value in rec.items():
        if not prefix and (key in TAG or key in WHERE):
            continue
        if key in LONG:
            continue
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        elif isinstance(value, list):
            if len(value) <= 4 and all(not isinstance(v, (dict, list)) for v in value):
                out[name] = value
        else:
            out[name] = value
    return out


def strip_paths(text: str) -> str:
    """Paths relative to the checkout; any other absolute path by its file name."""
    if text == str(ROOT):
        return "."
    text = text.replace(str(ROOT) + "/", "")
    return PATH.sub(lambda m: m.group(2), text)


def cell(value: object) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if value == 0:
            return "0"
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(cell(v) for v in value) + "]"
    return strip_paths(str(value)).replace("|", "\\|").replace("\n", " ")


def group_name(rec: dict, script: str) -> str:
    """The table a record goes to: its `bench` field, else its case's kind, else the
    script."""
    if "bench" in rec:
        return str(rec["bench"])
    if "case" in rec:
        return str(rec["case"]).split("/")[0].split("-")[0]
    if "summary" in rec:
        return "summary"
    return script


class Notes:
    """Long texts of one section, numbered once each ('[1]' in the cell)."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def cell(self, value: object) -> str:
        text = cell(value)
        if len(text) <= MAX_TEXT:
            return text
        if text not in self.texts:
            self.texts.append(text)
        return f"[{self.texts.index(text) + 1}]"

    def lines(self) -> list[str]:
        return [f"[{i + 1}] {t}" for i, t in enumerate(self.texts)]


def parts(cols: list[str], keys: list[str]) -> list[list[str]]:
    """`cols` (without `keys`) in runs of at most MAX_COLUMNS - len(keys), a run ending
    early rather than splitting columns of one dotted prefix ('figure_s.bounds.wall' and
    '.cpu') where it is at least half full."""
    room = max(1, MAX_COLUMNS - len(keys))
    out: list[list[str]] = [[]]

    def prefix(c: str) -> str:
        return c.rsplit(".", 1)[0] if "." in c else c

    for i, c in enumerate(cols):
        cur = out[-1]
        whole = [d for d in cols[i:] if prefix(d) == prefix(c)]
        starts = not cur or prefix(cur[-1]) != prefix(c)
        if len(cur) >= room or (starts and len(cur) + len(whole) > room
                                and len(cur) >= room / 2):
            out.append([])
        out[-1].append(c)
    return [p for p in out if p]


def table(rows: list[dict], notes: Notes | None = None) -> list[str]:
    notes = notes if notes is not None else Notes()
    flat = [flatten(r) for r in rows]
    cols: list[str] = []
    for f in flat:
        cols += [k for k in f if k not in cols and k != "bench"]
    # a column whose every value is the same across several rows goes above the table
    common = [c for c in cols if len(flat) > 1 and all(c in f for f in flat)
              and len({json.dumps(f[c]) for f in flat}) == 1]
    cols = [c for c in cols if c not in common]
    lines = []
    if len(flat) == 1 and len(cols) > 6:  # one record with many fields: one row per field
        lines += ["| field | value |", "|---|---|"]
        lines += [f"| {c} | {notes.cell(flat[0][c])} |" for c in cols]
        return lines

    # what names the instance (text, flags) before what was measured (numbers)
    def named(c: str) -> bool:
        return all(isinstance(f.get(c), (str, bool)) or f.get(c) is None for f in flat)
    cols = [c for c in cols if named(c)] + [c for c in cols if not named(c)]
    if common:
        lines.append("All rows: " + ", ".join(f"`{c}` = {notes.cell(flat[0][c])}"
                                              for c in common) + ".")
        lines.append("")
    if not cols:
        return lines
    keys = [c for c in cols[:KEY_COLUMNS] if named(c)] if len(cols) > MAX_COLUMNS else []
    for part in parts([c for c in cols if c not in keys], keys):
        shown = keys + part
        lines.append("| " + " | ".join(shown) + " |")
        lines.append("|" + "---|" * len(shown))
        for f in flat:
            lines.append("| " + " | ".join(notes.cell(f.get(c)) for c in shown) + " |")
        lines.append("")
    return lines[:-1]


def section(script: str, recs: list[dict]) -> list[str]:
    tag = recs[0]
    lines = [f"## `bench/{script}.py`", ""]
    if script in WHAT:
        lines += [WHAT[script][0].upper() + WHAT[script][1:] + ".", ""]
    runs = sorted({(r["run"], r.get("commit") or "unknown") for r in recs})
    if len(runs) > 1:
        lines += [f"The newest row of each {' and '.join(ROW_KEYS.get(script, ()))} over "
                  f"{len(runs)} runs: " + ", ".join(f"{run} (commit `{c}`)" for run, c in runs)
                  + f"; {tag.get('host') or 'unknown host'}.", ""]
    else:
        load = f", load {tag['load']} at the start" if tag.get("load") is not None else ""
        lines += [f"Run {tag['run']}, commit `{tag.get('commit') or 'unknown'}`, "
                  f"{tag.get('host') or 'unknown host'}{load}.", ""]
    groups: dict[str, list[dict]] = {}
    for r in recs:
        groups.setdefault(group_name(r, script), []).append(r)
    notes = Notes()
    for name, rows in groups.items():
        if len(groups) > 1:
            lines += [f"### {name}", ""]
        lines += table(rows, notes) + [""]
    if notes.texts:
        lines += ["Notes:", ""] + [f"{n}  " for n in notes.lines()[:-1]] \
            + notes.lines()[-1:] + [""]
    return lines


def benches() -> list[str]:
    return sorted(p.stem for p in BENCH.glob("*.py") if p.stem not in NOT_BENCHES)


def render(runs: dict[str, list[dict]]) -> str:
    lines = [
        "# Performance",
        "",
        "<!-- Generated by `python bench/performance_page.py` from bench/results/*.jsonl;"
        " do not edit by hand. -->",
        "",
        "Generated by `python bench/performance_page.py` from the JSON lines the benchmarks "
        "in `bench/` recorded in `bench/results/<script>.jsonl`: the newest run of each "
        "script (of the design comparison, the newest row of each design), one row per "
        "record, numbers as printed. To refresh a section, run its "
        "script (each says how in its docstring), then regenerate this page. Wall-clock "
        "seconds depend on the machine and its load: compare rows of one run, and read the "
        "host line of each section. What each number means is in the script's docstring.",
        "",
    ]
    order = [s for s in benches() if s in runs] + sorted(s for s in runs if s not in benches())
    for script in order:
        lines += section(script, runs[script])
    missing = [s for s in benches() if s not in runs]
    if missing:
        lines += ["## Not run in this generation", ""]
        lines += [f"- `bench/{s}.py`" + (f": {WHAT[s]}" if s in WHAT else "") for s in missing]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path,
                    help="JSON-lines files (default: bench/results/*.jsonl)")
    ap.add_argument("-o", "--output", default=str(PAGE), help="the page ('-': stdout)")
    args = ap.parse_args()
    files = args.files or sorted(RESULTS.glob("*.jsonl"))
    page = render(read_runs(files))
    if args.output == "-":
        sys.stdout.write(page)
    else:
        Path(args.output).write_text(page, encoding="utf-8")


if __name__ == "__main__":
    main()
