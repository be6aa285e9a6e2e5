"""certify.search.distributed.executor: serial and Dask executors give the same results in the same
order; a
killed worker loses nothing; a bad scheduler address is exit 2 with one line; the policy
keys workers/scheduler/device are read from [tool.certify]."""

from __future__ import annotations

import functools
import os
import signal
import time

import numpy as np
import pytest
import torch

from certify.search.distributed.executor import (
    DaskExecutor,
    SerialExecutor,
    chunk_ranges,
    current_executor,
    executor_from_settings,
    using,
)
from certify.settings import VerifySettings

from ..cli_helpers import run_cli, save_linear
from ..conftest import random_network
from .conftest import gone


def square_killing(x: int, victim: int) -> int:
    """x * x, except in the worker process `victim`, which SIGKILLs itself in the middle of
    its first task: the kill falls inside a task by construction, not by a timer's luck. The
    sleep keeps both workers busy, so each is handed tasks."""
    if os.getpid() == victim:
        os.kill(victim, signal.SIGKILL)
    time.sleep(0.4)
    return x * x


def _cached_keys() -> list[str]:
    from certify.search.distributed import executor

    return list(executor._cache)


def offset(payload: dict, a: int, b: int) -> list[int]:
    return [payload["base"] + i for i in range(a, b)]


@pytest.fixture(scope="module")
def dask2():
    ex = DaskExecutor(workers=2)
    yield ex
    ex.close()


def test_chunk_ranges_cover_in_order():
    assert chunk_ranges(10, 3) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_ranges(100, 4, align=16) == [(0, 32), (32, 64), (64, 96), (96, 100)]
    assert chunk_ranges(5, 10) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]
    assert chunk_ranges(0, 3) == []


def test_serial_is_the_default():
    assert isinstance(current_executor(), SerialExecutor) and not current_executor().remote
    assert isinstance(executor_from_settings(VerifySettings()), SerialExecutor)
    ex = SerialExecutor()
    assert ex.map(abs, [-3, 1, -2]) == [3, 1, 2]
    assert ex.map_chunks(offset, {"base": 10}, [(0, 2), (2, 3)]) == [[10, 11], [12]]
    with using(ex):
        assert current_executor() is ex
    assert current_executor() is not ex


@pytest.mark.slow
def test_dask_map_keeps_order(dask2):
    assert dask2.workers == 2
    items = list(range(-40, 0))
    assert dask2.map(abs, items) == [abs(i) for i in items]
    assert dask2.map_chunks(offset, {"base": 5}, [(0, 3), (3, 4), (4, 4)]) == [[5, 6, 7], [8],
                                                                            []]


@pytest.mark.slow
def test_killed_worker_changes_nothing(doomed2):
    """SIGKILL one worker process while the tasks run: Dask re-runs its tasks on the worker
    left (whether or not the dead one comes back); the results are the same, in order."""
    pids = list(doomed2.worker_pids().values())
    assert len(pids) == 2 and os.getpid() not in pids
    victim = pids[0]
    out = doomed2.map(functools.partial(square_killing, victim=victim), list(range(10)))
    assert out == [i * i for i in range(10)]
    assert gone(victim)  # it really died


def test_close_survives_a_failing_dask_teardown(caplog):
    """Dask's own teardown can raise after a worker died (its status watcher meets a worker
    address it never recorded): every result is in by then, so close() logs it and returns,
    and the client is closed all the same."""

    class Client:
        closed = False

        def close(self):
            Client.closed = True

    class Cluster:
        def close(self):
            raise KeyError("tcp://127.0.0.1:45237")

    ex = DaskExecutor.__new__(DaskExecutor)
    ex._scattered, ex.client, ex._cluster = {"k": 1}, Client(), Cluster()
    with caplog.at_level("WARNING", logger="certify.search.distributed.executor"):
        ex.close()
    assert Client.closed and ex._scattered == {}
    assert "KeyError" in caplog.text and "45237" in caplog.text


