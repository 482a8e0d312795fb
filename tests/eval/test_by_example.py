"""eval/by_example.py: Heitz and Neyret's by-example noise (numpy only, no VGG)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from eval.by_example import by_example_tile, degaussianise, gaussianise, triangle_grid, vertex_positions


@pytest.fixture(scope="module")
def photo() -> np.ndarray:
    """(128, 128, 3) float32: smooth noise with correlated channels, mean ~0.5, std ~0.1."""
    rng = np.random.default_rng(0)
    smooth = gaussian_filter(rng.standard_normal((128, 128, 3)), (3, 3, 0))
    mixing = np.array([[1.0, 0.5, 0.2], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]])  # correlated channels
    return np.clip(0.5 + 0.1 * (smooth / smooth.std()) @ mixing, 0.0, 1.0).astype(np.float32)


def test_tiles_keep_the_photo_mean_and_std(photo):
    """The variance-preserving blend keeps each channel's spread (a plain linear blend of
    three patches leaves ~0.65-0.7 of it here) and the histogram transform its mean."""
    tile = by_example_tile(photo, 512, 512, (1000, -300), seed=3, triangle_edge=16.0)
    assert tile.shape == (512, 512, 3) and tile.dtype == np.float32
    photo_mean, photo_std = photo.reshape(-1, 3).mean(0), photo.reshape(-1, 3).std(0)
    np.testing.assert_allclose(tile.reshape(-1, 3).mean(0), photo_mean, atol=0.25 * photo_std.min())
    np.testing.assert_allclose(tile.reshape(-1, 3).std(0) / photo_std, 1.0, atol=0.1)


def test_the_histogram_transform_goes_back_to_the_photo(photo):
    example = gaussianise(photo)
    gaussian = example.gaussian.reshape(-1, 3)
    np.testing.assert_allclose(gaussian.mean(0), 0.0, atol=1e-9)  # standard normal per channel, by rank
    np.testing.assert_allclose(gaussian.std(0), 1.0, atol=0.01)
    assert np.abs(np.corrcoef(((photo.reshape(-1, 3) - example.colour_mean) @ example.axes).T)
                  - np.eye(3)).max() < 1e-6  # the colour axes decorrelate
    assert np.abs(degaussianise(example, example.gaussian) - photo).mean() < 2e-3


def test_adjacent_tiles_are_parts_of_one_plane(photo):
    """Tiles at neighbouring origins are the pieces of one larger tile, bit for bit, at
    negative positions too: no seam at their edges."""
    whole = by_example_tile(photo, 96, 128, (-64, -40), seed=5, triangle_edge=24.0)
    left = by_example_tile(photo, 96, 64, (-64, -40), seed=5, triangle_edge=24.0)
    right = by_example_tile(photo, 96, 64, (0, -40), seed=5, triangle_edge=24.0)
    below = by_example_tile(photo, 48, 128, (-64, 8), seed=5, triangle_edge=24.0)
    np.testing.assert_array_equal(np.concatenate([left, right], axis=1), whole)
    np.testing.assert_array_equal(below, whole[48:])
    seam = np.abs(left[:, -1] - right[:, 0]).mean()
    assert seam < 2 * np.abs(np.diff(whole, axis=1)).mean()


def test_seeds_give_different_planes_and_a_seed_the_same_one(photo):
    a = by_example_tile(photo, 64, 64, (0, 0), seed=1)
    np.testing.assert_array_equal(a, by_example_tile(photo, 64, 64, (0, 0), seed=1))
    assert np.abs(a - by_example_tile(photo, 64, 64, (0, 0), seed=2)).mean() > 0.3 * photo.std()


def test_triangle_grid_weights_are_barycentric():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-200, 200, (2, 1000))
    weights, vertices = triangle_grid(x, y, 30.0)
    assert (weights >= -1e-12).all()
    np.testing.assert_allclose(weights.sum(-1), 1.0)
    # the weighted corners give back the point: they are its triangle's barycentric coordinates
    corners = vertex_positions(vertices, 30.0)  # (1000, 3, 2)
    np.testing.assert_allclose(np.einsum("nv,nvd->nd", weights, corners), np.stack([x, y], -1), atol=1e-9)
    # an equilateral grid: every triangle's edges are 30 px long
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1)
    np.testing.assert_allclose(edges, 30.0)
