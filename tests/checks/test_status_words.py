"""Status words that mean what they say, through the real CLI (issue 12.5, issue 8.5):
a vacuous bound is named on the verdict line, "no bound exists" is NOT APPLICABLE (never
UNKNOWN, never SKIPPED after simulating), and the simulation prints a short summary plus a
table of runs instead of one long line."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from ..cli_helpers import FAST_POLICY, A, C, K, run_cli, save_problem
from ..planted import linear_problem


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


@pytest.mark.slow
def test_vacuous_bound_on_the_verdict_line_in_json_and_table_of_runs(workdir, capsys):
    """X = [-1, 1]^2 (half-diagonal 1.41); with vbar = 4 the proved ISS bound is larger."""
    path = save_problem(workdir / "lin.ckpt", linear_problem(A, C, K, lam=0.3))
    code, out, err = run_cli(capsys, "run", path, "--noise", "4", "--sim-time", "3",
                             "--json", "c.json", "--junit", "c.xml", "--trajectories")
    assert code == 0, (out, err)
    verdict, headline = out.strip().splitlines()[-2:]  # the error bound after the verdict
    assert headline.startswith("error bound: ") and "; vacuous (larger than the box" in headline
    assert verdict.startswith("CERTIFIED: all required checks proved: mpdi; note: the proved "
                              "error bound ")
    assert "is valid but vacuous: larger than the box (half-diagonal of X 1.414)" in verdict
    cert = json.loads((workdir / "c.json").read_text())
    bounds = cert["checks"]["bounds"]
    assert bounds["status"] == "PROVED" and bounds["vacuous"] is True
    assert bounds["box_half_diagonal"] == pytest.approx(2 ** 0.5)
    # the number the note calls vacuous is the headline, larger than the half-diagonal
    said = float(re.search(r"error bound ([0-9.]+)", verdict).group(1))
    assert said > 2 ** 0.5 and said == pytest.approx(bounds["headline"], rel=5e-3)
    assert "valid but vacuous: larger than the box" in bounds["message"]
    # the simulation: one short line, then the table of runs with their valid windows
    sim_line = next(ln for ln in out.splitlines() if ln.startswith("  simulation: "))
    assert len(sim_line) < 400 and "see the table of runs" in sim_line
    table = out[out.index("  simulation runs:"):].splitlines()
    assert table[1].split() == ["run", "valid", "window", "(s)", "what", "ended", "it",
                                "max", "e/b", "peak", "after", "T", "bound/peak", "breach"]
    runs = cert["checks"]["simulation"]["runs"]
    assert len(table) >= len(runs) + 4  # header, one row per run, verdict, error bound
    for run in runs:
        assert run["window"] is not None and run["start"]
    # JUnit: every check passed or was not required; nothing red
    root = ET.parse(workdir / "c.xml").getroot()
    assert root.get("failures") == "0" and root.get("errors") == "0"
    # the simulated states are drawn on request only
    code, _, _ = run_cli(capsys, "report", "c.json", "--html", "t.html", "--trajectories")
    assert code == 0 and 'id="fig-simulation"' in (workdir / "t.html").read_text()


def test_no_bound_is_not_applicable_not_unknown_or_skipped(workdir, capsys):
    """K = 0 with an unstable plant: lam_cert <= 0, so no error bound exists at all."""
    unstable = np.array([[0.5, 1.0], [0.0, 0.2]])
    path = save_problem(workdir / "u.ckpt",
                        linear_problem(unstable, C, np.zeros((2, 1)), lam=0.3))
    code, out, _ = run_cli(capsys, "run", path, "--json", "c.json", "--require", "mpdi")
    assert code == 1
    cert = json.loads((workdir / "c.json").read_text())
    assert cert["checks"]["rate"]["status"] == "VIOLATED"
    bounds, sim = cert["checks"]["bounds"], cert["checks"]["simulation"]
    assert bounds["status"] == "NOT APPLICABLE"
    assert bounds["message"].startswith("no error bound exists: lam_cert = ")
    assert sim["status"] == "NOT APPLICABLE" and sim["runs"] == []  # nothing to compare with
    assert sim["message"].startswith("not applicable: no proved error bound to compare with")
    assert sim["message"].endswith("nothing was simulated.")
    assert "SKIPPED" not in out
    assert re.search(r"Error bounds \(Theorem 3, ISS\)\s+NOT APPLICABLE", out)
    assert re.search(r"Simulation vs bound\s+NOT APPLICABLE", out)