def test_problem_payload_rebuilds_the_same_problem(system3):
    from certify.model.problem import Problem
    from certify.search.distributed.payload import problem_from_payload, problem_payload
    from certify.search.grid import GridKernel

    problem = Problem(system=system3, network=random_network(3, 2, seed=3), lam=0.5,
                      P=system3.P)
    payload = problem_payload(problem)
    import pickle

    assert all(not isinstance(v, torch.Tensor) for v in payload["state"].values())
    again = problem_from_payload(pickle.loads(pickle.dumps(payload)))
    z = torch.rand(50, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    z = torch.as_tensor(np.vstack([system3.X, system3.Y])[:, 0]) + z * torch.as_tensor(
        np.diff(np.vstack([system3.X, system3.Y]), axis=1)[:, 0])
    assert torch.equal(GridKernel(problem)(z), GridKernel(again)(z))
    assert problem_from_payload(payload) is problem_from_payload(payload)  # built once


@pytest.mark.slow
def test_mpdi_grid_on_dask_equals_serial(system3, dask2):
    """The MPDI falsifier's grid sweep on 2 Dask workers finds the same points and values
    and counts the same violations as in this process."""
    from certify.checks.mpdi import falsify_mpdi
    from certify.model.problem import Problem

    problem = Problem(system=system3, network=random_network(3, 2, seed=5), lam=0.5,
                      P=system3.P)
    settings = VerifySettings(grid_points=40_000, adversarial_starts=4, adversarial_steps=5)
    serial = falsify_mpdi(problem, settings)
    with using(dask2):
        remote = falsify_mpdi(problem, settings)
    assert serial.grid_points == remote.grid_points
    assert serial.above_threshold == remote.above_threshold and serial.above_threshold > 0
    assert serial.best_value == remote.best_value
    assert np.array_equal(serial.top_points, remote.top_points)
    assert np.array_equal(serial.top_values, remote.top_values)


def test_bad_scheduler_is_exit_2_one_line(tmp_path, capsys):
    ckpt = save_linear(tmp_path / "lin.ckpt")
    t0 = time.perf_counter()
    code, out, err = run_cli(capsys, "run", ckpt, "--no-config", "--scheduler",
                             "tcp://127.0.0.1:9", "--json", str(tmp_path / "c.json"))
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("certify: error: --scheduler tcp://127.0.0.1:9: cannot connect")
    assert not (tmp_path / "c.json").exists()
    assert time.perf_counter() - t0 < 60  # the connect timeout, not a hang


def test_policy_keys_from_pyproject(tmp_path, monkeypatch, capsys):
    from certify.cli.config import load_settings

    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(
        '[tool.certify]\nworkers = 3\nscheduler = "tcp://10.0.0.1:8786"\ndevice = "cpu"\n')
    settings, _ = load_settings({})
    assert (settings.workers, settings.scheduler, settings.device) == \
        (3, "tcp://10.0.0.1:8786", "cpu")
    settings, _ = load_settings({"workers": 2, "scheduler": ""})
    assert (settings.workers, settings.scheduler) == (2, "")
    (tmp_path / "pyproject.toml").write_text("[tool.certify]\nworkers = 0\n")
    ckpt = save_linear(tmp_path / "lin.ckpt")
    code, _, err = run_cli(capsys, "run", ckpt)
    assert code == 2 and "workers must be an int >= 1; got 0" in err and err.count("\n") == 1


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_is_exit_2(tmp_path, monkeypatch, capsys):
    ckpt = save_linear(tmp_path / "lin.ckpt")
    code, _, err = run_cli(capsys, "run", ckpt, "--no-config", "--device", "cuda")
    assert code == 2 and "--device cuda: torch sees no CUDA device" in err
    assert err.count("\n") == 1
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text('[tool.certify]\ndevice = "cuda"\n')
    code, _, err = run_cli(capsys, "run", ckpt)
    assert code == 2 and "no CUDA device" in err
    code, _, err = run_cli(capsys, "run", ckpt, "--no-config", "--device", "tpu")
    assert code == 2 and "device must be 'cpu' or 'cuda'" in err


def test_device_cpu_explicitly_is_the_same_path(system3):
    """`device = "cpu"` runs the device-aware grid/ascent path (points made on the device,
    random numbers drawn on the CPU and moved): same outcome as the default."""
    from certify.arith.device import resolve_device
    from certify.checks.mpdi import falsify_mpdi
    from certify.model.problem import Problem

    problem = Problem(system=system3, network=random_network(3, 2, seed=7), lam=0.5,
                      P=system3.P)
    assert problem.on("cpu") is problem and resolve_device("cpu") == torch.device("cpu")
    base = dict(grid_points=5000, adversarial_starts=4, adversarial_steps=5)
    a = falsify_mpdi(problem, VerifySettings(**base))
    b = falsify_mpdi(problem, VerifySettings(**base, device="cpu"))
    assert a.best_value == b.best_value and np.array_equal(a.top_points, b.top_points)
    assert problem.P_t.device.type == "cpu"


def _vdp_certified():
    from pathlib import Path

    from certify.model import checkpoint

    return checkpoint.load(str(Path(__file__).parents[2] / "examples" / "vdp_certified.ckpt"))


#: a box budget that ends the vdp_certified proof before it closes (it needs about 3300)
BUDGET = 1200


@pytest.fixture(scope="module")
def serial_proof():
    from certify.prove.mpdi import prove_mpdi

    problem = _vdp_certified().problem
    return problem, prove_mpdi(problem, max_boxes=BUDGET)


def _same(a, b) -> None:
    assert a.status == b.status
    assert a.upper == b.upper and a.lower == b.lower
    assert a.stats.boxes_processed == b.stats.boxes_processed
    assert a.boxes == b.boxes


@pytest.mark.slow
def test_mpdi_proof_on_dask_equals_serial(dask2, serial_proof):
    """Same box budget, serial vs 2 Dask workers: the same verdict, the same proved upper
    bound and best point value, the same boxes (a budget-ended proof, so the bound is an
    intermediate one and every round must have matched)."""
    from certify.prove.mpdi import prove_mpdi

    problem, serial = serial_proof
    with using(dask2):
        remote = prove_mpdi(problem, max_boxes=BUDGET)
    assert serial.stats.budget_exhausted and remote.stats.budget_exhausted
    built = dask2.client.run(_cached_keys)  # the boxes really went to the workers
    assert any(k.startswith("mpdi-boxes:") for keys in built.values() for k in keys)
    _same(serial, remote)


class _KillDuringRound:
    """The Dask executor, but a worker is SIGKILLed as round `at` is submitted (after the
    payload was scattered to it in round 1; with the pipeline, round `at - 1` is still in
    flight then): deterministic in rounds, unlike a wall-clock timer that a fast proof can
    outrun."""

    def __init__(self, inner, victim: int, at: int = 2) -> None:
        self.inner, self.victim, self.at, self.calls = inner, victim, at, 0
        self.killed_at: int | None = None

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def submit_chunks(self, fn, payload, items):
        self.calls += 1
        if self.calls == self.at:
            os.kill(self.victim, signal.SIGKILL)
            self.killed_at = self.calls
        return self.inner.submit_chunks(fn, payload, items)


@pytest.mark.slow
def test_killed_worker_mid_proof_changes_nothing(doomed2, serial_proof):
    """SIGKILL a worker while a round of the MPDI proof runs on 2 workers: the same outcome."""
    from certify.prove.mpdi import prove_mpdi

    problem, serial = serial_proof
    victim = list(doomed2.worker_pids().values())[1]
    killer = _KillDuringRound(doomed2, victim)
    with using(killer):
        remote = prove_mpdi(problem, max_boxes=BUDGET)
    assert killer.killed_at == 2 and killer.calls >= 2  # killed mid-proof, between rounds
    assert gone(victim)
    _same(serial, remote)


def test_wire_format_round_trips_and_sends_only_the_slice():
    """Tensors cross to Dask workers as numpy arrays of their own: exact values and dtypes
    back (also inside tuples and the BoxEval dataclass), and a chunk that is a slice of a
    round's boxes pickles its own rows, not the whole round."""
    import pickle

    from certify.search.distributed.executor import WireArray, from_wire, to_wire
    from certify.search.evaluation import BoxEval

    big = torch.arange(60_000, dtype=torch.float64).reshape(-1, 6)
    chunk = (big[10:20], big[20:30], 3)
    wire = to_wire(chunk)
    assert isinstance(wire[0], WireArray) and wire[2] == 3
    assert len(pickle.dumps(wire)) < 4000 < len(pickle.dumps(chunk))
    back = from_wire(pickle.loads(pickle.dumps(wire)))
    assert torch.equal(back[0], big[10:20]) and torch.equal(back[1], big[20:30])
    ev = BoxEval(upper=torch.tensor([1.5, float("nan")]), centre_value=torch.tensor([0.25, -1.0]),
                 score=None)
    again = from_wire(pickle.loads(pickle.dumps(to_wire([ev, {"k": torch.tensor([1, 2])}]))))
    assert torch.equal(again[0].upper.nan_to_num(7.0), ev.upper.nan_to_num(7.0))
    assert torch.equal(again[0].centre_value, ev.centre_value) and again[0].score is None
    assert again[1]["k"].dtype == torch.int64 and again[1]["k"].tolist() == [1, 2]


def test_round_batch_fills_the_workers_and_keeps_small_runs_serial():
    from certify.search.distributed.executor import BOXES_PER_WORKER, round_batch

    class Remote:
        remote = True

        def __init__(self, workers: int) -> None:
            self.workers = workers

    assert round_batch(SerialExecutor(), 1024) == 1024
    assert round_batch(Remote(1), 1024) == round_batch(Remote(2), 1024) == 1024
    assert round_batch(Remote(3), 1024) * 2 >= 3 * BOXES_PER_WORKER
    assert round_batch(Remote(64), 1024) * 2 == 64 * BOXES_PER_WORKER
    assert round_batch(Remote(64), 10**6) == 10**6  # never smaller than asked


@pytest.mark.slow
def test_cli_workers_2_gives_the_serial_certificate(tmp_path, capsys):
    """`certify run --workers 2` end to end: the same exit code, verdict and proved numbers
    as the serial run (the grid and the MPDI rounds run on a local Dask cluster)."""
    import json

    ckpt = save_linear(tmp_path / "lin.ckpt")
    small = ("--no-config", "--grid-points", "20000", "--adversarial-starts", "4",
             "--sim-time", "1", "--quiet")
    serial_json, dask_json = tmp_path / "serial.json", tmp_path / "dask.json"
    code_s, _, _ = run_cli(capsys, "run", ckpt, *small, "--json", str(serial_json))
    code_d, _, err = run_cli(capsys, "run", ckpt, *small, "--workers", "2",
                             "--json", str(dask_json))
    assert code_s == code_d == 0, err
    serial, dask = json.loads(serial_json.read_text()), json.loads(dask_json.read_text())
    assert serial["verdict"] == dask["verdict"] == "CERTIFIED"
    assert dask["settings"]["workers"] == 2
    for name in ("mpdi", "rate"):
        for key in ("status", "lower", "upper", "proved_lower", "sampled_upper"):
            assert serial["checks"][name].get(key) == dask["checks"][name].get(key), (name, key)
