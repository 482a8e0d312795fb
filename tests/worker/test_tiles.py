"""Tile geometry (exact) and tile images (seams, quadtree, determinism) on the real model."""
import hashlib

import numpy as np
import pytest

from worker.errors import InvalidParameter
from worker.images import write_image
from worker.tiles import (NATIVE_ZOOM, SUPERSAMPLE_CAP, box_downsample, render_tile, render_window,
                          supersample_for, tile_points)

N = NATIVE_ZOOM
SIZE = 64


def mosaic(render, z, x, y, n=2):
    """n x n tiles starting at (x, y), stitched into one (n*SIZE, n*SIZE, 3) image."""
    return np.concatenate([np.concatenate([render(z, x + i, y + j) for i in range(n)], axis=1)
                           for j in range(n)], axis=0)


@pytest.fixture(scope="module")
def tile(runtime, code):
    return lambda z, x, y: render_tile(runtime, code, 3, z, x, y, SIZE)


def step_stats(img):
    """Mean |difference| between horizontally adjacent pixels, per column boundary."""
    return np.abs(np.diff(img, axis=1)).mean(axis=(0, 2))


# --- geometry: exact arithmetic -----------------------------------------------------------

def test_tile_points_exact_values():
    pts = tile_points(N, 0, 0, 64, pixels_per_unit=256.0)
    assert pts.shape == (64 * 64, 3)
    assert pts[0].tolist() == [0.5 / 256, 0.5 / 256, 0.0]
    assert pts[1].tolist() == [1.5 / 256, 0.5 / 256, 0.0]       # u grows along a row
    assert pts[64].tolist() == [0.5 / 256, 1.5 / 256, 0.0]      # v grows down the rows
    # one zoom out, 2x2 supersampled: quarter-pixel offsets of a 128 px/unit raster
    ss = tile_points(N - 1, 0, 0, 64, pixels_per_unit=256.0, supersample=2)
    assert ss.shape == (128 * 128, 3) and ss[0, 0] == 0.25 / 128 and ss[1, 0] == 0.75 / 128
    # planes put u, v and the offset on the documented axes
    assert tile_points(N, 0, 0, 64, pixels_per_unit=256.0, plane="xz", offset=2.5)[64].tolist() == \
        [0.5 / 256, 2.5, 1.5 / 256]
    assert tile_points(N, 0, 0, 64, pixels_per_unit=256.0, plane="yz", offset=-1.0)[1].tolist() == \
        [-1.0, 1.5 / 256, 0.5 / 256]


@pytest.mark.parametrize("x", [2 ** 31, -2 ** 31, 2 ** 31 - 1, -(2 ** 35)])
def test_huge_coordinates_are_exact(x):
    pts = tile_points(N, x, -x, 256, pixels_per_unit=256.0)
    # pixel centre (x*256 + i + 0.5) / 256 = x + (i + 0.5)/256: exactly representable
    assert pts[0, 0] == x + 0.5 / 256 and pts[255, 0] == x + 255.5 / 256
    assert pts[0, 1] == -x + 0.5 / 256
    assert len(np.unique(pts[:256, 0])) == 256                  # no two pixels collapse


def test_children_subsamples_are_the_parents_points():
    # The s = 2 sub-sample grid of a parent is exactly the pixel grid of its 4 children.
    parent = tile_points(N - 1, 3, -2, 64, pixels_per_unit=256.0, supersample=2).reshape(128, 128, 3)
    for i in (0, 1):
        for j in (0, 1):
            child = tile_points(N, 6 + i, -4 + j, 64, pixels_per_unit=256.0).reshape(64, 64, 3)
            assert np.array_equal(parent[64 * j:64 * (j + 1), 64 * i:64 * (i + 1)], child)


def test_supersample_factors():
    assert supersample_for(N) == 1 and supersample_for(N + 3) == 1
    assert supersample_for(N - 1) == 2 and supersample_for(N - 10) == SUPERSAMPLE_CAP


