"""The batched integrator against a plain serial RK4, one run at a time.

The reference below is written out here on purpose: the textbook RK4 on the joint state
(x, xhat) of one run, with f and h from the spec's torch evaluator and k from the general
point evaluation (`certify.model.gain.gain_value`, the composition every check uses), the
noise held over each step. The batch (every run side by side, the 2 dt runs riding along,
noise chosen from the states) must give the same trajectories up to the libraries'
rounding.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from certify.model.gain import gain_value
from certify.simulate.integrate import bounded_noise, gaussian_noise, simulate_doubled
from certify.simulate.noise import SwitchingNoise
from certify.spec.system import load_system
from tests.conftest import random_network

SAME = dict(rtol=1e-11, atol=1e-12)


def reference_run(system, net, x0, xhat0, v, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Serial RK4 of one run: x0, xhat0 [n], noise v [steps, p] held per step ->
    x, xhat [steps + 1, n]."""
    spec = net.spec(torch.float64, detach=True)

    def rhs(s: torch.Tensor, vk: torch.Tensor) -> torch.Tensor:
        x, xh = s[None, 0], s[None, 1]
        y = system.h(x) + vk
        k = gain_value(spec, system, xh, y)
        return torch.cat([system.f(x), system.f(xh) + k])

    s = torch.stack([torch.as_tensor(x0), torch.as_tensor(xhat0)]).to(torch.float64)
    out = [s]
    for k in range(v.shape[0]):
        vk = torch.as_tensor(v[k])[None]
        k1 = rhs(s, vk)
        k2 = rhs(s + dt / 2 * k1, vk)
        k3 = rhs(s + dt / 2 * k2, vk)
        k4 = rhs(s + dt * k3, vk)
        s = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(s)
    traj = torch.stack(out).numpy()
    return traj[:, 0], traj[:, 1]


@pytest.mark.parametrize("which,structure", [("vdp", "structural"), ("vdp", "direct"),
                                             ("three", "direct"), ("three", "structural")])
def test_the_batch_equals_serial_runs(which, structure, system3):
    """Uniform, switching and Gaussian noise side by side, two runs again at 2 dt: every
    run equals its serial reference (the switching runs replay the signal the batch chose,
    which the trajectories return)."""
    system = load_system("vdp") if which == "vdp" else system3
    n, p = system.n, system.p
    net = random_network(n, p, structure=structure, seed=5)
    gen = torch.Generator().manual_seed(2)
    X = torch.as_tensor(system.X, dtype=torch.float64)
    x0 = X[:, 0] + (X[:, 1] - X[:, 0]) * (0.3 + 0.4 * torch.rand(5, n, generator=gen,
                                                                  dtype=torch.float64))
    xh0 = x0 + 0.05 * torch.randn(5, n, generator=gen, dtype=torch.float64)
    steps, dt, vbar = 60, 0.01, 0.1
    noise = torch.cat([bounded_noise(steps, 2, p, vbar, dt, seed=1),
                       torch.zeros(steps, 2, p, dtype=torch.float64),
                       gaussian_noise(steps, 1, p, 0.15, seed=2)], dim=1)
    fb = SwitchingNoise(system, net, np.eye(n), vbar, [2, 3], dt=dt, seed=4)
    fine, coarse = simulate_doubled(system, net, x0, xh0, dt=dt, steps=steps, noise=noise,
                                    doubled=[0, 3], doubled_steps=steps // 2, feedback=fb)
    v = fine.v.numpy()
    assert np.all(np.linalg.norm(v[:, :4], axis=-1) <= vbar)
    assert np.array_equal(v[:-1, [0, 1, 4]], noise.numpy()[:, [0, 1, 4]])
    for r in range(5):
        x, xh = reference_run(system, net, x0[r], xh0[r], v[:-1, r], dt)
        np.testing.assert_allclose(fine.x[:, r].numpy(), x, **SAME)
        np.testing.assert_allclose(fine.xhat[:, r].numpy(), xh, **SAME)
    assert coarse is not None
    for i, r in enumerate([0, 3]):
        x, xh = reference_run(system, net, x0[r], xh0[r], v[:-1:2, r], 2 * dt)
        np.testing.assert_allclose(coarse.x[:, i].numpy(), x, **SAME)
        np.testing.assert_allclose(coarse.xhat[:, i].numpy(), xh, **SAME)


@pytest.mark.parametrize("structure", ["direct", "structural"])
@pytest.mark.parametrize("with_K", [False, True])
def test_a_zero_last_layer_skips_the_network_with_the_same_values(structure, with_K,
                                                                   system3):
    """N = 0 (a zero gain, training's warm start): k = K (y - h(xhat)) or 0, equal to the
    general evaluation."""
    from certify.simulate.integrate import GainFunction

    net = random_network(3, 2, structure=structure, seed=6)
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        if not with_K:
            net.K.zero_()
    gain = GainFunction(system3, net)
    assert gain.silent
    gen = torch.Generator().manual_seed(3)
    xhat = torch.rand(9, 3, generator=gen, dtype=torch.float64) * 2 - 1
    y = torch.rand(9, 2, generator=gen, dtype=torch.float64) * 2 - 1
    want = gain_value(net.spec(torch.float64, detach=True), system3, xhat, y)
    got = gain(xhat.numpy(), y.numpy())
    assert got.shape == (9, 3) and bool(np.any(got)) == with_K
    np.testing.assert_allclose(got, want.numpy(), rtol=1e-14, atol=1e-15)
