"""The noise function: statistics, determinism, infinity (issue 2's checks)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model.noise import channel_values, corner_hashes, noise_features, octave_seeds  # noqa: E402


def cell_grid(n=256, z_values=(0, 1, -7)):
    g = torch.arange(-n // 2, n // 2, dtype=torch.int64)
    x, y, z = torch.meshgrid(g, g, torch.tensor(z_values), indexing="ij")
    return torch.stack([x, y, z], dim=-1)


def values_at(cells, seed=0):
    """Channel values of individual cells (the [0,0,0] corner of each)."""
    seeds = octave_seeds(torch.tensor(seed), 1)[0]
    return channel_values(corner_hashes(cells, seeds)[..., 0, 0, 0]).numpy()


def corr(a, b):
    return abs(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_cell_values_are_uniform_with_the_right_moments():
    v = values_at(cell_grid())
    assert abs(v.mean() - 0.5) < 0.01
    assert abs(v.var() - 1 / 12) < 0.005
    assert v.min() > 0 and v.max() < 1


def test_neighbour_cells_and_channels_are_uncorrelated():
    v = values_at(cell_grid())
    assert corr(v[1:], v[:-1]) < 0.02  # x neighbours
    assert corr(v[:, 1:], v[:, :-1]) < 0.02  # y neighbours
    assert corr(v[:, :, 0], v[:, :, 1]) < 0.02  # z neighbours
    assert corr(v[1:, 1:], v[:-1, :-1]) < 0.02  # diagonal
    assert corr(v[..., 0], v[..., 1]) < 0.02  # colour channels


def test_far_cells_have_the_same_statistics_and_no_period():
    near = values_at(cell_grid())
    for offset in (10**7, -(10**7) * 128, 2**32, 2**40):
        far = values_at(cell_grid() + offset)
        assert abs(far.mean() - 0.5) < 0.01 and abs(far.var() - 1 / 12) < 0.005
        assert corr(far, near) < 0.02  # not a copy of the origin: no 2**32 period
    shifted = values_at(cell_grid() + torch.tensor([2**32, 0, 0]))
    assert not np.allclose(shifted, near)


def test_seeds_give_different_noise():
    a, b = values_at(cell_grid(), seed=1), values_at(cell_grid(), seed=2)
    assert corr(a, b) < 0.02
    assert np.array_equal(a, values_at(cell_grid(), seed=1))


def test_interpolation_is_continuous_and_nearest_is_a_cell_value():
    x = torch.linspace(0.0, 4.0, 4001, dtype=torch.float64)
    pts = torch.stack([x, torch.full_like(x, 0.3), torch.full_like(x, 0.7)], -1)[:, None, :]  # [P,1,3]
    seeds = octave_seeds(torch.tensor(3), 1)
    nearest, interp = noise_features(pts, seeds)
    steps = interp[1:, 0] - interp[:-1, 0]
    assert steps.abs().max() < 0.01  # lattice step 1, sample step 0.001: no jumps
    # nearest is piecewise constant: it changes only at cell borders (integers)
    changes = (nearest[1:, 0] != nearest[:-1, 0]).any(-1).nonzero().flatten()
    borders = x[changes + 1]
    assert torch.allclose(borders, borders.round(), atol=1e-3)
    # at a cell centre the interpolated value equals the cell's own value
    centre = torch.tensor([[[2.5, 0.5, 0.5]]], dtype=torch.float64)
    n, i = noise_features(centre, seeds)
    assert torch.allclose(n, i, atol=1e-6)
