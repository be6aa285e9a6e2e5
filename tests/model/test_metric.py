"""PolyMetric: values and derivatives, plain-data round trips, malformed metrics refused with
one line, and checkpoints that carry one (or not)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.errors import CheckpointError
from certify.model import checkpoint
from certify.model.metric import MetricError, PolyMetric, all_monomials, even_monomials
from certify.model.network import GainNetwork
from certify.spec.system import load_system


def _random_metric(n: int, degree: int, seed: int) -> PolyMetric:
    rng = np.random.default_rng(seed)
    E = all_monomials(n, degree)
    C = rng.normal(size=(len(E), n, n))
    return PolyMetric(E, C + C.transpose(0, 2, 1))


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 3), degree=st.integers(0, 4), seed=st.integers(0, 1000))
def test_values_and_partials_match_autograd(n, degree, seed):
    M = _random_metric(n, degree, seed)
    x = torch.randn(7, n, dtype=torch.float64, generator=torch.Generator().manual_seed(seed),
                    requires_grad=True)
    V = M.value(x)
    manual = sum(torch.prod(x ** torch.as_tensor(e), 1)[:, None, None]
                 * torch.as_tensor(c) for e, c in zip(M.exponents, M.coefficients))
    assert torch.allclose(V, manual, rtol=1e-12, atol=1e-12)
    D = M.partials(x.detach())
    if M.is_constant:
        assert not bool(D.any())
        return
    for a in range(n):
        for b in range(n):
            (g,) = torch.autograd.grad(V[:, a, b].sum(), x, retain_graph=True)
            assert torch.allclose(D[:, :, a, b], g, rtol=1e-10, atol=1e-10)
    back = PolyMetric.from_dict(M.to_dict(), n)
    assert np.array_equal(back.exponents, M.exponents)
    assert np.array_equal(back.coefficients, M.coefficients)


def test_even_monomials_are_even():
    E = even_monomials(2, 4)
    assert all(sum(e) % 2 == 0 for e in E) and (0, 0) in {tuple(e) for e in E}
    assert len(E) == 1 + 3 + 5


@pytest.mark.parametrize("data,words", [
    ({"kind": "polynomial", "exponents": [[0, 0]], "coefficients": [[[1, 2], [0, 1]]]},
     "not symmetric"),
    ({"kind": "polynomial", "exponents": [[5, 0]], "coefficients": [[[1, 0], [0, 1]]]},
     "degree 5"),
    ({"kind": "polynomial", "exponents": [[-1, 0]], "coefficients": [[[1, 0], [0, 1]]]},
     ">= 0"),
    ({"kind": "polynomial", "exponents": [[0, 0]], "coefficients": [[[1, 0, 0]]]},
     "matrices"),
    ({"kind": "polynomial", "exponents": [[0, 0]], "coefficients": [[[float("nan"), 0],
                                                                      [0, 1]]]}, "finite"),
    ({"kind": "polynomial", "exponents": [[0, 0], [0, 0]],
      "coefficients": [[[1, 0], [0, 1]], [[1, 0], [0, 1]]]}, "twice"),
    ({"kind": "quadratic"}, "kind = 'polynomial'"),
    ({"kind": "polynomial", "exponents": [[0, 0, 0]], "coefficients": [[[1, 0, 0], [0, 1, 0],
                                                                        [0, 0, 1]]]}, "3 states"),
])
def test_malformed_metrics_are_refused_in_one_line(data, words):
    with pytest.raises(MetricError) as err:
        PolyMetric.from_dict(data, n=2)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_checkpoints_carry_the_metric_or_none(tmp_path):
    s = load_system("vdp")
    net = GainNetwork(2, 1, (4,), structure="structural").double()
    M = PolyMetric(even_monomials(2, 2), np.stack([np.eye(2) * 3] + [np.eye(2) * 0.1] * 3))
    path = tmp_path / "m.ckpt"
    checkpoint.save(path, system=s, network=net, lam=0.5, P=np.eye(2), metric=M)
    got = checkpoint.load(path).problem.metric
    assert got is not None and np.array_equal(got.coefficients, M.coefficients)
    plain = tmp_path / "p.ckpt"
    checkpoint.save(plain, system=s, network=net, lam=0.5, P=np.eye(2))
    assert checkpoint.load(plain).problem.metric is None


def test_a_checkpoint_with_a_malformed_metric_is_refused(tmp_path):
    s = load_system("vdp")
    net = GainNetwork(2, 1, (4,), structure="structural").double()
    path = tmp_path / "bad.ckpt"
    checkpoint.save(path, system=s, network=net, lam=0.5, P=np.eye(2))
    data = torch.load(path, weights_only=True)
    data["state_metric"] = {"kind": "polynomial", "exponents": [[0, 0]],
                            "coefficients": [[[1.0, 2.0], [0.0, 1.0]]]}
    torch.save(data, path)
    with pytest.raises(CheckpointError, match="state_metric: the metric is not symmetric"):
        checkpoint.load(path)
