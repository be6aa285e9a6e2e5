"""Progress that tells the truth: one line per step with the time the certificate and JUnit
record, distinct keys for a step and a task of the same name, no long silences in logs."""

from __future__ import annotations

import io
import json
import re
import threading
import xml.etree.ElementTree as ET

import pytest

from certify.cli.display import ProgressDisplay
from certify.settings import CHECK_NAMES

from ..cli_helpers import FAST_POLICY, run_cli, save_linear

STEP_LINE = re.compile(r"^\[\d\d:\d\d:\d\d\] (\S+) +(NOT APPLICABLE|NOT RUN|\S+) +(\d+\.\d\d) s$")


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


@pytest.mark.slow
def test_step_times_shown_equal_certificate_and_junit(workdir, capsys):
    path = save_linear(workdir / "lin.ckpt")
    code, _, err = run_cli(capsys, "run", path, "--json", "c.json", "--junit", "c.xml")
    assert code == 0, err
    shown: dict[str, tuple[str, str]] = {}
    for line in err.splitlines():
        m = STEP_LINE.match(line)
        if m:
            assert m.group(1) not in shown, f"step {m.group(1)} printed twice"
            shown[m.group(1)] = (m.group(2), m.group(3))
    assert set(shown) == {*CHECK_NAMES, "figures", "reports"}, shown
    cert = json.loads((workdir / "c.json").read_text())
    junit = {c.get("name"): float(c.get("time"))
             for c in ET.parse(workdir / "c.xml").getroot().iter("testcase")}
    for name in CHECK_NAMES:
        status, seconds = shown[name]
        recorded = cert["timings"][name]
        assert status == cert["checks"][name]["status"]
        assert seconds == f"{recorded:.2f}"  # the same number, not a second stopwatch
        assert cert["checks"][name].get("seconds", recorded) == recorded
        assert abs(junit[name] - recorded) <= 5e-4
    assert shown["figures"][1] == f"{cert['timings']['figures']:.2f}"
    assert shown["reports"][0] == "written"


def test_a_step_and_a_task_of_the_same_name_do_not_collide():
    out = io.StringIO()
    d = ProgressDisplay(out, heartbeat=0)
    d.start_step("lipschitz")
    d.start("lipschitz", total=3)  # the check's own inner task, same name
    d.update("lipschitz")
    d.finish("lipschitz", "L <= 78.6885 (local, valid while y and y_e stay in Y); " * 3)
    d.finish_step("lipschitz", "PROVED", 10.61)
    d.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and lines[0].endswith("lipschitz ...")
    assert STEP_LINE.match(lines[1]).groups() == ("lipschitz", "PROVED", "10.61")
    assert d.shown == {"lipschitz": 10.61}


def test_plain_lines_never_go_silent_during_a_long_step():
    out = io.StringIO()
    d = ProgressDisplay(out, heartbeat=0.1)
    d.start_step("mpdi")
    d.start("mpdi proof", total=1.0)
    d.update("mpdi proof", 0.0, proved=0.4512, boxes=12_345, budget=2_000_000)
    # a long stretch with no event from the check: wait for the heartbeat's line itself (the
    # event), however late a busy machine schedules its thread; 60 s only catches a heartbeat
    # that never comes (it is due after 0.1 s)
    for _ in range(600):
        if "running" in out.getvalue():
            break
        threading.Event().wait(0.1)
    d.finish_step("mpdi", "PROVED", 0.6)
    d.close()
    status = [line for line in out.getvalue().splitlines() if "running" in line]
    assert status, out.getvalue()
    assert "mpdi proof 45.12% of the volume closed, 12,345 / 2,000,000 boxes" in status[0]


def test_rich_display_shows_each_step_once_with_its_time():
    out = io.StringIO()
    d = ProgressDisplay(out, rich=True)
    for name, seconds in (("necessary", 0.46), ("mpdi", 3.96)):
        d.start_step(name)
        d.start(f"{name} grid", total=10)
        d.update(f"{name} grid", 5)
        d.finish(f"{name} grid")
        d.finish_step(name, "PROVED", seconds)
    d.close()
    text = out.getvalue()
    assert text.count("necessary    PROVED") == 1 and "0.46 s" in text
    assert text.count("mpdi         PROVED") == 1 and "3.96 s" in text


def test_quiet_shows_nothing_but_still_knows_the_step():
    out = io.StringIO()
    d = ProgressDisplay(out, quiet=True)
    d.start_step("figures")
    assert d.current_step == "figures"
    d.finish_step("figures", "done", 0.1)
    d.close()
    assert out.getvalue() == "" and d.current_step is None
