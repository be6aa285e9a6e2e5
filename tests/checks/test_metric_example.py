"""The shipped checkpoints with a metric that follows the state (examples/vdp_metric.ckpt,
made by `certify train vdp --preset bound`, and examples/vdp_metric_learned.ckpt, a learned
gain trained against its certificate by bench/vdp_metric_learned.py; docs/error-bounds.md
section 7): `certify.verify` proves the metric's stages, and the error bound they give is
below what any constant-metric certificate of a gain with an exact boundary condition can prove
on the Van der Pol box (docs/error-bounds.md, sections 5 and 7)."""

from __future__ import annotations

from pathlib import Path

import pytest

from certify.model import checkpoint
from certify.results import Status
from certify.settings import VerifySettings
from certify.verify import verify

EXAMPLES = Path(__file__).parents[2] / "examples"
NOISE = 0.15
# the constant-metric wall at noise 0.15: the optimum of the relaxation of section 5 (each
# vertex of Jf's hull its own gain), a lower bound on every constant-metric certificate's
# ultimate bound of a gain with an exact boundary condition on the Van der Pol box
WALL = 1.2523


@pytest.mark.slow
@pytest.mark.parametrize("name", ["vdp_metric.ckpt", "vdp_metric_learned.ckpt"])
def test_the_metric_example_certifies_below_the_constant_metric_wall(name):
    ck = checkpoint.load(EXAMPLES / name)
    assert ck.problem.metric is not None and ck.problem.metric.degree >= 2
    cert = verify(ck, VerifySettings(noise=NOISE, skip=("simulation",)), figures=False)
    assert cert.verdict == "CERTIFIED"
    mb = cert.checks["metric_bound"]
    assert mb.status == Status.PROVED and mb.ultimate is not None
    b = cert.checks["bounds"]
    assert b.best == "metric"
    assert b.ultimate == pytest.approx(mb.ultimate)
    # the headline (after its settling time) and the limit are both below the wall, and
    # below the constant-metric bound the same certificate proves (its first stage)
    assert b.headline is not None and b.headline < WALL
    assert mb.ultimate < WALL
    constant = [x for x in b.bounds() if x.name == "dissipation" and x.applicable]
    assert constant and constant[0].bias is not None and mb.ultimate < constant[0].bias


@pytest.mark.slow
def test_the_learned_metric_example_has_a_learned_gain():
    """The gain of vdp_metric_learned.ckpt is a network with a learned part: the structural
    k = (G(x, y) + K) (y - h(x)) with G's output layer nonzero and G far from 0 on X x Y
    (vdp_metric.ckpt's G is 0: its gain is linear)."""
    import torch

    from training.collocation import collocation_points

    net = checkpoint.load(EXAMPLES / "vdp_metric_learned.ckpt").problem.network
    assert net.architecture()["structure"] == "structural" and net.architecture()["hidden"]
    assert float(net.layers[-1].weight.abs().max()) > 0
    xhat, y = collocation_points(checkpoint.load(EXAMPLES / "vdp_metric.ckpt").problem.system,
                                 2000, 0)
    with torch.no_grad():
        G = net(torch.cat([xhat, y], 1))
    assert float(G.abs().max()) > 0.1
