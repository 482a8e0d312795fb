"""The one pair of sRGB transfer functions every image reader and writer uses, and the
one smooth-shading removal (``even_lighting``: an upload's ``lighting: even``, and what the
structure detectors of model/ read).

Exact piecewise IEC 61966-2-1 curves (linear segment near black, 2.4 power above),
not the 2.2 gamma approximation. Inputs are clipped to [0, 1] first: the sampler's
output is nominally 0..1 and EXR uploads may hold HDR values we do not tone-map.
"""
from __future__ import annotations

import numpy as np

# Rec. 709 luminance weights of linear RGB: Y = LUMA_709 . (R, G, B).
LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

# Break points of the sRGB curve on each side.
_SRGB_KNEE = 0.04045
_LINEAR_KNEE = 0.0031308


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values to linear light.

    srgb : (...) float array, nominally 0..1 (clipped). Returns float32 of the same shape.
    """
    x = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)   # float64: exact 0 and 1
    out = np.where(x <= _SRGB_KNEE, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    return out.astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Encode linear-light values with the sRGB transfer function.

    linear : (...) float array, clipped to 0..1. Returns float32 of the same shape.
    """
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    out = np.where(x <= _LINEAR_KNEE, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055)
    return out.astype(np.float32)


def linear_to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear 0..1 floats to 8-bit sRGB codes (round half up). Returns uint8, same shape."""
    return (linear_to_srgb(linear) * np.float32(255) + np.float32(0.5)).astype(np.uint8)


def even_lighting(image: np.ndarray) -> np.ndarray:
    """The photo with its smooth shading divided out: light falling off across it, a
    vignette. A quadratic in x and y fitted to log luminance (least squares, linear light),
    taken out relative to its mean, so the photo keeps its mean log luminance and every
    detail smaller than the photo itself; the texture's own large patches partly go too
    where they happen to look like shading (the validation granite's).

    image : (H, W, 3) float32 sRGB 0..1. Returns the same shape, float32 sRGB 0..1 (a pixel
    brightened past white clips)."""
    linear = srgb_to_linear(image)
    height, width = linear.shape[:2]
    y, x = np.linspace(-1, 1, height)[:, None], np.linspace(-1, 1, width)[None, :]
    step = max(1, int(np.sqrt(height * width / 65536)))  # the fit needs no more samples than this
    sample = np.s_[::step, ::step]
    log_luminance = np.log(np.maximum(linear[sample] @ LUMA_709, 1e-4), dtype=np.float64)
    xs, ys = np.broadcast_arrays(x[sample], y[sample])
    terms = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=-1).reshape(-1, 6)
    _, cx, cy, cxx, cxy, cyy = np.linalg.lstsq(terms, log_luminance.ravel(), rcond=None)[0]
    shading = (cx * x + cxx * x * x) + (cy * y + cyy * y * y) + cxy * x * y     # (H, W) by broadcasting
    shading -= shading.mean()
    return linear_to_srgb(linear * np.exp(-shading)[..., None].astype(np.float32))
