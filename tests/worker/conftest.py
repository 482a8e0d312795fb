"""Worker fixtures: the real model export, a fixed texture code, meshes, a cheap sampler."""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
MESHES = REPO / "tests" / "data" / "meshes"
# The lead's export; TEXSPACE_TEST_MODEL_DIR points the tests at another export.
MODEL_DIR = Path(os.environ.get("TEXSPACE_TEST_MODEL_DIR", REPO / "model" / "weights"))


@pytest.fixture(scope="session")
def model_dir() -> Path:
    # The export may be being rewritten by a training run: wait briefly for all three files.
    for _ in range(30):
        if all((MODEL_DIR / f).is_file() for f in ("manifest.json", "encoder.onnx", "sampler.onnx")):
            return MODEL_DIR
        time.sleep(1)
    pytest.skip(f"no model export in {MODEL_DIR} (run python -m model.export)")


@pytest.fixture(scope="session")
def runtime(model_dir):
    from worker.runtime import ModelRuntime
    return ModelRuntime(model_dir)


@pytest.fixture(scope="session")
def brick() -> np.ndarray:
    """A real texture photo (scikit-image's bundled brick, CC0) as (H, W, 3) float32 sRGB."""
    from skimage import data
    gray = data.brick().astype(np.float32) / 255.0
    return np.repeat(gray[:, :, None], 3, axis=2)


@pytest.fixture(scope="session")
def code(runtime, brick) -> np.ndarray:
    from worker.encode import encode_image
    return encode_image(runtime, brick)


@pytest.fixture(scope="session")
def meshes() -> Path:
    return MESHES


class WavesSampler:
    """A real (non-neural) point function with the Sampler interface, implemented in numpy.

    For tests that need millions of points (memory bounds): the ONNX sampler takes about
    20 us per point on this shared machine. Deterministic in (points, code, seed).
    """

    pixels_per_unit = 64.0

    def __init__(self):
        self.calls: list[int] = []

    def sample(self, points, code, seed):
        points = np.asarray(points, dtype=np.float64)
        self.calls.append(len(points))
        k = np.array([[3.0, 5.0, 7.0], [11.0, 2.0, 13.0], [17.0, 19.0, 1.0]]) * (2 * np.pi / 64.0)
        out = np.empty((len(points), 3), dtype=np.float32)
        for a in range(0, len(points), 16384):   # chunked, like SamplerSession
            phase = np.mod(points[a:a + 16384], 64.0) @ k.T + float(seed)
            out[a:a + 16384] = 0.5 + 0.5 * np.sin(phase)
        return out


@pytest.fixture
def waves() -> WavesSampler:
    return WavesSampler()
