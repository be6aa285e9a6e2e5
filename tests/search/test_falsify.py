"""The falsifier: known maxima found, counts exact, the float32 screen changes no number."""

from __future__ import annotations

import numpy as np
import torch

from certify.search.falsify import grid_chunk, grid_shape, maximize_over_box
from certify.search.threads import torch_threads

LO, HI = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 1.0])
PEAK = torch.tensor([0.31, -1.17, 0.62], dtype=torch.float64)


def bump(z: torch.Tensor) -> torch.Tensor:
    """Max 0.5 at PEAK, positive only in a small ball around it."""
    return -1.0 + 1.5 * torch.exp(-((z - PEAK.to(z.dtype)) ** 2).sum(1) / 0.02)


def test_grid_covers_box_and_has_enough_points():
    shape = grid_shape(LO, HI, 10_000)
    assert np.prod(shape) >= 10_000
    pts = grid_chunk(torch.as_tensor(LO), torch.as_tensor(HI), shape, 0, int(np.prod(shape)))
    assert torch.allclose(pts.min(0).values, torch.as_tensor(LO))
    assert torch.allclose(pts.max(0).values, torch.as_tensor(HI))
    assert len(torch.unique(pts, dim=0)) == len(pts)


def test_ascent_finds_the_known_maximum_and_counts_are_exact():
    out = maximize_over_box(bump, LO, HI, grid_points=20_000, starts=8, steps=100)
    assert 0.5 - 1e-5 < out.best_value <= 0.5
    assert np.allclose(out.best_point, PEAK.numpy(), atol=1e-3)
    shape = grid_shape(LO, HI, 20_000)
    pts = grid_chunk(torch.as_tensor(LO), torch.as_tensor(HI), shape, 0, int(np.prod(shape)))
    assert out.above_threshold == int((bump(pts) > 0).sum()) > 0


def test_float32_screen_changes_no_number():
    def screen(z: torch.Tensor) -> torch.Tensor:
        return bump(z.to(torch.float32))

    plain = maximize_over_box(bump, LO, HI, grid_points=50_000, starts=4, steps=20)
    screened = maximize_over_box(bump, LO, HI, grid_points=50_000, starts=4, steps=20,
                                 screen=screen)
    assert screened.above_threshold == plain.above_threshold
    assert screened.grid_best_value == plain.grid_best_value
    assert screened.best_value == plain.best_value


def test_nan_points_are_counted_not_hidden():
    def holey(z: torch.Tensor) -> torch.Tensor:
        v = bump(z)
        return torch.where(z[:, 0] > 0.9, torch.full_like(v, float("nan")), v)

    out = maximize_over_box(holey, LO, HI, grid_points=5_000, starts=2, steps=5)
    assert out.nonfinite > 0


def test_torch_threads_restores_setting():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_float32_screen_keeps_the_float64_ranking_of_near_ties():
    """A plateau whose slope float32 cannot see: the screen ranks the points by chance, yet
    the candidates (and so the ascent's seeds and the answer) are float64's."""
    def plateau(z: torch.Tensor) -> torch.Tensor:
        return 1.0 - 1e-9 * ((z - PEAK.to(z.dtype)) ** 2).sum(1)

    def screen(z: torch.Tensor) -> torch.Tensor:
        return plateau(z.to(torch.float32))

    kw = dict(grid_points=20_000, starts=4, steps=0, top_k=5, threshold=2.0)
    plain = maximize_over_box(plateau, LO, HI, **kw)
    screened = maximize_over_box(plateau, LO, HI, screen=screen, **kw)
    assert np.array_equal(screened.top_points, plain.top_points)
    assert np.array_equal(screened.top_values, plain.top_values)
    assert screened.grid_best_value == plain.grid_best_value
