"""An upload's code: chosen among the encoder's codes by the photo's style (worker/encode.py)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from worker.colour_match import calibrate_texture, texture_vector
from worker.encode import (CODE_CHOICE, MEAN_CHOICE, ORIENTATIONS, candidate_codes, choice_recipe, choice_tile,
                           code_colour, crop_codes, encode_image, encode_texture, photo_style)
from worker.errors import FeatureUnavailable
from worker.photo import working_photo
from worker.runtime import ModelRuntime


def test_candidates_are_the_mean_the_median_each_position_and_the_main_axis():
    rng = np.random.default_rng(0)
    codes = rng.normal(size=(ORIENTATIONS * 9, 8)) * np.array([3, 1, 1, 1, 1, 1, 1, 1])
    candidates = candidate_codes(codes)
    assert candidates.shape == (13, 8) and candidates.dtype == np.float32
    np.testing.assert_allclose(candidates[0], codes.mean(0), atol=1e-6)
    np.testing.assert_allclose(candidates[1], np.median(codes, 0), atol=1e-6)
    for position in range(9):  # each grid position over its eight orientations
        np.testing.assert_allclose(candidates[2 + position], codes[position::9].mean(0), atol=1e-6)
    step = candidates[11] - candidates[0]
    np.testing.assert_allclose(candidates[12] - candidates[0], -step, atol=1e-6)
    # along the codes' widest axis (the first, 3x the others here), 0.7 of their spread along it
    axis = step / np.linalg.norm(step)
    assert abs(axis[0]) > 0.95
    assert np.linalg.norm(step) == pytest.approx(0.7 * ((codes - codes.mean(0)) @ axis).std(), rel=1e-4)


@pytest.fixture(scope="module")
def photos() -> list[np.ndarray]:
    """scikit-image's gravel, grass and brick (grey, CC0) as (512, 512, 3) float32 sRGB."""
    from skimage import data
    return [np.repeat(getattr(data, name)()[:, :, None], 3, axis=2).astype(np.float32) / 255.0
            for name in ("gravel", "grass", "brick")]


def style_distance(runtime, working, target, code, curves="quantile") -> float:
    vector = texture_vector(code, calibrate_texture(runtime.sampler, code, working, curves=curves))
    return float(np.square(runtime.style(choice_tile(runtime, vector)[None]) - target).sum())


def test_the_upload_stores_the_code_whose_tile_is_nearest_the_photo(runtime, photos):
    """Of the candidates, the stored code's tile scores the lowest Gram loss against the photo;
    below the crops' mean code on these photos, and the same on every encode. Its table's
    curves are chosen the same way (gravel and grass: linear; brick: quantile)."""
    curves = []
    for photo in photos:
        code, colour = encode_texture(runtime, photo)
        working = working_photo(photo, runtime.short_side)
        candidates = candidate_codes(crop_codes(runtime, working))
        target = photo_style(runtime, working)
        distances = [style_distance(runtime, working, target, c) for c in candidates]
        chosen = int(np.argmin(distances))
        np.testing.assert_array_equal(code, candidates[chosen])
        assert distances[chosen] < distances[0]
        # its table: the photo's histograms, or the moment transfer where that tile lies nearer
        nearer = "linear" if style_distance(runtime, working, target, code, "linear") < distances[chosen] else "quantile"
        np.testing.assert_allclose(colour, calibrate_texture(runtime.sampler, code, working, curves=nearer), atol=1e-6)
        np.testing.assert_allclose(code_colour(runtime, working, code), colour, atol=1e-6)  # as recolour makes it
        again = encode_texture(runtime, photo)
        np.testing.assert_array_equal(again[0], code)
        np.testing.assert_array_equal(again[1], colour)
        curves.append(nearer)
    assert curves == ["linear", "linear", "quantile"]
    assert choice_recipe(runtime) == CODE_CHOICE


def test_an_export_without_style_statistics_keeps_the_mean_code(model_dir, tmp_path, brick):
    for name in ("manifest.json", "encoder.onnx", "sampler.onnx"):
        shutil.copy(model_dir / name, tmp_path / name)
    older = ModelRuntime(tmp_path)
    assert older.style_path is None
    assert choice_recipe(older) == MEAN_CHOICE  # what its uploads record
    with pytest.raises(FeatureUnavailable, match="style"):
        older.style(np.zeros((1, 128, 128, 3), np.float32))
    code, _ = encode_texture(older, brick)
    np.testing.assert_allclose(code, encode_image(older, working_photo(brick, older.short_side)), atol=1e-6)
