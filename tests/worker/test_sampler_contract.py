"""The shipped samplers' published contract (model/weights/MODEL_CARD.md), straight in ONNX Runtime.

z is [1,8] or [P,8] and the colour table [1,K] or [P,K], in any pairing: each of the four
gives [P,3] and the pixels of the shared form. (A shared z with per-point tables once
gave P^2 rows, per-point z with a shared table a buffer-shape failure.)
"""
from __future__ import annotations

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

POINTS = 4096


@pytest.fixture(scope="module")
def texture(runtime, brick):
    """A real texture: an orange brick photo's code and colour table, as an upload gets them."""
    from worker.encode import encode_texture

    code, colour = encode_texture(runtime, brick * np.array([1.0, 0.6, 0.3], np.float32))
    if not len(colour):
        pytest.skip("this model export has no colour stage")
    return np.asarray(code, np.float32)[None], np.asarray(colour, np.float32)[None]


@pytest.mark.parametrize("name", ["sampler.onnx", "sampler_tileable.onnx"])
def test_every_documented_row_combination_gives_the_shared_forms_pixels(model_dir, texture, name):
    path = model_dir / name
    if not path.is_file():
        pytest.skip(f"{path} not exported")
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    z, colour = texture
    assert session.get_inputs()[3].shape[1] == colour.shape[1]
    points = np.random.default_rng(17).random((POINTS, 3)) * 3.0
    feed = {"points": points, "seed": np.asarray(5, np.int64)}
    if name == "sampler_tileable.onnx":
        feed["period"] = np.asarray(2.0)
    shared = session.run(None, feed | {"z": z, "colour": colour})[0]
    assert shared.shape == (POINTS, 3) and shared.dtype == np.float32
    assert shared.std() > 1e-3  # a texture, not a constant
    for z_rows in (1, POINTS):
        for colour_rows in (1, POINTS):
            rgb = session.run(None, feed | {"z": np.repeat(z, z_rows, axis=0),
                                            "colour": np.repeat(colour, colour_rows, axis=0)})[0]
            assert rgb.shape == (POINTS, 3), (z_rows, colour_rows)
            assert np.array_equal(rgb, shared), (z_rows, colour_rows)