@pytest.mark.parametrize("args", [dict(z=99), dict(size=8), dict(x=2 ** 40), dict(plane="xw"),
                                  dict(supersample=3)])
def test_bad_tile_parameters(args):
    kw = dict(z=N, x=0, y=0, size=64, supersample=1, plane="xy") | args
    with pytest.raises(InvalidParameter):
        tile_points(kw.pop("z"), kw.pop("x"), kw.pop("y"), kw.pop("size"), pixels_per_unit=256.0, **kw)


# --- images on the real model -------------------------------------------------------------

def test_seams_are_invisible(runtime, code, tile):
    img = mosaic(tile, N, -1, 5)
    # Seamless by construction: the stitched tiles equal one window of the global raster...
    window = render_window(runtime, code, 3, N, -SIZE, 5 * SIZE, 2 * SIZE, 2 * SIZE,
                           pixels_per_unit=runtime.pixels_per_unit)
    assert np.array_equal(img, window)
    # ...so the pixel step across the tile border is like any step inside a tile.
    steps = step_stats(img)
    inner = np.delete(steps, SIZE - 1)
    assert steps[SIZE - 1] <= inner.mean() + 4 * inner.std() + 1e-7


def test_quadtree_exact_when_supersampled(tile):
    # Parent at N-1 uses 2x2 sub-samples = its children's pixel grid at N: equal to rounding.
    parent = tile(N - 1, 2, -3)
    children = box_downsample(mosaic(tile, N, 4, -6), 2)
    assert np.abs(children - parent).max() < 1e-6


def registration_errors(tile, z, x, y):
    """Mean |parent - 2x2 mean of its children|, for the children in place and shifted.

    Returns {(dy, dx): error} for shifts of -1, 0, +1 child pixels. A sample-point
    comparison cannot be exact (one point vs the mean of four), and how far apart they are
    depends on how rough the weights make the texture at that scale; what must hold for any
    weights is that the parent is explained best by its own children, not by the blocks one
    child pixel beside them.
    """
    parent = tile(z, x, y)
    fine = mosaic(tile, z + 1, 2 * x - 1, 2 * y - 1, n=4)  # children plus a one-tile margin
    errors = {}
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            block = fine[SIZE + dy:3 * SIZE + dy, SIZE + dx:3 * SIZE + dx]
            errors[(dy, dx)] = float(np.abs(box_downsample(block, 2) - parent).mean())
    return errors


def test_children_centres_average_to_the_parent_centre():
    # Above native zoom each parent pixel is one point; its 4 children's points surround it
    # symmetrically, so their mean is exactly the parent's point.
    parent = tile_points(N, 3, -2, 64, pixels_per_unit=256.0).reshape(64, 64, 3)
    children = np.concatenate([np.concatenate(
        [tile_points(N + 1, 6 + i, -4 + j, 64, pixels_per_unit=256.0).reshape(64, 64, 3) for i in (0, 1)],
        axis=1) for j in (0, 1)], axis=0)
    assert np.array_equal(box_downsample(children, 2), parent)


def test_quadtree_zoomed_in_registers_on_its_children(tile):
    errors = registration_errors(tile, N, 1, 1)
    aligned = errors.pop((0, 0))
    assert aligned < min(errors.values())


@pytest.mark.slow
def test_quadtree_beyond_supersample_cap_registers_on_its_children(tile):
    # At N-3 the ideal factor is 8, capped to 4: the parent averages 4x4 of the 8x8 points its
    # children (at 4x4 each) average together, so the match is approximate. Same criterion.
    z = N - 3
    assert supersample_for(z) == SUPERSAMPLE_CAP == 4
    errors = registration_errors(tile, z, 0, 0)
    aligned = errors.pop((0, 0))
    assert aligned < min(errors.values())


def test_same_tile_same_bytes(runtime, code, model_dir):
    from worker.runtime import ModelRuntime
    first = write_image(render_tile(runtime, code, 11, N, -3, 9, SIZE), "png")
    again = write_image(render_tile(runtime, code, 11, N, -3, 9, SIZE), "png")
    fresh = ModelRuntime(model_dir)                              # a new process-like session
    other = write_image(render_tile(fresh, code, 11, N, -3, 9, SIZE), "png")
    assert hashlib.sha256(first).digest() == hashlib.sha256(again).digest() == \
        hashlib.sha256(other).digest()


