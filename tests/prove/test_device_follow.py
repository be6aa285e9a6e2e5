"""The MPDI proof runs on the device of its problem (`--device cuda`): every tensor the prover,
its enclosures and decisions make follows the device of its inputs.

No GPU is needed to check that: with torch's default device set to `meta`, a tensor made
without an explicit device lands on `meta`, and the first operation that mixes it with the
problem's CPU tensors raises. So a run under that default that gives the same verdict, box
count and bound as a plain run made no tensor anywhere but on the problem's device."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
import torch

from certify.arith.device import PROOF_BATCH, proof_batch
from certify.enclose.options import Technique
from certify.prove.mpdi import _mpdi_remote, prove_mpdi, prove_rate

from ..enclose.test_preconditioner_choice import _problem


@contextlib.contextmanager
def default_device_meta() -> Iterator[None]:
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def _summary(out) -> tuple:
    return out.status, out.stats.boxes_processed, out.upper, out.lower


@pytest.mark.parametrize("n,kwargs", [
    (2, {}),  # Hertz's vertex bound, the mixed rows (n <= 3)
    (4, {}),  # the decision module (n >= 4): vertex Cholesky tests, the box's congruence
    (3, {"crown": False}),  # forward Taylor models only
    (2, {"taylor": False}),  # plain intervals
    (2, {"taylor": "interval"}),
])
@pytest.mark.slow
def test_prover_makes_every_tensor_on_its_problems_device(n: int, kwargs: dict) -> None:
    prob = _problem(3, n, 8.0)
    seeds = torch.zeros(2, n + 1, dtype=torch.float64)
    plain = prove_mpdi(prob, max_boxes=1500, batch=256, seeds=seeds, **kwargs)
    with default_device_meta():
        followed = prove_mpdi(prob, max_boxes=1500, batch=256, seeds=seeds,
                              **kwargs)
    assert plain.stats.boxes_processed > 0
    assert _summary(followed) == _summary(plain)


@pytest.mark.slow
def test_prover_reports_a_violation_found_on_its_device() -> None:
    """The counterexample's float value and sound lower bound are computed on the problem's
    device too (a rate far too high: the proof finds a violation at once)."""
    prob = _problem(5, 3, 8.0)
    plain = prove_mpdi(prob, lam=5.0, max_boxes=5000)
    with default_device_meta():
        followed = prove_mpdi(prob, lam=5.0, max_boxes=5000)
    assert plain.status.value == "VIOLATED"
    assert _summary(followed) == _summary(plain)
    assert followed.counterexample.sound_bound == plain.counterexample.sound_bound > 0


@pytest.mark.slow
def test_rate_proof_makes_every_tensor_on_its_problems_device() -> None:
    prob = _problem(1, 2, 8.0)
    plain = prove_rate(prob, max_boxes=1500)
    with default_device_meta():
        followed = prove_rate(prob, max_boxes=1500)
    assert plain.lower is not None
    assert (followed.lower, followed.stats.boxes_processed) == \
        (plain.lower, plain.stats.boxes_processed)


def test_a_gpu_problem_is_bounded_in_process_and_in_larger_rounds() -> None:
    """Dask workers would rebuild the problem on their CPUs: a problem on a GPU keeps its
    boxes in process (the check is on the device's type, so no GPU is needed here)."""

    class TwoWorkers:
        remote, workers = True, 2

    prob = _problem(1, 2, 8.0)
    assert _mpdi_remote(prob, prob.lam, Technique.TAYLOR, True, TwoWorkers()) is not None
    prob.device = "cuda:0"
    assert _mpdi_remote(prob, prob.lam, Technique.TAYLOR, True, TwoWorkers()) is None
    assert proof_batch(torch.device("cuda", 0)) == PROOF_BATCH["cuda"] > proof_batch(
        torch.device("cpu")) == PROOF_BATCH["cpu"]


@pytest.mark.parametrize("above", [False, True], ids=["proved", "violated"])
@pytest.mark.slow
def test_mpdi_check_grid_ascent_and_proof_follow_the_device(above: bool) -> None:
    """The whole check (grid sweep, ascent, sound re-check of candidates, proof) on a linear
    ground truth: PROVED just below lam_cert, VIOLATED just above, alike under `meta`."""
    from certify.checks.mpdi import check_mpdi
    from certify.model.problem import Problem
    from certify.settings import VerifySettings

    from ..planted import lam_cert_linear, linear_problem
    from .test_prover import P_METRIC, A, C, K

    truth = lam_cert_linear(A, C, K, P_METRIC)
    base = linear_problem(A, C, K, lam=0.1, P=P_METRIC)
    prob = Problem(base.system, base.network, truth + (1e-3 if above else -1e-3), base.P)
    settings = VerifySettings(grid_points=500, adversarial_starts=4, adversarial_steps=10,
                              max_boxes=20_000)
    plain = check_mpdi(prob, settings)
    with default_device_meta():
        followed = check_mpdi(prob, settings)
    assert plain.status.value == ("VIOLATED" if above else "PROVED")
    assert (followed.status, followed.upper, followed.lower) == \
        (plain.status, plain.upper, plain.lower)


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.slow
def test_side_proofs_make_every_tensor_on_their_problems_device(structure: str) -> None:
    """The residual and dk/dy bounds (`certify.prove.side`, on settings.device in `certify
    run`): the same bounds under `meta`, with seeds for the residual as the check gives."""
    from certify.model.problem import Problem
    from certify.prove.side import bound_dk_dy, bound_residual

    from ..conftest import random_network

    base = _problem(2, 2, 8.0)
    net = random_network(2, 1, structure=structure, seed=4, scale=0.5)
    prob = Problem(base.system, net, base.lam, base.P)
    plain = (bound_residual(prob, max_boxes=4000, seeds=[[0.1, -0.2]])[0],
             bound_dk_dy(prob, max_boxes=4000)[0])
    with default_device_meta():
        followed = (bound_residual(prob, max_boxes=4000, seeds=[[0.1, -0.2]])[0],
                    bound_dk_dy(prob, max_boxes=4000)[0])
    assert plain[1] is not None and (structure == "structural") == (plain[0] == 0.0)
    assert followed == plain


def test_a_gpu_gets_a_larger_box_budget_unless_one_is_named(tmp_path, monkeypatch) -> None:
    """With device cuda the default box budget scales with the GPU's rounds; a budget named
    in the options or in [tool.certify] is kept (settings only: no GPU needed)."""
    from certify.cli.config import load_settings
    from certify.settings import GPU_MAX_BOXES, VerifySettings

    monkeypatch.chdir(tmp_path)
    cpu, _ = load_settings({})
    gpu, _ = load_settings({"device": "cuda"})
    named, _ = load_settings({"device": "cuda:0", "max_boxes": 5000})
    assert cpu.max_boxes == VerifySettings().max_boxes < gpu.max_boxes == GPU_MAX_BOXES
    assert named.max_boxes == 5000
    (tmp_path / "pyproject.toml").write_text('[tool.certify]\ndevice = "cuda"\nmax_boxes = 7\n')
    from_file, _ = load_settings({})
    assert (from_file.device, from_file.max_boxes) == ("cuda", 7)
