"""How a photo's texture runs and spreads where nothing repeats: grain along an image axis,
its strength and lean, the photo's lean, straightening, and evenness at large scales.
Functions over (H, W, 3) RGB arrays in [0, 1] at the working resolution.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from model.config import ModelConfig
from model.structure.correlation import rec709_luminance

# Grain detection (``grain="auto"``): a photo has grain when its luminance gradient energy
# across one image axis is at least GRAIN_RATIO times that along the other, at every
# blur in GRAIN_SCALES (px at the working resolution), so fine scratches alone or one
# coarse band alone do not count. Measured on the 41 packaged photos (log2 of the ratio
# at 1/2/4 px): the five wood photos (1.6-6.0), brushed metal (1.9-2.2), a striped rug
# (1.8) and skimage's brick laid on end (1.6-1.8: long joints up-down) pass; the brick
# wall (-0.06 at 4 px), cinder blocks (0.84), corrugated cardboard (0.19 at 4 px) do not.
GRAIN_RATIO = 3.0
GRAIN_SCALES = (1.0, 2.0, 4.0)
# How much longer a fit's noise cells are along the grain (``ModelConfig.grain_stretch``):
# STRONG_GRAIN_STRETCH where the gradient ratio is at least GRAIN_RATIO^2 at every blur
# (planed wood, planks: lines that run across the whole photo), else GRAIN_STRETCH. 60-s
# fits, seeds 0 / 1, quality-protocol tile style error, stretch 8 -> 16: ratio 11-63 (the
# validation wood, two training woods, planks) 0.038 / 0.039 -> 0.035 / 0.035, 0.035 / 0.030
# -> 0.009 / 0.008, 0.056 / 0.045 -> 0.044 / 0.033, 0.152 / 0.116 -> 0.097 / 0.098, and the
# lines run on instead of breaking into waves; ratio 3-5 (an old wood, the rug, brushed
# metal, skimage's brick) 0.457 / 0.331 -> 0.581 / 0.365, 10.5 / 10.3 -> 13.1 / 12.5,
# 0.029 / 0.051 -> 0.030 / 0.036, 0.337 / 0.367 -> 0.336 / 0.329.
GRAIN_STRETCH = ModelConfig.grain_stretch  # the model's default, 8
STRONG_GRAIN_STRETCH = 2 * GRAIN_STRETCH
# Grain off its image axis (``grain_tilt``, ``straighten``): the noise can be stretched
# along world x or y only, so a fit of a photo whose grain leans draws it along the axis
# as blobs with pale streaks (vpython_wood_old, about 7 degrees). Measured on the packaged
# photos with grain: that wood -6.9 degrees, brushed metal 2.5, the other six within 0.4
# (the striped rug 0.34). A fit turns a photo whose grain leans at least GRAIN_TILT_MIN degrees
# so that it runs along the nearer axis, and learns from the largest centred rectangle of
# the photo's shape inside the turned photo (a square: 0.78 of each side at 20 degrees,
# 0.71 at 45). Past about 30 degrees the axis test (``detect_grain``) no longer sees the
# grain (a wood photo turned 35-60 degrees: none found, the fit drew isotropic blotches):
# ``leaning_grain`` then looks for it on the photo turned by its main orientation. None of
# the 41 packaged photos without grain gains one that way (granite, the most directional,
# reaches a gradient ratio of 1.6 turned, under GRAIN_RATIO).
GRAIN_TILT_MIN = 3.0
GRAIN_TILT_MAX = 45.0
GRAIN_TILT_BLUR = 2.0

# Evenness (``detect_even``): the means of a photo's EVEN_BLOCK-px blocks vary by less than
# EVEN_SHARE of its luminance variance: nothing in it is larger than a few blocks. Measured on
# the 41 packaged photos at 256 px (share at 32 px): the metal grills 0.000 / 0.004, a
# ceiling tile and stucco 0.001, the skimage and validation gravel 0.015 / 0.016, asphalt
# 0.016, skimage grass 0.017, a grass 0.025, drywall 0.026; then concrete 0.033, the brick
# wall 0.041, the validation grass 0.073, granite 0.061, wood 0.15-0.44. A fit of an even
# photo mutes the noise octaves whose cells are EVEN_BLOCK px or larger (model.fit): the
# validation gravel's tiles otherwise keep blotches of 35-100 px with 3-6x the photo's
# power there (docs/DECISIONS.md, "Even photos mute their coarse octaves").
EVEN_BLOCK = 32
EVEN_SHARE = 0.03


def detect_grain(image: np.ndarray) -> str | None:
    """The axis the photo's grain runs along, ``"x"`` (left-right) or ``"y"`` (up-down),
    or None for an isotropic photo. ``image``: (H, W, 3) RGB in [0, 1] at the working
    resolution. Diagonal grain counts as none (a fit can stretch along x or y only)."""
    log_ratios = _gradient_log_ratios(image)
    threshold = np.log2(GRAIN_RATIO)
    if min(log_ratios) >= threshold:
        return "y"  # changes across columns, constant down them: streaks run up-down
    if max(log_ratios) <= -threshold:
        return "x"
    return None


def _gradient_log_ratios(image: np.ndarray) -> list[float]:
    """log2 of the luminance gradient energy across columns over that across rows, at each
    blur in GRAIN_SCALES: positive where streaks run up-down (y), negative left-right (x)."""
    luminance = rec709_luminance(image)
    log_ratios = []
    for sigma in GRAIN_SCALES:
        rows, cols = np.gradient(ndimage.gaussian_filter(luminance, sigma))
        log_ratios.append(np.log2(max(float(np.mean(cols ** 2)), 1e-20) / max(float(np.mean(rows ** 2)), 1e-20)))
    return log_ratios


def grain_stretch(image: np.ndarray, grain: str) -> float:
    """How much longer the fit's noise cells are along ``grain`` ("x" or "y"): the strong
    stretch where the photo's gradient ratio is at least GRAIN_RATIO^2 at every blur."""
    log_ratios = np.asarray(_gradient_log_ratios(image)) * (1.0 if grain == "y" else -1.0)
    return STRONG_GRAIN_STRETCH if log_ratios.min() >= 2 * np.log2(GRAIN_RATIO) else GRAIN_STRETCH


