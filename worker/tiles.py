"""Infinite 2D tiles of a texture (docs/ARCHITECTURE.md, Contract 2 and "World space").

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
the texture is magnified, one sample per pixel. The box filter is a cascade of exact 2 x 2
means (``box_downsample``), so a parent built from its children's linear pixels
(``parent_from_children``) is bit-identical to the parent rendered from scratch: the API
builds zoomed-out tiles from cached children where it has them (pay once).

Bounded zoom-out (``zoom_out="bounded"``): instead of all s x s sub-samples, each pixel
evaluates one of them, picked by a hash of the pixel's raster address. The cost per tile
is that of a native tile at every zoom; each pixel is an unbiased one-sample estimate of
the supersampled one (its difference is measured by bench/viewport.py).

Coordinates are exact: sub-sample indices are built in int64 and turned into world
positions with one power-of-two scaling (exact) and one division by
``pixels_per_unit`` (correctly rounded), so tile (z, 2^31, -2^31) is as precise as
tile (z, 0, 0).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from worker.contract import MAX_TILE_SIZE, MIN_TILE_SIZE, PLANE_AXES, PLANES
from worker.errors import InvalidParameter
from worker.files import OFFERED
from worker.runtime import Sampler

NATIVE_ZOOM = 6      # one tile pixel == one exemplar pixel
MIN_ZOOM = 2         # 16 exemplar pixels per tile pixel
MAX_ZOOM = 12        # 64x magnification
SUPERSAMPLE_CAP = 4  # at most 4 x 4 sampler calls per output pixel
COORD_LIMIT = 2 ** 36  # |x|, |y|: keeps 2*s*x*size + ... below 2^53 (exact in float64)
TILE_FORMATS = OFFERED["tile"]  # (written by worker.images.write_image)
ZOOM_OUT_MODES = ("supersample", "bounded")


def native_zoom_for(factor: int) -> int:
    """The zoom with one tile pixel per photo pixel for a photo kept at ``factor`` (a power of
    two) x the working resolution: a fit's detail (model/detail.py) shows up to it."""
    return NATIVE_ZOOM + int(factor).bit_length() - 1


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
    if plane not in PLANE_AXES:
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
    if plane not in PLANE_AXES:
        raise InvalidParameter(f"plane must be one of {PLANES}, got {plane!r}")
    axis_u, axis_v, axis_o = PLANE_AXES[plane]
    pts = np.empty((len(v), len(u), 3), dtype=np.float64)
    pts[:, :, axis_u] = u[None, :]
    pts[:, :, axis_v] = v[:, None]
    pts[:, :, axis_o] = offset
    return pts.reshape(-1, 3)


def box_downsample(rgb: np.ndarray, factor: int) -> np.ndarray:
    """Average factor x factor blocks as a cascade of 2 x 2 means, each ``((a + b) + (c + d)) / 4``
    in float32: the same operations whether a parent is rendered whole or built from its
    children's pixels, so both give the same bits.

    rgb : (H, W, C) with H, W divisible by factor (a power of two) -> (H/f, W/f, C) float32.
    """
    if factor & (factor - 1) or factor < 1:
        raise InvalidParameter(f"factor must be a power of two, got {factor}")
    out = np.asarray(rgb, dtype=np.float32)
    while factor > 1:
        top, bottom = out[0::2], out[1::2]
        out = ((top[:, 0::2] + top[:, 1::2]) + (bottom[:, 0::2] + bottom[:, 1::2])) * np.float32(0.25)
        factor //= 2
    return out


def parent_from_children(children: list[list[np.ndarray]]) -> np.ndarray:
    """Parent tile (z, x, y) from its four children (z + 1, 2x + i, 2y + j) as
    ``children[j][i]``, each (size, size, 3) float32 linear: bit-identical to rendering the
    parent when ``NATIVE_ZOOM - log2(SUPERSAMPLE_CAP) <= z < NATIVE_ZOOM`` (``exact_parent``)."""
    mosaic = np.concatenate([np.concatenate(row, axis=1) for row in children], axis=0)
    return box_downsample(mosaic, 2)


def exact_parent(z: int) -> bool:
    """Whether tile z equals its children downsampled, bit for bit (its sub-sample grid is
    its children's pixel grid and their pixels are themselves exact)."""
    return NATIVE_ZOOM - (SUPERSAMPLE_CAP.bit_length() - 1) <= z < NATIVE_ZOOM


