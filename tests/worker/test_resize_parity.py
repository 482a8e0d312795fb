"""The two ``resize_short_side``: model/data.py (training and fitting: uint8, Pillow Lanczos)
and worker/images.py (encoder crops at upload: float32, scikit-image bilinear,
antialiased when shrinking). They stay separate (worker/ never imports model/), but the
encoder must see exemplars at the scale and brightness it was trained on: same output
shape always, and values close. The filters differ, so single pixels at sharp edges
differ by up to ~0.1 on these textures (~0.25 on photos with hard edges: Lanczos
overshoot); the bounds below are on mean differences."""
import numpy as np
import pytest
import skimage.data
from PIL import Image

from model.data import DEFAULT_SHORT_SIDE
from model.data import resize_short_side as model_resize
from worker.images import resize_short_side as worker_resize

SHAPES = [(300, 500), (512, 512), (1000, 257)]  # (H, W): landscape, square, tall and odd
SHORT_SIDES = [DEFAULT_SHORT_SIDE, 128, 384]     # training default, encoder crop size, upscaling


def texture(name: str, shape: tuple[int, int]) -> np.ndarray:
    """A real texture photo bundled with scikit-image, (H, W, 3) uint8 at ``shape``."""
    grey = getattr(skimage.data, name)()
    rgb = np.stack([grey, (grey * 0.85).astype(np.uint8), (grey * 0.6).astype(np.uint8)], axis=-1)
    return np.asarray(Image.fromarray(rgb).resize(shape[::-1], Image.Resampling.BICUBIC))


@pytest.mark.parametrize("name", ["brick", "gravel"])
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("short_side", SHORT_SIDES)
def test_same_shape_and_close_values(name, shape, short_side):
    rgb8 = texture(name, shape)
    ours = model_resize(rgb8, short_side).astype(np.float32) / 255.0
    theirs = worker_resize(rgb8.astype(np.float32) / 255.0, short_side)
    assert ours.shape == theirs.shape
    assert min(ours.shape[:2]) == short_side
    diff = np.abs(ours - theirs)
    assert diff.mean() < 0.03, f"mean |diff| {diff.mean():.4f}"           # measured <= 0.017
    channel_means = np.abs(ours.mean(axis=(0, 1)) - theirs.mean(axis=(0, 1)))
    assert channel_means.max() < 2e-3, f"channel means differ by {channel_means}"  # measured <= 5e-4


def test_already_at_the_short_side_both_return_the_input():
    rgb8 = texture("brick", (256, 400))
    assert np.array_equal(model_resize(rgb8, 256), rgb8)
    rgb = rgb8.astype(np.float32) / 255.0
    assert np.array_equal(worker_resize(rgb, 256), rgb)
