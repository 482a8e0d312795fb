"""Colour tables (worker/colour_match.py): tiles get the photo's colours, by construction."""
from __future__ import annotations

import numpy as np
import pytest
from skimage.color import rgb2lab

from worker.colour import linear_to_srgb
from worker.colour_match import (
    calibrate_texture, colour_table, compressed_colour, identity_colour, knots_of, texture_vector,
)
from worker.encode import encode_texture
from worker.photo import resize_short_side
from worker.tiles import render_tile


def tinted(gray: np.ndarray, rgb: tuple[float, float, float]) -> np.ndarray:
    """A coloured photo from a grey one: sRGB (H, W, 3) times an sRGB tint."""
    return gray * np.asarray(rgb, np.float32)


def tile_lab(runtime, vector, seeds=(1, 2)) -> np.ndarray:
    """CIELAB pixels (N, 3) of native-zoom tiles (zoom 6) at two seeds, 2 x 2 tiles each."""
    tiles = [render_tile(runtime.sampler, vector, s, 6, x, y, 128, pixels_per_unit=runtime.pixels_per_unit)
             for s in seeds for x in (0, 1) for y in (0, 1)]
    return np.concatenate([rgb2lab(linear_to_srgb(t)).reshape(-1, 3) for t in tiles])


@pytest.fixture(scope="module")
def colour_sampler(runtime):
    if not runtime.sampler.colour_size:
        pytest.skip("this model export has no colour stage")
    return runtime.sampler


@pytest.mark.parametrize("tint", [(1.0, 0.55, 0.25), (0.35, 0.3, 0.25), (0.7, 0.9, 1.0)])
def test_tiles_have_the_photos_colour(runtime, colour_sampler, brick, tint):
    # Orange, dark brown and pale blue bricks: whatever the encoder's colours, the tiles'
    # mean CIELAB colour is the photo's (within dE 3) and so is the contrast per channel.
    photo = tinted(brick, tint)
    code, colour = encode_texture(runtime, photo)
    assert colour.shape == (colour_sampler.colour_size,)
    photo_lab = rgb2lab(resize_short_side(photo, runtime.short_side)).reshape(-1, 3)
    lab = tile_lab(runtime, texture_vector(code, colour))
    assert np.linalg.norm(lab.mean(0) - photo_lab.mean(0)) < 3.0
    ratio = lab.std(0) / np.maximum(photo_lab.std(0), 0.5)
    assert ratio[0] == pytest.approx(1.0, abs=0.25)  # lightness contrast
    assert (ratio[1:] < 1.5).all()  # no chroma noise added to a (nearly) single-hue photo


def test_identity_table_changes_nothing(runtime, colour_sampler, code):
    points = np.random.default_rng(0).random((3000, 3)) * 8
    plain = colour_sampler.sample(points, code, 3)
    same = colour_sampler.sample(points, texture_vector(code, identity_colour(colour_sampler.colour_size)), 3)
    assert np.abs(plain - same).max() < 1e-5


def test_table_is_deterministic_and_blends_stay_valid(runtime, colour_sampler, brick):
    a = calibrate_texture(colour_sampler, np.zeros(8, np.float32), tinted(brick, (1, 0.6, 0.3)))
    assert np.array_equal(a, calibrate_texture(colour_sampler, np.zeros(8, np.float32),
                                               tinted(brick, (1, 0.6, 0.3))))
    b = calibrate_texture(colour_sampler, np.zeros(8, np.float32), tinted(brick, (0.3, 0.5, 1)))
    knots = knots_of(len(a))
    for table in (a, b, 0.5 * (a + b)):
        values = table[15:15 + 3 * knots].reshape(3, knots)
        assert (np.diff(values, axis=1) >= 0).all()  # increasing curves: structure kept
        assert (table[12:15] > 0).all()  # grid steps
    points = np.random.default_rng(1).random((2000, 3)) * 4
    per_point = np.repeat(texture_vector(np.zeros(8), 0.5 * (a + b))[None], len(points), axis=0)
    blended = colour_sampler.sample(points, per_point, 0)
    shared = colour_sampler.sample(points, texture_vector(np.zeros(8), 0.5 * (a + b)), 0)
    assert np.abs(blended - shared).max() < 1e-6  # per-point tables = the same shared table


