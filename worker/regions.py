"""Large 2D renders of the infinite plane: one big image, or a zipped tile pyramid.

The region is the pixel rectangle [x0, x0 + width) x [y0, y0 + height) of the zoom-``z``
raster of ``worker/tiles.py`` (any integers, not tile aligned); its pixel values are
exactly those of the tiles covering it (same sampling and anti-aliasing).

Formats:

* ``tiff``: tiled TIFF (256 x 256 tiles), 16-bit sRGB, zip compression, via OpenImageIO.
* ``exr``: tiled OpenEXR, half-float linear, zip compression, via OpenImageIO.
* ``png``: 8-bit sRGB, written by a streaming encoder (one row of tiles in memory).
* ``pyramid``: a zip of ``{z}/{x}/{y}.png`` tiles of ``size`` pixels for every zoom from
  ``min_zoom`` to ``z`` (the tiles covering the rectangle at each level, each rendered exactly like the tile
  endpoint, so the bytes match it) plus ``tilejson.json`` (TileJSON 3.0.0, xyz scheme,
  plus a ``texspace`` object with the box and tile size).

Rendering goes in blocks of ``BLOCK`` x ``BLOCK`` pixels, one stripe of ``BLOCK`` rows at
a time: memory is O(BLOCK * width). Progress after every stripe (pyramid: every tile
row); ``should_cancel()`` before each.
"""
from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import OpenImageIO as oiio

from worker.colour import linear_to_srgb, linear_to_srgb8
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.files import atomic_output
from worker.images import write_image
from worker.runtime import Sampler
from worker.tiles import (MAX_ZOOM, MIN_ZOOM, render_tile, render_window,
                          resolve_pixels_per_unit, supersample_for)
from worker.volume_writers import PngStream

FORMATS = ("tiff", "exr", "png", "pyramid")
_EXT = {"tiff": ".tif", "exr": ".exr", "png": ".png", "pyramid": ".zip"}
_ZIP_TIME = (2020, 1, 1, 0, 0, 0)
BLOCK = 256                  # pixels per side of one sampler call / one TIFF or EXR tile


@dataclass(frozen=True)
class RegionLimits:
    max_pixels: int = 16384 * 16384     # single image (tiff, exr, png)
    max_tiles: int = 4096               # pyramid, all levels together


