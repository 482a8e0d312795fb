"""One working-resolution resize (``worker.photo.resize_short_side``) for training,
fitting, the upload's encoder crops and colour table, and evaluation.

It replaced two: training's 8-bit Pillow Lanczos and the upload's scikit-image bilinear
resize with a Gaussian pre-blur. Their pixels differed little on average, but the softer
one changed a photo's VGG Gram statistics by about a fit's whole error (validation gravel
1.55 against 1.9), so the encoder and the fits were judged against another photo than the
one they learnt from. These tests hold the one resize to what the space was trained
through, and training and upload to the same working image."""
import numpy as np
import pytest
import skimage.data
from PIL import Image

from model.data import DEFAULT_SHORT_SIDE, load_exemplar
from tests.helpers import pillow_lanczos
from worker.images import read_image
from worker.photo import resize_short_side

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
def test_the_working_resize_is_trainings_lanczos(name, shape, short_side):
    rgb8 = texture(name, shape)
    ours = resize_short_side(rgb8.astype(np.float32) / 255, short_side)
    trained = pillow_lanczos(rgb8, short_side)
    assert ours.shape == trained.shape and min(ours.shape[:2]) == short_side and ours.dtype == np.float32
    assert 0 <= ours.min() and ours.max() <= 1  # overshoot at hard edges is clipped, as 8 bits clip it
    difference = np.abs(ours - trained)
    # 8-bit rounding after the first pass is all that differs (measured: max 1.2/255)
    assert difference.max() < 2 / 255, f"max |diff| {difference.max() * 255:.2f}/255"
    assert difference.mean() < 0.5 / 255


def test_a_blurring_resize_would_be_caught():
    """The bound above separates filters: the former bilinear, Gaussian-pre-blurred resize
    is many levels away on a hard-edged photo."""
    from skimage.transform import resize

    rgb = texture("gravel", (512, 512)).astype(np.float32) / 255
    blurred = resize(rgb, (256, 256, 3), order=1, anti_aliasing=True, preserve_range=True)
    assert np.abs(blurred - resize_short_side(rgb, 256)).max() > 10 / 255


def test_training_and_upload_see_the_same_working_image(tmp_path):
    path = tmp_path / "gravel.png"
    Image.fromarray(texture("gravel", (300, 500))).save(path)
    upload = resize_short_side(read_image(path.read_bytes(), max_pixels=1 << 20), DEFAULT_SHORT_SIDE)
    exemplar = load_exemplar(path, DEFAULT_SHORT_SIDE)
    assert exemplar.shape == upload.shape
    assert np.abs(exemplar - upload).max() <= 0.5 / 255 + 1e-6  # training's 8-bit quantisation only


def test_already_at_the_short_side_returns_the_input():
    rgb = texture("brick", (256, 400)).astype(np.float32) / 255
    assert resize_short_side(rgb, 256) is rgb
