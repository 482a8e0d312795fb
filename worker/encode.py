"""What a texture stores of an uploaded photo: its code and its colour table for the model's
sampler. One way through: the photo (``worker.photo``), then the encoder (``worker.runtime``)
on the photo's crops, each in its eight orientations, then the choice of code, then the table
(``worker.colour_match``).

The choice: the crops' mean code is one guess of several the encoder's codes offer
(``candidate_codes``). Each candidate draws one tile; the code whose tile's VGG16 Gram
statistics (the model's ``style.onnx``, the refinement's own loss) lie nearest the photo's is
stored (docs/DECISIONS.md, "An upload chooses its code"). Its colour table is then chosen
the same way: the photo's histograms (quantile curves), or the moment transfer (linear
curves) where that tile lies nearer the photo (``code_colour``). An export without style
statistics keeps the mean and quantile curves.
"""
from __future__ import annotations

import numpy as np

from worker.colour import even_lighting, linear_to_srgb
from worker.colour_match import calibrate_texture, texture_vector
from worker.photo import encoder_crops, working_photo
from worker.runtime import ModelRuntime
from worker.tiles import NATIVE_ZOOM, render_tile

ORIENTATIONS = 8  # encoder_crops's dihedral copies of each crop, orientation-major
# A candidate's tile: 128 px at the native zoom (the crop size the Gram loss's layer weights
# were measured at). Its seed and place are arbitrary but fixed, so an upload's choice is
# deterministic. Four such crops (a 256-px tile) chose as well (median 3.44 against 3.47 over
# the floor) for 1.8x the upload's time.
STYLE_CROP = 128
CHOICE_SEED, CHOICE_X, CHOICE_Y = 7, 3, 3
# the mean moved this many standard deviations either way along the codes' main axis
PRINCIPAL_STEP = 0.7
# The recipe an upload's code is chosen by, kept with it (service: Texture.code_choice).
# 1: the crops' mean code (also what a model without style statistics gets);
# 2: of ``candidate_codes``, the one nearest the photo in style (``choose_code``).
# Bump it whenever encode_texture chooses another code for the same photo and model:
# ``texspace reencode --stale-codes`` then chooses the stored uploads' codes again.
MEAN_CHOICE, CODE_CHOICE = 1, 2


def encode_image(runtime: ModelRuntime, image: np.ndarray, *, grid: int = 3) -> np.ndarray:
    """Texture code of an sRGB image: the mean of its crops' codes. Returns (8,) float32."""
    return crop_codes(runtime, image, grid=grid).mean(axis=0).astype(np.float32)


def crop_codes(runtime: ModelRuntime, image: np.ndarray, *, grid: int = 3) -> np.ndarray:
    """The encoder's code of each crop of ``encoder_crops`` (eight orientations of each grid
    position, orientation-major): (8 N0, code_size) float32."""
    crops = encoder_crops(image, short_side=runtime.short_side, size=runtime.input_size, grid=grid)
    return runtime.encode(crops)


def candidate_codes(codes: np.ndarray) -> np.ndarray:
    """The codes an upload chooses among, from its crops' codes (8 N0, k) as ``crop_codes``
    gives them: their mean (first), their element-wise median, each grid position's mean over
    its eight orientations, and the mean moved ``PRINCIPAL_STEP`` standard deviations either
    way along the codes' first principal axis. (N0 + 4, k) float32."""
    codes = np.asarray(codes, np.float64)
    mean = codes.mean(axis=0)
    per_position = codes.reshape(ORIENTATIONS, -1, codes.shape[1]).mean(axis=0)
    _, singular, axes = np.linalg.svd(codes - mean, full_matrices=False)
    step = PRINCIPAL_STEP * singular[0] / np.sqrt(len(codes)) * axes[0]
    return np.vstack([mean, np.median(codes, axis=0), per_position, mean + step, mean - step]).astype(np.float32)


def photo_style(runtime: ModelRuntime, working: np.ndarray) -> np.ndarray:
    """The photo's style: the mean style vector of its 128-px crops on the encoder's grid. (D,)"""
    crops = encoder_crops(working, short_side=runtime.short_side, size=STYLE_CROP, dihedral=False)
    return runtime.style((crops.transpose(0, 2, 3, 1) + 1) / 2).mean(axis=0)


