"""The shipped learned observers above three states (examples/vdp2_learned.ckpt, n = 4, and
examples/vdp3_learned.ckpt, n = 6; made by `certify train vdp2|vdp3 --preset certified`,
README): a linear injection K plus a trained tanh network N(xhat, y) (not the LMI fallback, whose N
is zero; N is small beside K and nearly affine on the box: a learned correction of the LMI
warm start), whose MPDI the prover proves over the whole box: CERTIFIED."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from certify.model import checkpoint
from certify.results import Status
from certify.settings import CHECK_NAMES, VerifySettings
from certify.verify import verify

EXAMPLES = Path(__file__).parents[2] / "examples"


@pytest.mark.slow
@pytest.mark.parametrize("name, n", [("vdp2_learned.ckpt", 4), ("vdp3_learned.ckpt", 6)])
def test_a_learned_observer_above_three_states_is_certified(name, n):
    ck = checkpoint.load(EXAMPLES / name)
    net = ck.problem.network
    assert ck.problem.system.n == n and net.layers, "a network with hidden layers"
    # the learned part is there: the network N(xhat, y) is not affine on the box
    g = torch.Generator().manual_seed(0)
    box = torch.as_tensor(ck.problem.system.X, dtype=torch.float64)
    ybox = torch.as_tensor(ck.problem.system.Y, dtype=torch.float64)
    x = box[:, 0] + (box[:, 1] - box[:, 0]) * torch.rand(64, n, generator=g, dtype=torch.float64)
    y = ybox[:, 0] + (ybox[:, 1] - ybox[:, 0]) * torch.rand(64, len(ybox), generator=g,
                                                             dtype=torch.float64)
    with torch.no_grad():
        z = torch.cat([x, y], 1)
        k = net(z)
        mid = net(0.5 * (z + z.flip(0)))
        linear_mid = 0.5 * (k + k.flip(0))  # what an affine N would give
    assert k.abs().max() > 1.0 and (mid - linear_mid).abs().max() > 1e-4 * k.abs().max()
    skip = tuple(c for c in CHECK_NAMES if c != "mpdi")
    cert = verify(ck, VerifySettings(grid_points=20_000, adversarial_starts=8,
                                     adversarial_steps=30, skip=skip), figures=False)
    assert cert.checks["mpdi"].status == Status.PROVED
    assert cert.checks["mpdi"].upper < 0
    assert cert.verdict == "CERTIFIED"
