"""eval/structure.py: its degraded copies and how a run is summarised (no packaged
photos needed: a synthetic tile grid stands in)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch", reason="eval/structure.py imports model/ (the train extra)")


@pytest.fixture(scope="module")
def structure():
    import eval.structure

    return eval.structure


def test_shading_darkens_the_corners_and_ramps_across(structure):
    flat = np.full((64, 80, 3), 0.5, np.float32)
    vignette = structure.shaded(flat, vignette=0.3)
    assert vignette[0, 0, 0] == pytest.approx(0.35) and vignette[32, 40, 0] == pytest.approx(0.5)
    ramp = structure.shaded(flat, falloff=0.2)
    assert ramp[10, 0, 0] == pytest.approx(0.4) and ramp[10, -1, 0] == pytest.approx(0.6)


def test_every_degraded_copy_is_a_photo_at_the_working_size(structure):
    from scipy import ndimage
    detail = ndimage.gaussian_filter(np.random.default_rng(0).standard_normal((256, 256, 3)), (3, 3, 0))
    photo = (0.5 + 0.3 * detail / np.abs(detail).max()).astype(np.float32)
    for how, degrade in structure.DEGRADED.items():
        copy = degrade(photo)
        assert copy.shape == photo.shape and 0 <= copy.min() and copy.max() <= 1, how
        assert 0 < np.abs(copy - photo).mean() < 0.1, how  # changed, and still the photo


def test_rows_mark_a_found_grid_right_and_the_summary_counts_them(structure):
    size, tile = 256, 64
    y, x = np.mgrid[0:size, 0:size]
    grid = np.where((y % tile == 0) | (x % tile == 0), 0.55, 0.85)
    grid = np.repeat((grid + 0.02 * np.random.default_rng(1).standard_normal(grid.shape))[..., None], 3, axis=2)
    right = structure.structure_row("grid", grid.astype(np.float32), (tile, 0.0, 0.0, tile))
    wrong = structure.structure_row("grid", grid.astype(np.float32), (tile * 1.5, 0.0, 0.0, tile))
    assert right["right"] and not wrong["right"]
    flat = dict(structure.structure_row("flat", np.full((64, 64, 3), 0.5, np.float32)), right=False)
    text = structure.to_markdown({"packaged": [], "crops": [], "turns": [right], "degraded": [flat, {**flat, "right": True}],
                                  "close-ups": [right, wrong], "hexagonal tiles": [wrong]})
    assert ("Close-ups right: 1 of 2. Degraded copies that find what the clean photo does: 1 of 2. Turns right: "
            "1 of 1. Hexagonal tiles right: 0 of 1.") in text
    assert text.count("| flat |") == 1  # only the degraded copy that differs is listed


def test_a_turned_photo_is_judged_against_the_upright_lattice_turned_the_same_way(structure):
    """straighten's sense of turning and turned_lattice's agree: a grid of 48-px tiles with
    4-px grout, turned 10 degrees either way, is found on the turned lattice, not the other."""
    from model.structure import photo_structure, same_lattice, straighten

    size, tile = 400, 48
    y, x = np.mgrid[0:size, 0:size]
    grid = np.where((y % tile < 4) | (x % tile < 4), 0.45, 0.85)
    grid = np.repeat((grid + 0.02 * np.random.default_rng(2).standard_normal(grid.shape))[..., None], 3, axis=2)
    upright = photo_structure(grid.astype(np.float32))[1]
    assert upright is not None
    for degrees in (10.0, -10.0):
        found = photo_structure(straighten(grid.astype(np.float32), degrees))[1]
        assert found is not None and same_lattice(found, structure.turned_lattice(upright, degrees), 0.05), found
        assert not same_lattice(found, structure.turned_lattice(upright, -degrees), 0.05)
