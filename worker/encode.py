"""What a texture stores of an uploaded photo: its code (the encoder's mean over the
photo's crops, each in its eight orientations) and its colour table for the model's
sampler. One way through: the photo (``worker.photo``), then the encoder
(``worker.runtime``), then the table (``worker.colour_match``).
"""
from __future__ import annotations

import numpy as np

from worker.colour import even_lighting
from worker.colour_match import calibrate_texture
from worker.photo import encoder_crops, working_photo
from worker.runtime import ModelRuntime


def encode_image(runtime: ModelRuntime, image: np.ndarray, *, grid: int = 3) -> np.ndarray:
    """Texture code of an sRGB image: the mean of its crops' codes. Returns (8,) float32."""
    crops = encoder_crops(image, short_side=runtime.short_side, size=runtime.input_size, grid=grid)
    return runtime.encode(crops).mean(axis=0).astype(np.float32)


def encode_texture(runtime: ModelRuntime, image: np.ndarray, lighting: str = "as-is") -> tuple[np.ndarray, np.ndarray]:
    """What a texture stores of an sRGB photo: its code (8,) float32 and its colour table
    for the model's sampler (worker/colour_match.py; empty if the sampler has no colour stage),
    from the photo as ``working_photo`` gives it."""
    working = working_photo(image, runtime.short_side, lighting)
    # The crops are cut at max(short_side, input size): where the crop fits (every model so
    # far), that is the working image itself, so the photo is resized once, not twice.
    if runtime.short_side >= runtime.input_size:
        cropped = working
    else:  # crops larger than the working image: cut from the photo (evened as a whole)
        cropped = even_lighting(image) if lighting == "even" else image
    code = encode_image(runtime, cropped)
    return code, calibrate_texture(runtime.sampler, code, working)