@pytest.mark.parametrize("x, y", [(2 ** 31 - 1, -2 ** 31), (-2 ** 31, 2 ** 31 - 1), (10 ** 9, 10 ** 9)])
def test_far_tiles_look_like_near_tiles(tile, x, y):
    near, far = tile(N, 0, 0), tile(N, x, y)
    assert np.isfinite(far).all() and far.min() >= 0 and far.max() <= 1
    # Stationary texture: same colour statistics far away (no precision blow-up, no banding).
    # A tile's mean colour wanders with the coarsest octave (256-px cells), so compare a
    # zoomed-out far tile (several coarse cells) against the spread of zoomed-out near ones.
    coarse = N - 3
    near_means = np.array([tile(coarse, i, j).mean(axis=(0, 1)) for i, j in
                           [(0, 0), (5, -7), (-9, 3), (12, 12), (-20, 4), (7, 30)]])
    far_mean = tile(coarse, x, y).mean(axis=(0, 1))
    assert (np.abs(far_mean - near_means.mean(0)) < 4 * near_means.std(0) + 0.01).all()
    ratio = (far.std(axis=(0, 1)) + 1e-4) / (near.std(axis=(0, 1)) + 1e-4)
    assert ((ratio > 1 / 3) & (ratio < 3)).all()
    # and not a constant or row-repeated image (lost precision collapses neighbours)
    assert len(np.unique(far.reshape(-1, 3), axis=0)) > far.shape[0] * far.shape[1] // 2


# --- parents from children, bounded zoom-out ------------------------------------------------

@pytest.mark.parametrize("levels", [1, 2])
def test_parent_from_children_is_bit_identical(runtime, code, tile, levels):
    from worker.tiles import exact_parent, parent_from_children

    z = N - levels
    assert exact_parent(z) and not exact_parent(N) and not exact_parent(N - 3)
    children = [[tile(z + 1, 2 * 3 + i, 2 * -2 + j) for i in (0, 1)] for j in (0, 1)]
    assert np.array_equal(parent_from_children(children), tile(z, 3, -2))


def test_box_downsample_is_the_mean(runtime):
    rgb = np.random.default_rng(0).random((32, 32, 3), dtype=np.float32)
    assert np.allclose(box_downsample(rgb, 4), rgb.reshape(8, 4, 8, 4, 3).mean(axis=(1, 3)), atol=1e-6)
    with pytest.raises(InvalidParameter):
        box_downsample(rgb, 3)


def test_bounded_zoom_out_is_one_subsample_per_pixel(runtime, code):
    z = N - 2
    bounded = render_tile(runtime, code, 3, z, 1, -1, SIZE, zoom_out="bounded")
    banded = render_tile(runtime, code, 3, z, 1, -1, SIZE, zoom_out="bounded", band_samples=7 * SIZE)
    assert np.array_equal(bounded, banded)                        # independent of bands
    # each pixel is one of the s x s sub-samples the supersampled pixel averages
    s = supersample_for(z)
    pts = tile_points(z, 1, -1, SIZE, pixels_per_unit=runtime.pixels_per_unit, supersample=s)
    raw = runtime.sample(pts, code, 3).reshape(SIZE, s, SIZE, s, 3).transpose(0, 2, 1, 3, 4).reshape(SIZE, SIZE, s * s, 3)
    assert (np.abs(raw - bounded[:, :, None, :]).max(axis=-1).min(axis=-1) == 0).all()
    # and it is an unbiased estimate of the supersampled tile: same mean colour, near it
    ref = render_tile(runtime, code, 3, z, 1, -1, SIZE)
    assert np.abs(bounded.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))).max() < 0.01
    with pytest.raises(InvalidParameter):
        render_tile(runtime, code, 3, z, 1, -1, SIZE, zoom_out="cheap")
