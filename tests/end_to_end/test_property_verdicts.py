"""Property test (issue 8): random small specs and networks through the real CLI; every
verdict agrees with an independent 40-digit evaluation (`tests/mp_reference.py`).

- no PROVED MPDI where a sampled point has reference lam_max(D) > the proved upper bound;
- every VIOLATED MPDI point has reference lam_max(D) > 0, at least its sound bound;
- a VIOLATED necessary condition has reference q > 0 at its witness;
- a spec undefined on its box is refused (exit 2); exit codes in {0, 1, 2, 3}; no traceback.
"""

from __future__ import annotations

import json

import mpmath
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from certify.cli.main import main
from certify.model import checkpoint
from certify.spec.system import System

from ..mp_reference import (
    dk_dy_norm,
    lam_max_D,
    manifold_q,
    network_layers,
    random_network,
    random_spec,
    residual_norm,
)
from ..soak import examples

POLICY = """
[tool.certify]
grid_points = 1500
adversarial_starts = 4
adversarial_steps = 15
max_boxes = 3000
rate_boxes = 3000
residual_boxes = 3000
lipschitz_boxes = 3000
top_counterexamples = 3
"""

CASES = st.fixed_dictionaries({
    "n": st.integers(2, 4), "p": st.integers(1, 2), "seed": st.integers(0, 2**31 - 1),
    "cond": st.floats(0.0, 6.0), "net": st.sampled_from(["small", "zero", "saturated",
                                                         "large"]),
    "hostile": st.booleans(),
})


@settings(max_examples=examples(10), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(case=CASES)
@example(case={"n": 2, "p": 1, "seed": 11, "cond": 6.0, "net": "zero", "hostile": True})
@example(case={"n": 3, "p": 2, "seed": 7, "cond": 6.0, "net": "saturated", "hostile": False})
@pytest.mark.slow
def test_verdicts_agree_with_a_40_digit_reference(case, tmp_path_factory, capsys):
    rng = np.random.default_rng(case["seed"])
    n, p = case["n"], min(case["p"], case["n"] - 1)
    spec = random_spec(rng, n, p, case["cond"], allow_undefined=case["hostile"])
    work = tmp_path_factory.mktemp("prop")
    (work / "pyproject.toml").write_text(POLICY)
    (work / "s.toml").write_text(spec.text)
    if not spec.defined:
        code = main(["check", str(work / "s.toml"), "--no-synthesis"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
        event("refused: undefined on the box")
        return
    system = System.from_text(spec.text)
    net = random_network(rng, n, p, case["net"])
    path = work / "c.ckpt"
    checkpoint.save(path, system=system, network=net, lam=spec.lam, P=system.P)
    code = main(["run", str(path), "--config", str(work / "pyproject.toml"), "--json",
                 str(work / "c.json"), "--skip", "simulation,bounds"])
    out = capsys.readouterr()
    assert code in (0, 1, 3), out.out + out.err
    assert "Traceback" not in out.err
    checks = json.loads((work / "c.json").read_text())["checks"]
    layers = network_layers(net)
    mpdi = checks["mpdi"]
    event(f"mpdi {mpdi['status']}, necessary {checks['necessary']['status']}, "
          f"rate {checks['rate']['status']}, residual {checks['residual']['status']}, "
          f"lipschitz {checks['lipschitz']['status']}")
    if mpdi["status"] == "VIOLATED":
        assert mpdi["counterexamples"]
        for cex in mpdi["counterexamples"]:
            ref = lam_max_D(spec, layers, cex["xhat"], cex["y"])
            assert ref > 0, (cex, ref)
            assert mpmath.mpf(cex["sound_bound"]) <= ref * (1 + mpmath.mpf(10) ** -30)
    if mpdi["status"] == "PROVED":
        box = np.vstack([spec.X, np.asarray(json.loads(json.dumps(system.Y.tolist())))])
        pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((25, n + p))
        pts = np.vstack([pts, box[:, 0], box[:, 1]])
        for z in pts:
            ref = lam_max_D(spec, layers, z[:n].tolist(), z[n:].tolist())
            assert ref <= mpmath.mpf(mpdi["upper"]), (z, ref, mpdi["upper"])
    nec = checks["necessary"]
    if nec["status"] == "VIOLATED":
        assert manifold_q(spec, nec["witness"]) > 0
    if nec["status"] == "PROVED" and nec["q_upper"] is not None:
        for x in spec.X[:, 0] + (spec.X[:, 1] - spec.X[:, 0]) * rng.random((10, n)):
            inside = all(system.Y[k, 0] <= x[k] <= system.Y[k, 1] for k in range(p))
            if inside:
                assert manifold_q(spec, x.tolist()) <= mpmath.mpf(nec["q_upper"])
    lip, res = checks["lipschitz"], checks["residual"]
    box = np.vstack([spec.X, system.Y])
    pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((6, n + p))
    if lip["status"] == "PROVED":
        assert lip["sampled"] <= lip["value"]
        for z in pts:
            assert dk_dy_norm(layers, z.tolist(), n) <= mpmath.mpf(lip["value"])
    if res["status"] == "PROVED":
        assert res["sampled"] <= res["upper"]
        for z in pts:
            assert residual_norm(layers, z[:n].tolist(), p) <= mpmath.mpf(res["upper"])
    rate = checks["rate"]
    if rate["status"] == "VIOLATED":
        w = rate["worst"]
        assert lam_max_D(spec, layers, w["xhat"], w["y"], lam=0.0) >= 0


def test_reference_agrees_with_the_kernels_on_a_plain_case():
    """The reference and certify's float64 kernel agree to rounding on an ordinary point."""
    from certify.model.kernels import mpdi_lam_max

    rng = np.random.default_rng(5)
    spec = random_spec(rng, 3, 1, 2.0)
    system = System.from_text(spec.text)
    net = random_network(rng, 3, 1, "large")
    z = torch.as_tensor(spec.X.mean(1).tolist() + [float(system.Y[0].mean())],
                        dtype=torch.float64)[None]
    with torch.no_grad():
        ours = float(mpdi_lam_max(system, net, torch.as_tensor(system.P), spec.lam,
                                  z[:, :3], z[:, 3:])[0])
    ref = float(lam_max_D(spec, network_layers(net), z[0, :3].tolist(), z[0, 3:].tolist()))
    assert ours == pytest.approx(ref, rel=1e-9, abs=1e-9 * (1 + abs(ref)))