def _pyramid_levels(z: int, min_zoom: int, tiles: tuple[int, int, int, int]):
    """[(level, tx0, ty0, tx1, ty1)]: tiles covering the zoom-z tile box at each level."""
    x0, y0, x1, y1 = tiles
    levels = []
    for level in range(min_zoom, z + 1):
        f = 2 ** (z - level)
        levels.append((level, x0 // f, y0 // f, -(-x1 // f), -(-y1 // f)))
    return levels


def pyramid_tile_count(z: int, min_zoom: int, x0: int, y0: int, width: int, height: int, size: int) -> int:
    """Tiles of a pyramid of the region, all levels together (what ``max_tiles`` bounds)."""
    return sum((xb - xa) * (yb - ya) for _, xa, ya, xb, yb in
               _pyramid_levels(z, min_zoom, _tile_box(x0, y0, width, height, size)))


def _tile_box(x0: int, y0: int, width: int, height: int, size: int) -> tuple[int, int, int, int]:
    """(tx0, ty0, tx1, ty1): the size-pixel tiles covering the pixel rectangle."""
    return x0 // size, y0 // size, -(-(x0 + width) // size), -(-(y0 + height) // size)


def render_region(sampler: Sampler, code: np.ndarray, seed: int, *, z: int, x0: int, y0: int,
                  width: int, height: int, fmt: str = "png", out_path: str | os.PathLike,
                  size: int = 256, min_zoom: int | None = None, plane: str = "xy",
                  offset: float = 0.0, pixels_per_unit: float | None = None,
                  limits: RegionLimits = RegionLimits(),
                  progress: Callable[[float], None] | None = None,
                  should_cancel: Callable[[], bool] | None = None) -> Path:
    """Render pixels [x0, x0+width) x [y0, y0+height) of zoom z into ``out_path``.

    fmt : png | tiff | exr (one image) or pyramid (zip of ``size`` tiles, see module doc).
    Returns the final path, written atomically.
    """
    if fmt not in FORMATS:
        raise InvalidParameter(f"region format must be one of {FORMATS}, got {fmt!r}")
    if not MIN_ZOOM <= z <= MAX_ZOOM:
        raise InvalidParameter(f"zoom {z} outside [{MIN_ZOOM}, {MAX_ZOOM}]")
    if width < 1 or height < 1:
        raise InvalidParameter("width and height must be positive")
    ppu = resolve_pixels_per_unit(sampler, pixels_per_unit)

    def check_cancel():
        if should_cancel is not None and should_cancel():
            raise Canceled("region job canceled")

    out_path = Path(out_path)
    with atomic_output(out_path, suffix=_EXT[fmt]) as tmp:
        if fmt == "pyramid":
            low = MIN_ZOOM if min_zoom is None else int(min_zoom)
            if not MIN_ZOOM <= low <= z:
                raise InvalidParameter(f"min_zoom must be in [{MIN_ZOOM}, {z}]")
            levels = _pyramid_levels(z, low, _tile_box(x0, y0, width, height, size))

            def tile(level, x, y):
                return render_tile(sampler, code, seed, level, x, y, size, pixels_per_unit=ppu,
                                   plane=plane, offset=offset)

            _write_pyramid(tmp, levels, tile, size, z, progress, check_cancel, limits)
        else:
            if width * height > limits.max_pixels:
                raise LimitExceeded(f"region of {width}x{height} pixels exceeds {limits.max_pixels}")
            s = supersample_for(z)
            starts = range(y0, y0 + height, BLOCK)

            def stripes():
                for i, row in enumerate(starts):
                    check_cancel()
                    rows = min(BLOCK, y0 + height - row)
                    yield np.concatenate([
                        render_window(sampler, code, seed, z, col, row, min(BLOCK, x0 + width - col),
                                      rows, pixels_per_unit=ppu, plane=plane, offset=offset,
                                      supersample=s)
                        for col in range(x0, x0 + width, BLOCK)], axis=1)
                    if progress is not None:
                        progress((i + 1) / len(starts))

            _write_image_stripes(tmp, fmt, width, height, stripes())
    return out_path


def _write_image_stripes(path: str, fmt: str, width: int, height: int, stripes) -> None:
    """Write (BLOCK, width, 3) linear stripes (last may be shorter) as one PNG / TIFF / EXR."""
    if fmt == "png":
        with open(path, "wb") as f:
            png = PngStream(f, width, height)
            for stripe in stripes:
                png.write_rows(linear_to_srgb8(stripe))
            png.close()
        return
    spec = oiio.ImageSpec(width, height, 3, "uint16" if fmt == "tiff" else "half")
    spec.attribute("compression", "zip")
    spec.tile_width = spec.tile_height = BLOCK
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise OSError(f"OpenImageIO cannot open {path}: {oiio.geterror()}")
    try:
        for k, stripe in enumerate(stripes):
            pixels = (linear_to_srgb(stripe) * 65535 + 0.5).astype(np.uint16) if fmt == "tiff" \
                else stripe.astype(np.float16)
            y = k * BLOCK
            if not out.write_tiles(0, width, y, y + len(stripe), 0, 1, np.ascontiguousarray(pixels)):
                raise OSError(f"OpenImageIO failed writing rows {y}..{y + len(stripe)}: {out.geterror()}")
    finally:
        out.close()


def _write_pyramid(path, levels, tile, size, zoom, progress, check_cancel, limits) -> None:
    total = sum((xb - xa) * (yb - ya) for _, xa, ya, xb, yb in levels)
    if total > limits.max_tiles:
        raise LimitExceeded(f"pyramid of {total} tiles exceeds the limit of {limits.max_tiles}")
    done = 0
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:   # PNGs are compressed
        for level, xa, ya, xb, yb in levels:
            for y in range(ya, yb):
                check_cancel()
                for x in range(xa, xb):
                    info = zipfile.ZipInfo(f"{level}/{x}/{y}.png", _ZIP_TIME)
                    z.writestr(info, write_image(tile(level, x, y), "png"))
                done += xb - xa
                if progress is not None:
                    progress(done / total)
        meta = {"tilejson": "3.0.0", "scheme": "xyz", "tiles": ["{z}/{x}/{y}.png"],
                "minzoom": levels[0][0], "maxzoom": zoom,
                "texspace": {"zoom": zoom, "tile_size": size,
                             "levels": [list(lv) for lv in levels]}}
        z.writestr(zipfile.ZipInfo("tilejson.json", _ZIP_TIME), json.dumps(meta, indent=1))