def grain_tilt(image: np.ndarray, grain: str) -> float:
    """Degrees from the image axis ``grain`` (``"x"`` or ``"y"``) to the direction the
    photo's grain runs, measured from +x towards +y (x right, y down: clockwise as shown),
    in (-90, 90]. The grain runs where the luminance changes least: across the main axis of
    the structure tensor (the mean outer product of the luminance gradient, taken as
    derivatives of a GRAIN_TILT_BLUR px Gaussian: ``structure_tensor``)."""
    (xx, xy), (_, yy) = structure_tensor(image)
    across = 0.5 * np.degrees(np.arctan2(2 * xy, xx - yy))
    axis = 0.0 if grain == "x" else 90.0
    return float(-((axis - across) % 180.0 - 90.0))


def structure_tensor(image: np.ndarray, blur: float = GRAIN_TILT_BLUR) -> np.ndarray:
    """(2, 2) float64: the mean outer product of the luminance gradient (x, y), taken as
    derivatives of a ``blur`` px Gaussian, without the border the blur mirrors."""
    luminance = rec709_luminance(image)
    margin = int(4 * blur)  # the blur's mirrored border bends leaning streaks
    # derivatives of the Gaussian: central differences damp the steeper component of a
    # leaning streak more and overstate its lean (by 7% on 9-px stripes)
    gy, gx = (ndimage.gaussian_filter(luminance, blur, order=order)[margin:-margin, margin:-margin]
              for order in ((1, 0), (0, 1)))
    return np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])


def photo_lean(image: np.ndarray, blur: float = GRAIN_TILT_BLUR) -> tuple[float, float]:
    """(degrees, stretch): the direction the photo's features run along, as ``grain_tilt``
    measures it from +x towards +y, and how much longer they are along it than across it
    (the square root of the structure tensor's eigenvalue ratio: features stretched k times
    have gradients k times weaker along them)."""
    # eigenvalues ascending: the first vector is where luminance changes least, along the features
    values, vectors = np.linalg.eigh(structure_tensor(image, blur))
    if not values[1] > 0:  # a flat photo (no gradient anywhere) leans nowhere: a stretch of 0 broke the fit
        return 0.0, 1.0
    degrees = (np.degrees(np.arctan2(vectors[1, 0], vectors[0, 0])) + 90.0) % 180.0 - 90.0
    return float(degrees), float(np.sqrt(values[1] / max(values[0], 1e-30)))