def apply_table(table: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """The sampler's colour stage in numpy (model/colour.py's layout): raw linear RGB (M, 3)
    -> linear RGB (M, 3) in [0, 1]."""
    knots = knots_of(len(table))
    a, start, step = table[:9].reshape(3, 3), table[9:12], table[12:15]
    values, back = table[15:15 + 3 * knots].reshape(3, knots), table[-9:].reshape(3, 3)
    u = compressed_colour(raw) @ a.T
    grid = np.arange(knots)
    d = np.stack([np.interp(u[:, c], start[c] + step[c] * grid, values[c]) for c in range(3)], axis=1)
    return np.clip(np.maximum(d @ back.T, 0) ** 4 - 1 / 256, 0, 1)


def structured_raw(seed: int = 4, n: int = 20000) -> np.ndarray:
    """Raw output that varies along one colour direction (a pink ramp of skewed values, far
    from the grey photo's hue) with near-silent noise (1e-3) across it, as a grill fit's did."""
    rng = np.random.default_rng(seed)
    level = rng.gamma(2.0, 0.1, (n, 1))
    return np.clip(0.3 + level * np.array([1.0, 0.2, 0.1]) + rng.normal(0, 1e-3, (n, 3)), 0, 1)


def grey_photo(seed: int = 5, n: int = 30000) -> np.ndarray:
    """A grey photo (linear RGB) with a little colour noise: its lightness axis dominates."""
    rng = np.random.default_rng(seed)
    grey = rng.beta(5.0, 2.0, (n, 1)) * 0.6
    return np.clip(grey + rng.normal(0, 0.01, (n, 3)), 0, 1)


def test_a_linear_table_is_trainings_moment_transfer():
    """A fit's table (curves="linear") gives its raw output exactly the colour transfer the
    fit was judged under in training (model.colour.transfer_colour_moments)."""
    torch = pytest.importorskip("torch", reason="training's transfer is in model/, the train extra")
    from model.colour import compressed_moments, transfer_colour_moments

    raw, photo = structured_raw(), grey_photo()
    ours = apply_table(colour_table(photo, raw, 64, curves="linear"), raw)
    as_image = lambda pixels: torch.from_numpy(pixels.T.copy())[None, :, :, None]  # noqa: E731 - [1,3,M,1]
    mean, covariance = compressed_moments(as_image(photo))
    theirs = transfer_colour_moments(as_image(raw), mean, covariance)[0, :, :, 0].numpy().T
    difference = np.abs(ours - theirs)
    assert difference.mean() < 2e-4 and difference.max() < 0.01  # (the largest where both clip at 1)


def test_a_linear_table_keeps_a_near_grey_photos_chroma_spread():
    """A fit of a near-grey photo has raw colour directions of ~1e-6 variance; a fixed ridge
    of that size in the whitening narrowed the tiles' CIELAB a/b spread to 0.56-0.69x the
    photo's (four of 40 validation photos). The table's output has the photo's spread."""
    rng = np.random.default_rng(6)  # grey raw output, colour noise of std ~6e-4 in compressed colour
    raw = np.clip(0.15 + rng.beta(5.0, 2.0, (20000, 1)) * 0.5 + rng.normal(0, 1.5e-3, (20000, 3)), 0, 1)
    photo = grey_photo()
    out = apply_table(colour_table(photo, raw, 64, curves="linear"), raw)
    as_lab = lambda linear: rgb2lab(linear_to_srgb(linear)[None])[0]  # noqa: E731
    ratio = as_lab(out).std(0) / as_lab(photo).std(0)
    assert ratio == pytest.approx([1.0, 1.0, 1.0], abs=0.03)  # (0.54 for a and b with the fixed ridge)


@pytest.mark.parametrize("curves", ["quantile", "linear"])
def test_the_raw_outputs_silent_colours_do_not_reach_the_lightness(curves):
    """The photo's lightness is drawn from the raw output's own variation, not from its
    near-silent noise blown up by the whitening: the symmetric whitening on the photo's axes
    used before gave a grill fit speckle, and here a lightness that follows the raw ramp with
    correlation 0.63 (0.89 when the raw ramp is grey too); now 0.88 (quantile), 0.999 (linear)."""
    raw, photo = structured_raw(), grey_photo()
    out = apply_table(colour_table(photo, raw, 64, curves=curves), raw)
    lightness = compressed_colour(out).sum(axis=1)
    ramp = compressed_colour(raw) @ np.array([1.0, 0.2, 0.1])
    assert np.corrcoef(lightness, ramp)[0, 1] > {"quantile": 0.85, "linear": 0.99}[curves]
    with pytest.raises(ValueError, match="curves"):
        colour_table(photo, raw, 64, curves="cubic")


def test_colour_table_matches_histograms_without_a_sampler():
    # The table alone, evaluated in numpy: a skewed raw distribution is mapped onto a
    # two-colour photo's distribution along its principal axis.
    rng = np.random.default_rng(4)
    raw = np.clip(rng.gamma(2.0, 0.1, (20000, 1)) * np.ones((1, 3)) + rng.normal(0, 0.01, (20000, 3)), 0, 1)
    photo = np.where(rng.random((30000, 1)) < 0.3, [0.8, 0.2, 0.1], [0.05, 0.05, 0.1])
    photo = np.clip(photo + rng.normal(0, 0.02, photo.shape), 0, 1)
    out = apply_table(colour_table(photo, raw, 64), raw)
    assert np.abs(out.mean(0) - photo.mean(0)).max() < 0.02
    assert np.abs(np.mean(out[:, 0] > 0.4) - 0.3) < 0.03  # the red share survives
