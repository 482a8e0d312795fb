"""The one pair of sRGB transfer functions every image reader and writer uses.

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
