"""The pipelined MPDI proof on Dask: serial == 1 worker == 2 workers (verdict, bounds, boxes,
counterexample) with rounds really in flight, on a budget-ended proof and on a violation; a
worker killed while a round is in flight changes nothing."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.distributed.executor import DaskExecutor, SerialExecutor

from .conftest import gone

pytestmark = pytest.mark.slow

#: a box budget that ends the vdp_certified proof before it closes (it needs about 2100), in
#: about 20 rounds of batch 64 (a batch the frontier fills, so rounds go in flight)
BUDGET = 1400
BATCH = 64
#: vdp_certified at 1.02 x its rate: a violation found after a few rounds, with rounds in
#: flight (the planted corner is one box per round: nothing to pipeline)
VIOLATED_RATE = 1.02


class CountingInFlight:
    """Wraps an executor; records the most rounds submitted and not yet collected."""

    def __init__(self, inner) -> None:
        self.inner, self.in_flight, self.max_in_flight, self.rounds = inner, 0, 0, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def submit_chunks(self, fn, payload, items):
        handle = self.inner.submit_chunks(fn, payload, items)
        self.in_flight += 1
        self.rounds += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        outer = self

        class Handle:
            def result(self):
                out = handle.result()
                outer.in_flight -= 1
                return out

            def cancel(self):
                handle.cancel()

        return Handle()


class KillWithRoundsInFlight(CountingInFlight):
    """SIGKILLs `victim` as round `at` is submitted, while the rounds before it are in
    flight (its chunk of the last one among them, queued or running, is lost with it)."""

    def __init__(self, inner, victim: int, at: int) -> None:
        super().__init__(inner)
        self.victim, self.at = victim, at
        self.in_flight_at_kill: int | None = None

    def submit_chunks(self, fn, payload, items):
        if self.rounds + 1 == self.at:
            self.in_flight_at_kill = self.in_flight
            os.kill(self.victim, signal.SIGKILL)
        return super().submit_chunks(fn, payload, items)


@pytest.fixture(scope="module")
def clusters():
    one, two = DaskExecutor(workers=1), DaskExecutor(workers=2)
    yield one, two
    one.close()
    two.close()


def _same(a, b) -> None:
    assert a.status is b.status and a.message == b.message
    assert a.upper == b.upper and a.lower == b.lower
    assert a.stats.boxes_processed == b.stats.boxes_processed
    assert a.stats.proved_volume_fraction == b.stats.proved_volume_fraction
    assert a.boxes == b.boxes
    assert (a.counterexample is None) == (b.counterexample is None)
    if a.counterexample is not None:
        assert a.counterexample == b.counterexample


def _vdp_problem():
    from certify.model import checkpoint

    path = Path(__file__).parents[2] / "examples" / "vdp_certified.ckpt"
    return checkpoint.load(str(path)).problem


@pytest.mark.parametrize("case", ["budget", "violation"])
def test_serial_one_and_two_workers_agree_with_rounds_in_flight(clusters, case):
    problem = _vdp_problem()
    if case == "budget":
        kw = {"max_boxes": BUDGET, "batch": BATCH}
    else:
        kw = {"lam": VIOLATED_RATE * problem.lam, "batch": BATCH}
    serial = prove_mpdi(problem, executor=SerialExecutor(), **kw)
    for ex in clusters:
        counted = CountingInFlight(ex)
        remote = prove_mpdi(problem, executor=counted, **kw)
        assert counted.rounds >= 4 and counted.max_in_flight == 2  # pipelined
        _same(serial, remote)
    if case == "budget":
        assert serial.status is Status.UNKNOWN and serial.stats.budget_exhausted
    else:
        assert serial.status is Status.VIOLATED and serial.counterexample.sound_bound > 0


def test_killed_worker_with_rounds_in_flight_changes_nothing(doomed2):
    """A worker SIGKILLed with a round in flight (and never restarted) changes nothing."""
    problem = _vdp_problem()
    kw = {"max_boxes": BUDGET, "batch": BATCH}
    serial = prove_mpdi(problem, executor=SerialExecutor(), **kw)
    victim = list(doomed2.worker_pids().values())[0]
    killer = KillWithRoundsInFlight(doomed2, victim, at=8)
    remote = prove_mpdi(problem, executor=killer, **kw)
    assert killer.in_flight_at_kill == 1 and killer.rounds > 8  # mid-proof, pipelined
    assert gone(victim)  # it really died
    _same(serial, remote)
