"""One contract over every check: result type, JSON round trip, determinism, NaN => never PROVED.

Runs on the 3-state, 2-output spec of conftest, so every check is exercised beyond n=2, p=1.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from certify.certificate import Certificate
from certify.checks.bounds import check_bounds
from certify.checks.dissipation import check_dissipation
from certify.checks.invariance import check_invariance
from certify.checks.lipschitz import check_lipschitz
from certify.checks.metric_bound import check_metric_bound
from certify.checks.mpdi import check_mpdi
from certify.checks.necessary import check_necessary
from certify.checks.rate import check_rate
from certify.checks.registry import get_check, presentation, run_order
from certify.checks.residual import check_residual
from certify.checks.simulation import check_simulation
from certify.model import checkpoint
from certify.model.problem import Problem
from certify.presentation import Presentation, Quantity
from certify.results import (
    RESULT_TYPES,
    CheckFailure,
    Status,
    from_jsonable,
    result_from_jsonable,
    to_jsonable,
)
from certify.settings import CHECK_NAMES, VerifySettings
from certify.verify import verify

from ..conftest import random_network

SETTINGS = VerifySettings(grid_points=4000, adversarial_starts=6, adversarial_steps=20,
                          max_boxes=40_000, rate_boxes=20_000, residual_boxes=20_000,
                          lipschitz_boxes=20_000, dissipation_boxes=40_000, sim_time=0.5,
                          sim_dt=0.01,
                          sim_initial_conditions=2)


def _problem(system, structure="direct", nan=False):
    net = random_network(3, 2, hidden=(5,), structure=structure, seed=11, scale=0.3)
    with torch.no_grad():
        net.K.copy_(torch.tensor([[2.0, 0.0], [0.5, 0.0], [0.0, 1.5]], dtype=torch.float64))
        if nan:
            net.layers[0].weight[0, 0] = float("nan")
    return Problem(system, net, 0.1, system.P)


def _run_all(problem):
    s = SETTINGS
    out = {
        "necessary": check_necessary(problem.system, problem.P, problem.lam, s),
        "mpdi": check_mpdi(problem, s),
        "residual": check_residual(problem, s),
        "lipschitz": check_lipschitz(problem, s),
    }
    out["rate"] = check_rate(problem, s, mpdi=out["mpdi"])
    lam_cert = out["rate"].proved_lower
    out["dissipation"] = check_dissipation(problem, s, residual=out["residual"])
    out["invariance"] = check_invariance(problem.system, budget=20_000, seed=s.seed)
    out["metric_bound"] = check_metric_bound(problem, s, dissipation=out["dissipation"],
                                             residual=out["residual"])
    out["bounds"] = check_bounds(problem, lam_cert=lam_cert, eps_bar=out["residual"].upper,
                                 L=out["lipschitz"].value, vbar=s.noise,
                                 dissipation=out["dissipation"], metric=out["metric_bound"],
                                 invariance=out["invariance"])
    out["simulation"] = check_simulation(problem, out["bounds"], s, certified=False)
    return out


@pytest.fixture(scope="module")
def results(request):
    from certify.spec.system import System

    from ..conftest import SPEC_3X2

    system = System.from_text(SPEC_3X2, origin="contract spec")
    return {s: _run_all(_problem(system, s)) for s in ("direct", "structural")}


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.parametrize("name", sorted(RESULT_TYPES.keys() - {"metric"}))
@pytest.mark.slow
def test_result_type_and_json_round_trip(results, structure, name):
    result = results[structure][name]
    assert isinstance(result, RESULT_TYPES[name])
    assert isinstance(result.status, Status) and result.message
    data = json.loads(json.dumps(to_jsonable(result), allow_nan=False))
    back = from_jsonable(RESULT_TYPES[name], data)
    assert to_jsonable(back) == to_jsonable(result)


@pytest.mark.slow
def test_structural_residual_is_exactly_zero(results):
    res = results["structural"]["residual"]
    assert res.structural and res.upper == 0.0 and res.status == Status.PROVED


@pytest.mark.slow
def test_sampled_side_never_exceeds_proved_side(results):
    for per in results.values():
        m = per["mpdi"]
        if m.upper is not None:
            assert m.lower <= m.upper + 1e-9
        r = per["rate"]
        if r.proved_lower is not None:
            assert r.proved_lower <= r.sampled_upper + 1e-9
        lip = per["lipschitz"]
        if lip.value is not None:
            assert lip.sampled <= lip.value + 1e-9
        res = per["residual"]
        if res.upper is not None:
            assert res.sampled <= res.upper + 1e-12


@pytest.mark.slow
def test_nan_weights_are_never_proved(system3):
    problem = _problem(system3, nan=True)
    for name, result in _run_all(problem).items():
        if name in ("necessary", "invariance"):  # independent of the network
            continue
        assert result.status != Status.PROVED, (name, result.message)


@pytest.mark.slow
def test_same_seed_same_certificate(tmp_path, system3):
    path = tmp_path / "c.ckpt"
    problem = _problem(system3)
    checkpoint.save(path, system=system3, network=problem.network, lam=problem.lam)
    ck = checkpoint.load(path)
    a, b = verify(ck, SETTINGS), verify(ck, SETTINGS)

    def numbers(cert: Certificate) -> dict:
        d = cert.to_dict()
        for key in ("timings", "created"):
            d.pop(key)
        for check in d["checks"].values():
            check.pop("seconds", None)
            if isinstance(check.get("proof"), dict):
                for k in ("seconds", "boxes_per_second", "volume_history", "boxes_processed",
                          "proved_volume_fraction", "max_depth", "budget_exhausted"):
                    check["proof"].pop(k, None)
            if isinstance(check.get("solver"), dict):
                check.pop("solver")
        d["figures"].pop("proof_history", None)
        d["figures"].pop("proof_boxes", None)  # the prover's leaves depend on its timing
        return d

    assert a.verdict == b.verdict
    assert numbers(a)["checks"]["mpdi"]["lower"] == numbers(b)["checks"]["mpdi"]["lower"]
    assert numbers(a)["checks"]["necessary"] == numbers(b)["checks"]["necessary"]
    res_a, res_b = numbers(a)["checks"]["residual"], numbers(b)["checks"]["residual"]
    assert res_a["sampled"] == res_b["sampled"]
    again = Certificate.from_dict(json.loads(a.to_json()))
    assert again.to_dict() == a.to_dict()


def test_settings_are_frozen_and_echoed():
    with pytest.raises(dataclasses.FrozenInstanceError):
        SETTINGS.grid_points = 3  # type: ignore[misc]
    assert np.isclose(dataclasses.asdict(SETTINGS)["noise"], 0.15)


def test_sim_time_is_automatic_unless_set():
    """sim_time None (the default) is the automatic horizon; any number, the default's own
    value included, is kept as set; a non-positive one is refused naming the field."""
    from certify.errors import SettingsError
    from certify.settings import DEFAULT_SIM_TIME, VerifySettings, make_settings

    assert VerifySettings().sim_time is None and DEFAULT_SIM_TIME > 0
    assert make_settings({"sim_time": 10}).sim_time == 10.0
    for bad in (0, -1.0, float("nan"), True):
        with pytest.raises(SettingsError, match="sim_time"):
            make_settings({"sim_time": bad})


# ----------------------------------------------------------------------------- check protocol

_PLAIN = (type(None), bool, int, float, str)


def _plain(value) -> bool:
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    return isinstance(value, _PLAIN)


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.parametrize("name", CHECK_NAMES)
@pytest.mark.slow
def test_every_registered_check_presents_its_result_as_plain_data(results, structure, name):
    """Each check object declares its result type and settings, and its presenter returns
    pure data (labels, numbers, reasons): the reports format it, nothing here imports them."""
    check = get_check(name)
    result = results[structure][name]
    assert check.name == name and check.title
    assert isinstance(result, check.result_type) and RESULT_TYPES[name] is check.result_type
    assert set(check.reads) <= set(dataclasses.asdict(SETTINGS)), check.reads
    assert set(check.needs) | set(check.uses) <= set(CHECK_NAMES)
    cert = Certificate(verdict="INCONCLUSIVE", summary="", checks={name: result},
                       required=[], settings=dataclasses.asdict(SETTINGS), system={},
                       lam=0.1, P=np.eye(3).tolist(), network={}, checkpoint={},
                       versions={}, timings={})
    pres = presentation(name, result, cert)
    assert isinstance(pres, Presentation)
    quantities = [pres.sampled, pres.proved, *pres.setting, *pres.numbers, *pres.facts]
    assert all(isinstance(q, Quantity) for q in quantities)
    for q in quantities:
        assert _plain(q.value), (name, q)
    for q in (pres.sampled, pres.proved):  # a missing number in the table says why
        assert q.value is not None or q.missing, (name, q)


def test_run_order_puts_what_a_check_uses_first():
    order = [c.name for c in run_order()]
    assert sorted(order) == sorted(CHECK_NAMES)
    for check in run_order():
        for dep in (*check.needs, *check.uses):
            assert order.index(dep) < order.index(check.name), (dep, check.name)


def test_failure_record_presents_and_round_trips():
    failure = CheckFailure(Status.ERROR, "internal error: ValueError: x", "ValueError", 0.5)
    data = json.loads(json.dumps(to_jsonable(failure)))
    back = result_from_jsonable("mpdi", data)
    assert back == failure
    pres = presentation("mpdi", back, None)
    assert pres.proved.value is None and pres.proved.missing == "internal error"
    assert ("Exception", "ValueError") in [(q.label, q.value) for q in pres.facts]


@pytest.mark.slow
def test_maps_are_computed_only_when_asked(tmp_path, system3):
    path = tmp_path / "c.ckpt"
    problem = _problem(system3)
    checkpoint.save(path, system=system3, network=problem.network, lam=problem.lam)
    ck = checkpoint.load(path)
    quick = dataclasses.replace(SETTINGS, skip=("lipschitz", "simulation", "rate"))
    bare = verify(ck, quick, figures=False)
    assert bare.figures.mpdi_map is None and bare.figures.necessary_map is None
    assert "figures" not in bare.timings
    full = verify(ck, quick)
    assert full.figures.mpdi_map is not None and full.figures.residual_map is not None
    assert len(full.figures.mpdi_map.values) == len(full.figures.mpdi_map.y)
    assert bare.checks["mpdi"].lower == full.checks["mpdi"].lower  # same numbers either way
