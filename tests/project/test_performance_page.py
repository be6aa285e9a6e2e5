"""docs/performance.md is written for readers: no table wider than `MAX_COLUMNS` (a wide one
is split, each part repeating the columns that name its rows), long texts as notes under the
table, and no path of the machine that ran the benchmark."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _page_module():
    spec = importlib.util.spec_from_file_location("performance_page",
                                                  ROOT / "bench" / "performance_page.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _records() -> list[dict]:
    tag = {"run": "2026-01-01T00:00:00+00:00", "commit": "abc1234", "script": "compare",
           "host": "ci (2 CPUs)"}
    rows = []
    for i, (system, design) in enumerate((("vdp", "lmi"), ("vdp", "bound"),
                                          ("lorenz", "lmi"))):
        rows.append({**tag, "system": system, "design": design,
                     "checkpoint": f"/tmp/cmp{i}/{system}_{design}.ckpt",
                     "path": "/work/wt/someone/tree",
                     "outcome": f"the learned gain did not beat the linear design ({i}); "
                                "returning the linear design",
                     **{f"bounds.b{k}": 1.5 * k + i for k in range(12)},
                     "figure_s": {"mpdi": {"wall": 1.0 + i, "cpu": 0.5}},
                     "seconds": 3.25 + i})
    return rows


def test_wide_tables_split_paths_stripped_long_texts_as_notes(tmp_path):
    page_mod = _page_module()
    f = tmp_path / "compare.jsonl"
    f.write_text("\n".join(json.dumps(r) for r in _records()) + "\n")
    page = page_mod.render(page_mod.read_runs([f]))
    tables = [ln for ln in page.splitlines() if ln.startswith("| ")]
    widths = {ln.count("|") - 1 for ln in tables}
    assert max(widths) <= page_mod.MAX_COLUMNS
    headers = [ln for ln in tables if ln.startswith("| system | design |")]
    assert len(headers) >= 3  # split, each part naming its rows
    assert "/tmp" not in page and "/work" not in page and "someone" not in page
    assert "| vdp | bound | vdp_bound.ckpt |" in page
    assert re.search(r"\| vdp \| lmi \|.*\[1\]", page)
    assert "[1] the learned gain did not beat the linear design (0)" in page
    # every number is still there, once per row
    for k in range(12):
        assert f"bounds.b{k}" in page
    assert "figure_s.mpdi.wall" in page and "`figure_s.mpdi.cpu` = 0.5" in page


def test_the_shipped_page_is_readable():
    page = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    tables = [ln for ln in page.splitlines() if ln.startswith("| ")]
    assert tables and max(ln.count("|") - 1 for ln in tables) <= 8
    assert not re.search(r"(?<![\w.])/(tmp|work|home|root)/", page)


def test_the_design_table_keeps_the_newest_row_of_each_design(tmp_path):
    """A later run that re-measures one design replaces that row only."""
    page = _page_module()
    first = _records()
    later = {**first[1], "run": "2026-02-01T00:00:00+00:00", "commit": "def5678",
             "seconds": 99.0}
    new = {**first[0], "run": "2026-02-01T00:00:00+00:00", "commit": "def5678",
           "design": "metric", "seconds": 7.0}
    path = tmp_path / "compare.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in first + [later, new]) + "\n")
    rows = page.read_runs([path])["compare"]
    assert [(r["system"], r["design"]) for r in rows] == [
        ("vdp", "lmi"), ("vdp", "bound"), ("lorenz", "lmi"), ("vdp", "metric")]
    assert rows[1]["seconds"] == 99.0 and rows[0]["seconds"] == 3.25
    text = page.render({"compare": rows})
    assert "over 2 runs" in text and "def5678" in text and "abc1234" in text
