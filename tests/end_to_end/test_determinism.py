"""The same checkpoint gets the same certificate on a busy machine as on a quiet one: every
budget counts boxes, and without `max_seconds` nothing reads the clock to decide anything.

Each shipped example is verified twice, the second time beside processes that keep every
CPU busy, and the certificates are compared with what depends on the clock or the machine
removed (`bench/same_numbers.py`'s VOLATILE keys: timings, dates, versions). Equality is
asserted, never a time."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.same_numbers import scrub
from certify.model import checkpoint
from certify.settings import VerifySettings, usable_cpus
from certify.verify import verify

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted(path.stem for path in (ROOT / "examples").glob("*.ckpt"))


@contextlib.contextmanager
def busy_cpus() -> Iterator[None]:
    """One process spinning on each CPU this process may use, for the block."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(usable_cpus())]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
        for hog in hogs:
            hog.wait()


@pytest.mark.slow
@pytest.mark.parametrize("name", EXAMPLES)
def test_a_busy_machine_gives_the_same_certificate(name):
    ck = checkpoint.load(str(ROOT / "examples" / f"{name}.ckpt"))
    # every budget counts boxes, as shipped, but smaller where a proof is long (the same
    # mechanism decides a small budget and a large one: the test needs no more than these);
    # the simulation reads no clock and costs seconds: not run
    # (above two states, where each box costs more, smaller still)
    side = 60_000 if ck.problem.system.n <= 3 else 8_000
    settings = VerifySettings(grid_points=100_000, rate_boxes=side, lipschitz_boxes=side,
                              residual_boxes=side, dissipation_boxes=side,
                              metric_boxes=60_000, skip=("simulation",))

    def certificate() -> dict:
        return scrub(json.loads(verify(ck, settings, figures=False).to_json()))

    alone = certificate()
    with busy_cpus():
        crowded = certificate()
    assert crowded == alone
    assert alone["verdict"] == ("NOT CERTIFIED" if name == "vdp" else "CERTIFIED")
