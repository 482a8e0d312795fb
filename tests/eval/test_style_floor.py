"""eval/style_floor.py: a photo's floor and the ratio of a synthesis over it (runs VGG16)."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the style floor runs VGG16 (the train extra)")

from eval.style_floor import (corner_crops, crop_errors, off_grid_error, photo_floor, style_ratio,  # noqa: E402
                              tile_crops)


@pytest.fixture(scope="module", autouse=True)
def two_threads():
    torch.set_num_threads(2)


@pytest.fixture(scope="module")
def noise() -> np.ndarray:
    """(256, 256, 3) float32 uniform noise: every crop differs from the others."""
    return np.random.default_rng(0).random((256, 256, 3), dtype=np.float32)


@pytest.fixture(scope="module")
def noise_floor(noise):
    return photo_floor(noise)


def test_crops_are_the_corners_and_the_quadrants():
    image = np.arange(256 * 384 * 3, dtype=np.float32).reshape(256, 384, 3)
    corners = corner_crops(image)
    assert corners.shape == (4, 128, 128, 3)
    for crop, (y, x) in zip(corners, ((0, 0), (0, 256), (128, 0), (128, 256))):
        np.testing.assert_array_equal(crop, image[y:y + 128, x:x + 128])
    tiles = np.stack([image[:, :256], image[:, 128:]])
    quadrants = tile_crops(tiles)
    assert quadrants.shape == (8, 128, 128, 3)
    np.testing.assert_array_equal(quadrants[1], image[:128, 128:256])   # tile 0, top right
    np.testing.assert_array_equal(quadrants[6], image[128:, 128:256])   # tile 1, bottom left
    with pytest.raises(ValueError):
        corner_crops(image[:100])


def test_a_periodic_image_has_no_floor_and_noise_has_one(noise, noise_floor):
    """Four crops of a pattern whose period divides the crop size are one image: each
    matches the mean of the others exactly. Noise crops do not."""
    periodic = np.tile(noise[:16, :16], (16, 16, 1))
    flat = photo_floor(periodic)
    assert flat.corner_errors.shape == (4,) and flat.floor < 1e-9
    rough = noise_floor
    assert rough.floor > 1e-4 and rough.floor > 1e4 * max(flat.floor, 1e-12)
    assert math.isclose(rough.floor, float(rough.corner_errors.mean()))


def test_the_photo_scores_about_its_floor_and_a_flat_tile_far_above(noise, noise_floor):
    """The photo's own quadrants, against the mean of all four (themselves included), score
    under the leave-one-out floor; a flat grey tile with the photo's mean colour, far above."""
    floor = noise_floor
    own = crop_errors(noise[None], floor)
    assert own.shape == (4,)
    assert 0 < own.mean() < floor.floor
    grey = np.broadcast_to(noise.reshape(-1, 3).mean(0), (1, 256, 256, 3)).astype(np.float32)
    assert style_ratio(float(crop_errors(grey, floor).mean()), floor.floor) > 10


def test_off_the_corner_grid_a_periodic_photo_scores_far_above_its_floor(noise, noise_floor):
    """A pattern whose period divides the crop size has no floor at its corners, yet its own
    crops at other phases score as much as noise's crops do against each other: the floor
    there is a phase artefact. Noise's own crops elsewhere score about its floor (below it:
    they overlap the corners)."""
    periodic = np.tile(noise[:16, :16], (16, 16, 1))
    flat = photo_floor(periodic)
    assert off_grid_error(periodic, flat) > 0.5 * noise_floor.floor > 1e6 * max(flat.floor, 1e-12)
    assert 0.3 < off_grid_error(noise, noise_floor) / noise_floor.floor < 1.2
    assert off_grid_error(noise, noise_floor) == off_grid_error(noise, noise_floor, seed=0)  # fixed offsets


def test_style_ratio_divides_and_refuses_a_missing_floor():
    assert style_ratio(0.3, 0.1) == pytest.approx(3.0)
    assert style_ratio(0.05, 0.2) == pytest.approx(0.25)
    assert style_ratio(0.0, 0.2) == 0.0
    for floor in (0.0, -1e-3, float("nan"), float("inf")):
        assert style_ratio(0.3, floor) is None
    assert style_ratio(float("nan"), 0.1) is None
