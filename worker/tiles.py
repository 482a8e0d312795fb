"""Infinite 2D tiles of a texture (DESIGN.md Contract 2, docs/ARCHITECTURE.md "World space").

Zoom ``z`` has ``pixels_per_unit * 2 ** (z - NATIVE_ZOOM)`` raster pixels per world unit,
so at ``NATIVE_ZOOM`` one tile pixel is one exemplar pixel (at the model's working
resolution). Tile (z, x, y, size) holds raster pixels [x*size, (x+1)*size) x
[y*size, (y+1)*size); pixel (i, j) has its centre at raster (x*size + i + 0.5,
y*size + j + 0.5) and world ``u = col / ppw``, ``v = row / ppw`` (v grows down).

Seamless by construction: every tile is a window on one global raster of a point
function, so neighbours share no state and cannot disagree.

Anti-aliasing. Below ``NATIVE_ZOOM`` a tile pixel covers several exemplar pixels, so we
evaluate ``s = min(2 ** (NATIVE_ZOOM - z), SUPERSAMPLE_CAP)`` sub-samples per axis on
the sub-pixel grid (the zoom-z raster at s times the resolution, centres at
``(s*x*size + m + 0.5) / s``) and box-filter them in linear light. Because the
sub-sample grid of zoom z with factor s *is* the pixel grid of zoom z + log2(s), the
four children of a tile, box-downsampled, reproduce the parent exactly (to float
rounding) for every ``z >= NATIVE_ZOOM - log2(SUPERSAMPLE_CAP)``. Further out, each
pixel averages a regular CAP x CAP subset of the exemplar pixels it covers; the bound
there is statistical (measured in tests/worker/test_tiles.py). Zoomed in (z > native)
the texture is magnified, one sample per pixel.

Coordinates are exact: sub-sample indices are built in int64 and turned into world
positions with one power-of-two scaling (exact) and one division by
``pixels_per_unit`` (correctly rounded), so tile (z, 2^31, -2^31) is as precise as
tile (z, 0, 0).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from worker.errors import InvalidParameter
from worker.runtime import Sampler

NATIVE_ZOOM = 6      # one tile pixel == one exemplar pixel
MIN_ZOOM = 2         # 16 exemplar pixels per tile pixel
MAX_ZOOM = 12        # 64x magnification
MIN_TILE_SIZE = 64
MAX_TILE_SIZE = 1024
SUPERSAMPLE_CAP = 4  # at most 4 x 4 sampler calls per output pixel
COORD_LIMIT = 2 ** 36  # |x|, |y|: keeps 2*s*x*size + ... below 2^53 (exact in float64)
PLANES = ("xy", "xz", "yz")
# Which world axis receives u, v and the plane offset, per plane.
_PLANE_AXES = {"xy": (0, 1, 2), "xz": (0, 2, 1), "yz": (1, 2, 0)}


def supersample_for(z: int, cap: int = SUPERSAMPLE_CAP) -> int:
    """Sub-samples per axis for zoom ``z``: 2^(NATIVE_ZOOM - z) when zoomed out, capped."""
    return int(min(2 ** max(NATIVE_ZOOM - z, 0), cap))


def _check_tile(z: int, x: int, y: int, size: int, supersample: int, plane: str) -> None:
    if not MIN_ZOOM <= z <= MAX_ZOOM:
        raise InvalidParameter(f"zoom {z} outside [{MIN_ZOOM}, {MAX_ZOOM}]")
    if not MIN_TILE_SIZE <= size <= MAX_TILE_SIZE:
        raise InvalidParameter(f"tile size {size} outside [{MIN_TILE_SIZE}, {MAX_TILE_SIZE}]")
    if abs(x) > COORD_LIMIT or abs(y) > COORD_LIMIT:
        raise InvalidParameter(f"tile coordinates must satisfy |x|, |y| <= 2^36, got {x}, {y}")
    if supersample < 1 or supersample & (supersample - 1) or supersample > 16:
        raise InvalidParameter(f"supersample must be a power of two in [1, 16], got {supersample}")
    if plane not in _PLANE_AXES:
        raise InvalidParameter(f"plane must be one of {PLANES}, got {plane!r}")


def raster_coords(z: int, start: int, count: int, *, pixels_per_unit: float,
                  supersample: int = 1) -> np.ndarray:
    """World coordinates of ``count`` consecutive sub-sample centres along one axis.

    start : index of the first *pixel* on the zoom-z raster (e.g. x * size).
    Returns (count * supersample,) float64: ``(s*start + m + 0.5) / (s * ppw)`` for
    m in [0, count*s), where ppw = pixels_per_unit * 2^(z - NATIVE_ZOOM).
    """
    s = int(supersample)
    # 2*(s*start + m) + 1 is an odd integer < 2^53: exact in int64 and in float64.
    twice = (np.arange(count * s, dtype=np.int64) + s * int(start)) * 2 + 1
    shift = NATIVE_ZOOM - z - 1 - (s.bit_length() - 1)  # divide by 2*s*2^(z-N): exact
    return np.ldexp(twice.astype(np.float64), shift) / float(pixels_per_unit)


def tile_points(z: int, x: int, y: int, size: int, *, pixels_per_unit: float,
                plane: str = "xy", offset: float = 0.0, supersample: int = 1) -> np.ndarray:
    """World positions of every sub-sample of tile (z, x, y).

    Returns (size*s * size*s, 3) float64, row-major over the tile's sub-sample raster
    (row = v index, column = u index), so ``rgb.reshape(size, s, size, s, 3)`` groups
    the s x s sub-samples of each pixel.
    """
    _check_tile(z, x, y, size, supersample, plane)
    u = raster_coords(z, x * size, size, pixels_per_unit=pixels_per_unit, supersample=supersample)
    v = raster_coords(z, y * size, size, pixels_per_unit=pixels_per_unit, supersample=supersample)
    return plane_points(u, v, plane=plane, offset=offset)


def plane_points(u: np.ndarray, v: np.ndarray, *, plane: str = "xy", offset: float = 0.0) -> np.ndarray:
    """Grid of points on an axis-aligned plane from column coords u (C,) and row coords v (R,).

    Returns (R*C, 3) float64, row-major (rows follow v). Built by broadcasting, no copies
    of u or v beyond the output itself.
    """
    if plane not in _PLANE_AXES:
        raise InvalidParameter(f"plane must be one of {PLANES}, got {plane!r}")
    axis_u, axis_v, axis_o = _PLANE_AXES[plane]
    pts = np.empty((len(v), len(u), 3), dtype=np.float64)
    pts[:, :, axis_u] = u[None, :]
    pts[:, :, axis_v] = v[:, None]
    pts[:, :, axis_o] = offset
    return pts.reshape(-1, 3)


def box_downsample(rgb: np.ndarray, factor: int) -> np.ndarray:
    """Average factor x factor blocks. rgb : (H, W, C) with H, W divisible by factor -> (H/f, W/f, C)."""
    if factor == 1:
        return rgb
    h, w, c = rgb.shape
    return rgb.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3), dtype=np.float32)


def render_window(sampler: Sampler, code: np.ndarray, seed: int, z: int, col0: int, row0: int,
                  width: int, height: int, *, pixels_per_unit: float, plane: str = "xy",
                  offset: float = 0.0, supersample: int = 1) -> np.ndarray:
    """Linear RGB of any pixel window [col0, col0+width) x [row0, row0+height) of the
    zoom-z raster (tiles are windows aligned on multiples of their size).

    Returns (height, width, 3) float32; identical to the matching pixels of the tiles.
    """
    s = int(supersample)
    limit = COORD_LIMIT * MAX_TILE_SIZE
    if max(abs(col0), abs(row0), abs(col0 + width), abs(row0 + height)) > limit:
        raise InvalidParameter(f"raster coordinates must stay within +-2^46, got {col0}, {row0}")
    u = raster_coords(z, col0, width, pixels_per_unit=pixels_per_unit, supersample=s)
    v = raster_coords(z, row0, height, pixels_per_unit=pixels_per_unit, supersample=s)
    rgb = sampler.sample(plane_points(u, v, plane=plane, offset=offset), code, seed)
    return box_downsample(rgb.reshape(height * s, width * s, 3), s)


def resolve_pixels_per_unit(sampler: Sampler, pixels_per_unit: float | None) -> float:
    """The explicit value, else ``sampler.pixels_per_unit`` (a ModelRuntime has one)."""
    if pixels_per_unit is None:
        pixels_per_unit = getattr(sampler, "pixels_per_unit", None)
        if pixels_per_unit is None:
            raise InvalidParameter("pixels_per_unit is required for a bare sampler session")
    return float(pixels_per_unit)


def render_tile(sampler: Sampler, code: np.ndarray, seed: int, z: int, x: int, y: int,
                size: int = 256, *, pixels_per_unit: float | None = None, plane: str = "xy",
                offset: float = 0.0, supersample: int | None = None, band_samples: int | None = None,
                before_band: Callable[[], None] | None = None) -> np.ndarray:
    """Linear RGB of tile (z, x, y).

    code : (8,) float32 texture code. pixels_per_unit defaults to ``sampler.pixels_per_unit``
    (a ModelRuntime has one). supersample defaults to ``supersample_for(z)``.
    band_samples : render in bands of whole rows of about this many sampler calls, calling
    ``before_band()`` before each (the API lets small tiles go first there).
    Returns (size, size, 3) float32 linear 0..1.
    """
    ppu = resolve_pixels_per_unit(sampler, pixels_per_unit)
    s = supersample_for(z) if supersample is None else int(supersample)
    _check_tile(z, x, y, size, s, plane)
    rows = size if not band_samples else max(1, min(size, band_samples // (size * s * s)))
    out = np.empty((size, size, 3), dtype=np.float32)
    for r0 in range(0, size, rows):
        if before_band is not None:
            before_band()
        n = min(rows, size - r0)
        out[r0:r0 + n] = render_window(sampler, code, seed, z, x * size, y * size + r0, size, n,
                                       pixels_per_unit=ppu, plane=plane, offset=offset, supersample=s)
    return out
