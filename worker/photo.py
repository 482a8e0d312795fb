"""The photo as the model sees it: at its working resolution (``resize_short_side``), its
lighting evened where asked (``working_photo``), cut into the encoder's crops
(``encoder_crops``). An upload's code, a fit's photo and first code, training and
evaluation all take these steps on what ``worker.decode.read_image`` returns: float32
(H, W, 3) sRGB-encoded 0..1.

A leaf module like ``worker.decode``: numpy, Pillow and the standard library, plus the
leaves ``worker.colour``, ``worker.decode`` and ``worker.errors``, so ``model/`` may import
it (tests/test_imports.py holds the rule).
"""
from __future__ import annotations

import numpy as np
from PIL import Image

from worker.colour import even_lighting
from worker.decode import DECODE_BAND_PIXELS
from worker.errors import InvalidParameter, LimitExceeded

RESIZE_DIRECT_PIXELS = 1 << 22  # larger images are box-reduced in bands before resizing
MAX_WORK_PIXELS = 1 << 24       # resize_short_side refuses to produce more pixels than this
# How an upload's photo is lit: "as-is" (taken as it is) or "even" (its smooth shading divided
# out first: ``even_lighting``). Photo-sourced textures often carry a light falloff; without
# evening, a shaded photo's tiles show its light and dark sides as blotches (a grass photo's
# style error 0.014 -> 0.053; evened 0.030). Off by default: evening flattens a material's own tone.
LIGHTING = ("as-is", "even")


def working_photo(image: np.ndarray, short_side: int, lighting: str = "as-is") -> np.ndarray:
    """The photo as a texture is encoded and fitted from: at the model's working resolution
    (``resize_short_side``), its shading evened out where ``lighting`` is "even" (evening
    after the resize is the same, shading being smooth, and far cheaper)."""
    if lighting not in LIGHTING:
        raise InvalidParameter(f"lighting must be one of {', '.join(LIGHTING)}, got {lighting!r}")
    working = resize_short_side(image, short_side)
    return even_lighting(working) if lighting == "even" else working


def working_shape(height: int, width: int, short_side: int) -> tuple[int, int]:
    """(rows, cols) of an image of that size resized so its shorter side is ``short_side``
    (the longer side rounded, never below the shorter)."""
    scale = short_side / min(height, width)
    return max(short_side, round(height * scale)), max(short_side, round(width * scale))


def resize_short_side(image: np.ndarray, short_side: int) -> np.ndarray:
    """Resize (H, W, 3) float32 sRGB 0..1 so min(H, W) == short_side: the model's working
    resolution, for training, fitting, the upload's encoder crops and colour table, and
    evaluation alike.

    Lanczos-3 (Pillow's filter, support widened by the shrink factor): a pass along x, then
    one along y, each clipped to 0..1, as the 8-bit Pillow resize the space was trained
    through does. Another filter is not a detail: the upload path once used scikit-image's
    bilinear resize with a Gaussian pre-blur, and on the validation gravel the VGG Gram error
    between the two 256-px versions of the same photo (1.55) was most of a fit's error
    against it (1.9): the encoder and the fits were judged against a softer photo than the
    one they learnt from. Images over ``RESIZE_DIRECT_PIXELS`` that shrink by 2 or more are
    first box-reduced in bands (bounded memory) to a short side in [short_side,
    2 * short_side)."""
    h, w = image.shape[:2]
    shape = working_shape(h, w, short_side)
    if shape == (h, w):
        return image
    if shape[0] * shape[1] > MAX_WORK_PIXELS:
        raise LimitExceeded(f"resizing {w}x{h} to a short side of {short_side} gives "
                            f"{shape[0] * shape[1]} pixels, limit is {MAX_WORK_PIXELS}")
    factor = min(h, w) // short_side
    if h * w > RESIZE_DIRECT_PIXELS and factor >= 2:
        image = _box_reduce(image, factor)
    out = np.empty(shape + (3,), np.float32)
    for c in range(3):
        channel = Image.fromarray(np.ascontiguousarray(image[..., c], dtype=np.float32))
        across = np.clip(np.asarray(channel.resize((shape[1], channel.height), Image.Resampling.LANCZOS)), 0, 1)
        down = Image.fromarray(across).resize((shape[1], shape[0]), Image.Resampling.LANCZOS)
        out[..., c] = np.clip(np.asarray(down), 0, 1)
    return out


def crop_starts(length: int, size: int, count: int) -> np.ndarray:
    """Where ``count`` crops of ``size`` start along a side of ``length``: first and last flush
    with the borders, evenly spaced between, rounded; duplicates (no room for ``count``
    distinct positions) dropped. Returns sorted int starts."""
    return np.unique(np.round(np.linspace(0, length - size, count)).astype(int))


def encoder_crops(image: np.ndarray, *, short_side: int, size: int = 128, grid: int = 3,
                  dihedral: bool = True) -> np.ndarray:
    """Crops of an sRGB image for the encoder.

    The image is resized so its shorter side is ``max(short_side, size)`` (the model's
    working resolution: features keep the scale seen in training), then a regular
    ``grid x grid`` lattice of ``size`` crops is taken, first and last flush with the
    borders, evenly spaced between (a side with room for only one crop gives one
    position; duplicates are dropped). ``dihedral``: each crop also in its other seven
    orientations (quarter turns, each mirrored), so the mean code does not depend on how the
    photo was turned or mirrored. It also scored better: on the 40 validation families of
    ``make quality-large`` the upload's style error over the photo's floor, median 4.81 ->
    4.40 (geometric mean 5.89 -> 5.83, lower on 25 of 40), for 8x the encoder's work.
    Values map 0..1 -> -1..1 (``2x - 1``).

    image : (H, W, 3) float32 sRGB 0..1. Returns (N, 3, size, size) float32: the grid's
    crops (N0 <= grid^2, row-major) first, then with ``dihedral`` the same N0 in each further
    orientation (N = 8 N0).
    """
    work = resize_short_side(image, max(short_side, size))
    h, w = work.shape[:2]
    rows, cols = crop_starts(h, size, grid), crop_starts(w, size, grid)
    windows = np.lib.stride_tricks.sliding_window_view(work, (size, size), axis=(0, 1))
    crops = windows[rows[:, None], cols[None, :]]          # (R, C, 3, size, size)
    crops = crops.reshape(-1, 3, size, size)
    if dihedral:
        turns = [np.rot90(crops, k, axes=(2, 3)) for k in range(4)]
        crops = np.concatenate(turns + [turn[..., ::-1] for turn in turns])
    return (crops * np.float32(2) - np.float32(1)).astype(np.float32)


def _box_reduce(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean of factor x factor blocks of (H, W, 3) float32, a band of rows at a time
    (trailing rows / columns that fill no whole block are dropped)."""
    h, w = image.shape[0] // factor, image.shape[1] // factor
    out = np.empty((h, w, 3), dtype=np.float32)
    rows = max(1, DECODE_BAND_PIXELS // (w * factor * factor))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        band = image[r0 * factor:r1 * factor, :w * factor]
        out[r0:r1] = band.reshape(r1 - r0, factor, w, factor, 3).mean(axis=(1, 3), dtype=np.float32)
    return out