def choice_tile(runtime: ModelRuntime, vector: np.ndarray) -> np.ndarray:
    """The tile a candidate is judged by: (STYLE_CROP, STYLE_CROP, 3) sRGB of a texture vector
    (code + colour table)."""
    return linear_to_srgb(render_tile(runtime.sampler, vector, CHOICE_SEED, NATIVE_ZOOM, CHOICE_X, CHOICE_Y,
                                      STYLE_CROP, pixels_per_unit=runtime.pixels_per_unit))


def style_distances(runtime: ModelRuntime, vectors: list[np.ndarray], target: np.ndarray) -> np.ndarray:
    """How far each texture vector's (code + colour table) ``choice_tile`` lies from the style
    ``target`` (``photo_style``): the Gram loss over ``style.onnx``'s layers. (N,) float32."""
    tiles = np.stack([choice_tile(runtime, vector) for vector in vectors])
    return np.square(runtime.style(tiles) - target).sum(axis=1)


def nearer_curves(runtime: ModelRuntime, working: np.ndarray, code: np.ndarray, target: np.ndarray,
                  quantile: np.ndarray, distance: float) -> np.ndarray:
    """The code's colour table: ``quantile`` (its quantile-curve table, whose tile lies at
    ``distance`` from ``target``), or its linear-curve table where that tile lies nearer.
    Quantile curves give the photo's histograms; where the code draws its features in other
    proportions than the photo's, they stretch them (a bland plate's rare dark flecks into
    dark blotches) and the moment transfer draws nearer the photo."""
    linear = calibrate_texture(runtime.sampler, code, working, curves="linear")
    if linear.size and style_distances(runtime, [texture_vector(code, linear)], target)[0] < distance:
        return linear
    return quantile


def code_colour(runtime: ModelRuntime, working: np.ndarray, code: np.ndarray) -> np.ndarray:
    """An encoder code's colour table for the photo ``working`` as an upload gets it (``texspace
    recolour`` computes stored ones again with it): quantile curves, or the nearer of them and
    linear ones where the model has style statistics (``nearer_curves``). (colour_size,) float32."""
    quantile = calibrate_texture(runtime.sampler, code, working)
    if choice_recipe(runtime) != CODE_CHOICE or not quantile.size:
        return quantile
    target = photo_style(runtime, working)
    distance = style_distances(runtime, [texture_vector(code, quantile)], target)[0]
    return nearer_curves(runtime, working, code, target, quantile, distance)


def choose_code(runtime: ModelRuntime, working: np.ndarray, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of ``candidate_codes(codes)``, the code whose tile (with its quantile-curve table) is
    nearest the photo ``working`` in style, and its table as ``code_colour`` chooses it:
    ((k,) float32, (colour_size,) float32). Ties keep the first (the mean)."""
    candidates = candidate_codes(codes)
    target = photo_style(runtime, working)
    colours = [calibrate_texture(runtime.sampler, code, working) for code in candidates]
    distances = style_distances(runtime, [texture_vector(c, colour) for c, colour in zip(candidates, colours)], target)
    best = int(np.argmin(distances))
    if not colours[best].size:
        return candidates[best], colours[best]
    return candidates[best], nearer_curves(runtime, working, candidates[best], target, colours[best], distances[best])


def choice_recipe(runtime: ModelRuntime) -> int:
    """The recipe ``encode_texture`` chooses a code by under ``runtime``: ``CODE_CHOICE`` where
    the model has style statistics and its working photo holds a style crop, else ``MEAN_CHOICE``."""
    return CODE_CHOICE if runtime.style_path is not None and runtime.short_side >= STYLE_CROP else MEAN_CHOICE


def encode_texture(runtime: ModelRuntime, image: np.ndarray, lighting: str = "as-is") -> tuple[np.ndarray, np.ndarray]:
    """What a texture stores of an sRGB photo: its code (code_size,) float32 and its colour
    table for the model's sampler (worker/colour_match.py; empty if the sampler has no colour
    stage), from the photo as ``working_photo`` gives it: the chosen code (module docstring)
    where the model has style statistics, else the crops' mean code."""
    working = working_photo(image, runtime.short_side, lighting)
    # The crops are cut at max(short_side, input size): where the crop fits (every model so
    # far), that is the working image itself, so the photo is resized once, not twice.
    if runtime.short_side >= runtime.input_size:
        cropped = working
    else:  # crops larger than the working image: cut from the photo (evened as a whole)
        cropped = even_lighting(image) if lighting == "even" else image
    codes = crop_codes(runtime, cropped)
    if choice_recipe(runtime) == CODE_CHOICE:
        return choose_code(runtime, working, codes)
    code = codes.mean(axis=0).astype(np.float32)
    return code, calibrate_texture(runtime.sampler, code, working)
