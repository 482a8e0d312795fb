"""model/lattice.py: a photo on its repeat lattice, measured on synthetic grids (no torch)."""
from __future__ import annotations

import numpy as np
import pytest

from model.lattice import lattice_contrast


def test_lattice_contrast_counts_what_differs_between_repeats_not_the_grid():
    rng = np.random.default_rng(0)
    grid = np.ones((128, 128, 3), np.float32)
    grid[::16] = grid[:, ::16] = 0.2  # grout every 16 px
    assert lattice_contrast(grid, (16.0, 0.0, 0.0, 16.0)) == 0.0
    assert lattice_contrast(grid, (15.6, 0.0, 0.3, 16.4)) == 0.0  # a vector a fraction of a pixel off
    marbled = grid + 0.1 * np.kron(rng.standard_normal((8, 8, 1)), np.ones((16, 16, 3))).astype(np.float32)
    # each tile its own shade: neighbours differ by 0.1^2 * 2 per channel, 3 channels
    assert lattice_contrast(marbled, (16.0, 0.0, 0.0, 16.0)) == pytest.approx(0.06, rel=0.35)
