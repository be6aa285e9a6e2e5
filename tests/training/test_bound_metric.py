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