def _pick(cols: np.ndarray, rows: np.ndarray, z: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-sample (a, b) in [0, s)^2 of each pixel (rows x cols), from a hash of its raster
    address and zoom (splitmix64 finaliser, wrapping uint64 arithmetic): deterministic,
    independent of how the raster is cut into tiles or bands."""
    with np.errstate(over="ignore"):
        h = (cols.astype(np.uint64)[None, :] * np.uint64(0x9E3779B97F4A7C15)
             ^ rows.astype(np.uint64)[:, None] * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ np.uint64((z + 64) * 0x165667B19E3779F9 % 2 ** 64))
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    bits = s.bit_length() - 1
    a = (h & np.uint64(s - 1)).astype(np.int64)
    b = ((h >> np.uint64(bits)) & np.uint64(s - 1)).astype(np.int64)
    return a, b


def render_window(sampler: Sampler, code: np.ndarray, seed: int, z: int, col0: int, row0: int,
                  width: int, height: int, *, pixels_per_unit: float, plane: str = "xy",
                  offset: float = 0.0, supersample: int = 1, bounded: bool = False) -> np.ndarray:
    """Linear RGB of any pixel window [col0, col0+width) x [row0, row0+height) of the
    zoom-z raster (tiles are windows aligned on multiples of their size). ``bounded``: one
    hashed sub-sample per pixel instead of the mean of all s x s (module docstring).

    Returns (height, width, 3) float32; identical to the matching pixels of the tiles.
    """
    s = int(supersample)
    limit = COORD_LIMIT * MAX_TILE_SIZE
    if max(abs(col0), abs(row0), abs(col0 + width), abs(row0 + height)) > limit:
        raise InvalidParameter(f"raster coordinates must stay within +-2^46, got {col0}, {row0}")
    u = raster_coords(z, col0, width, pixels_per_unit=pixels_per_unit, supersample=s)
    v = raster_coords(z, row0, height, pixels_per_unit=pixels_per_unit, supersample=s)
    if bounded and s > 1:  # one of the s x s sub-samples per pixel
        a, b = _pick(np.arange(col0, col0 + width, dtype=np.int64), np.arange(row0, row0 + height, dtype=np.int64),
                     z, s)
        pu = u[np.arange(width)[None, :] * s + a]
        pv = v[np.arange(height)[:, None] * s + b]
        axis_u, axis_v, axis_o = PLANE_AXES[plane]
        pts = np.empty((height, width, 3), dtype=np.float64)
        pts[:, :, axis_u], pts[:, :, axis_v], pts[:, :, axis_o] = pu, pv, offset
        return sampler.sample(pts.reshape(-1, 3), code, seed).reshape(height, width, 3)
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
                before_band: Callable[[], None] | None = None, zoom_out: str = "supersample") -> np.ndarray:
    """Linear RGB of tile (z, x, y).

    code : (8,) float32 texture code. pixels_per_unit defaults to ``sampler.pixels_per_unit``
    (a ModelRuntime has one). supersample defaults to ``supersample_for(z)``.
    band_samples : render in bands of whole rows of about this many sampler calls, calling
    ``before_band()`` before each (the API lets small tiles go first there, and stops
    tiles whose client has gone: an exception it raises ends the render).
    zoom_out : ``"supersample"`` (every sub-sample, box-filtered) or ``"bounded"`` (one
    hashed sub-sample per pixel: a native tile's cost at every zoom).
    Returns (size, size, 3) float32 linear 0..1.
    """
    if zoom_out not in ZOOM_OUT_MODES:
        raise InvalidParameter(f"zoom_out must be one of {ZOOM_OUT_MODES}, got {zoom_out!r}")
    ppu = resolve_pixels_per_unit(sampler, pixels_per_unit)
    s = supersample_for(z) if supersample is None else int(supersample)
    _check_tile(z, x, y, size, s, plane)
    bounded = zoom_out == "bounded"
    per_pixel = 1 if bounded else s * s
    rows = size if not band_samples else max(1, min(size, band_samples // (size * per_pixel)))
    out = np.empty((size, size, 3), dtype=np.float32)
    for r0 in range(0, size, rows):
        if before_band is not None:
            before_band()
        n = min(rows, size - r0)
        out[r0:r0 + n] = render_window(sampler, code, seed, z, x * size, y * size + r0, size, n,
                                       pixels_per_unit=ppu, plane=plane, offset=offset, supersample=s,
                                       bounded=bounded)
    return out