def grain_turn(image: np.ndarray, grain: str | None) -> float:
    """The degrees a fit turns the photo by so its grain runs along ``grain``'s axis: its
    ``grain_tilt`` where that leans GRAIN_TILT_MIN..GRAIN_TILT_MAX degrees, else 0 (no
    grain, one close enough to the axis, or one too far off it to call along it)."""
    tilt = grain_tilt(image, grain) if grain else 0.0
    return tilt if GRAIN_TILT_MIN <= abs(tilt) <= GRAIN_TILT_MAX else 0.0


def leaning_grain(image: np.ndarray) -> str | None:
    """The axis, ``"x"`` or ``"y"``, of a grain that leans too far for ``detect_grain``
    (which compares the gradients along the image axes): the axis nearer the photo's main
    orientation (``grain_tilt``), if the photo turned onto it (``straighten``) has grain
    along it; else None. The fit then turns the photo by ``grain_turn``."""
    tilt = grain_tilt(image, "x")  # (-90, 90] from +x
    axis = "x" if abs(tilt) <= 45.0 else "y"
    turn = grain_tilt(image, axis)
    if not GRAIN_TILT_MIN <= abs(turn) <= GRAIN_TILT_MAX:
        return None  # along an axis already: what detect_grain found, it found
    return axis if detect_grain(straighten(image, turn)) == axis else None


def turn_lattice(lattice: tuple[float, float, float, float], degrees: float) -> tuple[float, float, float, float]:
    """A lattice (ax, ay, bx, by) found on a photo ``straighten``ed by ``degrees``, in the
    photo's own frame: both vectors turned by ``degrees`` from +x towards +y."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    ax, ay, bx, by = lattice
    return (float(c * ax - s * ay), float(s * ax + c * ay), float(c * bx - s * by), float(s * bx + c * by))


def straighten(image: np.ndarray, degrees: float) -> np.ndarray:
    """``image`` turned by ``-degrees`` (a grain at ``degrees``, as ``grain_tilt`` measures,
    comes to lie along its axis): the largest centred rectangle of the image's own aspect
    that the turned image covers, at the same pixel size. Cubic interpolation, clipped to
    [0, 1]; (h, w, 3) -> (h', w', 3) with h' / h = w' / w <= 1."""
    height, width = image.shape[:2]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    # a w' x h' rectangle fits inside the turned w x h one when w'c + h'|s| <= w and w'|s| + h'c <= h
    shrink = min(width / (width * c + height * abs(s)), height / (width * abs(s) + height * c))
    out_h, out_w = int(height * shrink), int(width * shrink)
    rows, cols = np.mgrid[0:out_h, 0:out_w].astype(np.float64)
    y, x = rows - (out_h - 1) / 2, cols - (out_w - 1) / 2
    # output pixel (x, y) shows the photo at (x, y) turned by +degrees (x right, y down)
    src_x, src_y = x * c - y * s + (width - 1) / 2, x * s + y * c + (height - 1) / 2
    turned = [ndimage.map_coordinates(np.asarray(image[..., k], np.float64), [src_y, src_x], order=3, mode="nearest")
              for k in range(image.shape[2])]
    return np.clip(np.stack(turned, axis=-1), 0.0, 1.0).astype(image.dtype)


def detect_even(image: np.ndarray) -> bool:
    """Whether the photo's luminance is even at large scales: the variance of its
    ``EVEN_BLOCK``-px block means is below ``EVEN_SHARE`` of the pixels' variance (a flat
    photo, with no variance, is not called even: there is nothing to mute for)."""
    lum = rec709_luminance(image)
    rows, cols = lum.shape[0] // EVEN_BLOCK, lum.shape[1] // EVEN_BLOCK
    if rows * cols < 4 or lum.var() <= 1e-8:
        return False
    blocks = lum[:rows * EVEN_BLOCK, :cols * EVEN_BLOCK].reshape(rows, EVEN_BLOCK, cols, EVEN_BLOCK).mean(axis=(1, 3))
    return bool(blocks.var() < EVEN_SHARE * lum.var())
