"""model/lattice.py: a photo on its repeat lattice, measured on synthetic grids (no torch)."""
from __future__ import annotations

import numpy as np
import pytest

from model.lattice import _cell_residuals, cell_shade_covariance, lattice_contrast


def test_lattice_contrast_counts_what_differs_between_repeats_not_the_grid():
    rng = np.random.default_rng(0)
    grid = np.ones((128, 128, 3), np.float32)
    grid[::16] = grid[:, ::16] = 0.2  # grout every 16 px
    assert lattice_contrast(grid, (16.0, 0.0, 0.0, 16.0)) == 0.0
    assert lattice_contrast(grid, (15.6, 0.0, 0.3, 16.4)) == 0.0  # a vector a fraction of a pixel off
    marbled = grid + 0.1 * np.kron(rng.standard_normal((8, 8, 1)), np.ones((16, 16, 3))).astype(np.float32)
    # each tile its own shade: neighbours differ by 0.1^2 * 2 per channel, 3 channels
    assert lattice_contrast(marbled, (16.0, 0.0, 0.0, 16.0)) == pytest.approx(0.06, rel=0.35)


def _tiles_with_shades(shade: float, grain: float, seed: int = 0, cells: int = 16, side: int = 256) -> np.ndarray:
    """A 16-px tile grid with grout, each tile a luminance shade of std ``shade`` (0: none),
    over blotchy grain of std ``grain`` (noise blurred over a few pixels, so a tile's mean
    varies with it too)."""
    rng = np.random.default_rng(seed)
    image = np.full((side, side, 3), 0.6)
    image[::cells] = image[:, ::cells] = 0.3
    image += shade * np.kron(rng.standard_normal((side // cells, side // cells, 1)), np.ones((cells, cells, 3)))
    noise = rng.standard_normal((side // 4 + 1, side // 4 + 1, 1))
    blotches = np.kron(noise, np.ones((4, 4, 3)))[2:side + 2, 2:side + 2]  # 4-px blotches off the tile grid
    return image + grain * blotches / blotches.std()


def test_cell_shades_are_measured_apart_from_the_grain_within_the_cells():
    """Tiles of their own shades give those shades back (the shades' spread over the photo's);
    a grid whose tiles only carry grain mostly gives none, though its tiles' means vary more
    than faint shades make them; a lattice with too few cells to compare gives none."""
    lattice = (16.0, 0.0, 0.0, 16.0)
    shaded = _tiles_with_shades(shade=0.1, grain=0.05)
    covariance = cell_shade_covariance(shaded, lattice)
    expected = np.sqrt(3 * 0.1**2 / shaded.reshape(-1, 3).var(axis=0).mean())  # three channels, one shade
    assert np.sqrt(np.trace(covariance)) == pytest.approx(expected, rel=0.2)
    assert np.allclose(covariance, covariance[0, 0], rtol=0.05)  # one luminance shade: all channels together
    grain_only = _tiles_with_shades(shade=0.0, grain=0.05)
    naive = _cell_residuals(grain_only, lattice, 0.0)
    assert np.sqrt(np.trace(np.cov(naive.T)) / grain_only.reshape(-1, 3).var(axis=0).mean()) > 0.15
    # the shifted cells take the grain's part out, up to sampling error: most photos of grain alone
    # show no shades, every one with faint shades (a third of the grain's spread) does
    assert sum(cell_shade_covariance(_tiles_with_shades(0.0, 0.05, seed), lattice) is None for seed in range(20)) >= 14
    assert all(cell_shade_covariance(_tiles_with_shades(0.03, 0.05, seed), lattice) is not None for seed in range(20))
    assert cell_shade_covariance(shaded, (64.0, 0.0, 0.0, 64.0)) is None  # 4 x 4 cells: none with 4 whole neighbours
