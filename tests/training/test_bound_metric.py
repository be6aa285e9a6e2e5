"""The bound preset's designs with a metric that follows the state (`training.bound_metric`):
settings refused with their name, and the gain schedule's distillation targets (values and
x-derivatives of K(x) - K_0) against the polynomial written out by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from training.bound_metric import MetricSettings, schedule_targets


@pytest.mark.parametrize("kw, word", [({"degrees": (5,)}, "degrees"), ({"degrees": ()}, "degrees"),
                                      ({"rounds": -1}, "rounds"), ({"points": 1.5}, "points"),
                                      ({"lr": 0.0}, "lr"), ({"tube_widen": float("nan")},
                                                           "tube_widen")])
def test_metric_settings_refuse_bad_values_by_name(kw, word):
    with pytest.raises(ValueError, match=word):
        MetricSettings(**kw)


def test_schedule_targets_are_the_schedule_without_its_constant_term():
    """K(x) = K0 + x1 K1 + x1 x2^2 K2 (n = 2, p = 1): the targets are x1 K1 + x1 x2^2 K2 and
    its gradient, at random states."""
    sched = np.array([[0, 0], [1, 0], [1, 2]])
    coeffs = np.array([[[5.0], [7.0]], [[1.0], [-2.0]], [[0.5], [3.0]]])  # [J, n, p]
    x = torch.as_tensor(np.random.default_rng(0).uniform(-2, 2, (50, 2)))
    val, der = schedule_targets(sched, coeffs, x)
    x1, x2 = x[:, 0].numpy(), x[:, 1].numpy()
    want = x1[:, None, None] * coeffs[1] + (x1 * x2 ** 2)[:, None, None] * coeffs[2]
    assert np.allclose(val.numpy(), want)
    d1 = coeffs[1] + (x2 ** 2)[:, None, None] * coeffs[2]  # d/dx1
    d2 = (2 * x1 * x2)[:, None, None] * coeffs[2]  # d/dx2
    assert np.allclose(der.numpy()[..., 0], d1) and np.allclose(der.numpy()[..., 1], d2)


def test_no_state_metric_applies_to_the_bound_preset_only(tmp_path, capsys):
    from ..cli_helpers import run_cli

    code, _, err = run_cli(capsys, "train", "vdp", "--preset", "tiny", "--no-state-metric",
                           "-o", str(tmp_path / "t.ckpt"))
    assert code == 2 and "--no-state-metric applies to preset bound only" in err
    assert not (tmp_path / "t.ckpt").exists()


def test_no_state_metric_reaches_the_design(monkeypatch, tmp_path):
    """`--no-state-metric` asks train_bound for no metric design (metric=False)."""
    import argparse

    from certify.spec.system import load_system
    from training import bound
    from training.presets import make_config

    seen = {}

    class Stop(Exception):
        pass

    def fake(*args, **kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(bound, "train_bound", fake)
    system = load_system("vdp")
    args = argparse.Namespace(output=str(tmp_path / "b.ckpt"), quiet=True, no_state_metric=True,
                              min_rate=None, lam=None, metric=None)
    with pytest.raises(Stop):
        bound.run_bound(args, system, make_config(system, "bound"))
    assert seen["metric"] is False
