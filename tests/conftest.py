"""Shared fixtures: small systems and networks (float64)."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, settings

from certify.model.network import GainNetwork
from certify.spec.system import System

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))

# Property tests assert on values, never on time: no per-example deadline and no "too slow"
# health check (both read the wall clock, so a busy machine would turn them red), for every
# test whatever its own settings say about example counts.
settings.register_profile("certify", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("certify")

SPEC_3X2 = """
name = "three"
description = "3 states, 2 outputs, nonlinear, for generality tests"
states = ["a", "b", "c"]
outputs = ["ya", "yc"]
f = ["b - a**3", "-a - 0.5*b + sin(c)", "-2*c + a*b"]
h = ["a", "c + 0.1*a"]

[box]
X = [[-1, 1], [-1.5, 1.5], [-1, 1]]
Y = [[-1.2, 1.2], [-1.3, 1.3]]

[design]
lam = 0.5
P = [[2, 0.1, 0], [0.1, 1, 0], [0, 0, 1]]

[training.paper]
mu1 = 1.0
mu2 = 1.0
rho = [1.0, 1.0, 1.0]

[simulation]
x0 = [0.5, -0.5, 0.2]
xhat0 = [0.0, 0.0, 0.0]
t_final = 5.0
"""

LINEAR_SPEC = """
name = "linear"
states = ["x1", "x2"]
outputs = ["y"]
f = ["x2", "-2*x1 - 3*x2"]
h = ["x1"]
[box]
X = [[-1, 1], [-1, 1]]
Y = [[-1, 1]]
[design]
lam = 0.5
"""


@pytest.fixture
def system3() -> System:
    return System.from_text(SPEC_3X2, origin="test spec three")


@pytest.fixture
def linear_system() -> System:
    return System.from_text(LINEAR_SPEC, origin="test spec linear")


def random_network(n: int, p: int, hidden=(6, 5), structure="direct", seed: int = 0,
                   scale: float = 1.0) -> GainNetwork:
    torch.manual_seed(seed)
    net = GainNetwork(n, p, hidden, structure=structure).double()
    with torch.no_grad():
        for prm in net.parameters():
            prm.mul_(scale)
        net.K.copy_(torch.randn(n, p, dtype=torch.float64) * 0.3)
    return net.requires_grad_(False)
