"""Large 2D renders of a rectangle of tiles: one big image, or a zipped tile pyramid.

The region is a box of tiles ``(x0, y0, x1, y1)`` (half-open: x0 <= x < x1) at zoom
``zoom`` with tile size ``size``, in the tile convention of ``worker/tiles.py``; pixel
values are exactly those of the corresponding tiles (same sampling and anti-aliasing).

Formats:

* ``tiff``: tiled TIFF (tiles of ``size`` when size is a multiple of 16, else stripes),
  16-bit sRGB, zip compression, via OpenImageIO.
* ``exr``: tiled OpenEXR, half-float linear, zip compression, via OpenImageIO.
* ``png``: 8-bit sRGB, written by a streaming encoder (one row of tiles in memory).
* ``pyramid``: a zip of ``{z}/{x}/{y}.png`` for every zoom from ``min_zoom`` to ``zoom``
  (the tiles covering the box at each level, each rendered exactly like the tile
  endpoint, so the bytes match it) plus ``tilejson.json`` (TileJSON 3.0.0, xyz scheme,
  plus a ``texspace`` object with the box and tile size).

Rendering goes one row of tiles at a time: memory is O(tiles per row * size^2).
Progress after every row; ``should_cancel()`` before every row.
"""
from __future__ import annotations

import json
import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import OpenImageIO as oiio

from worker.colour import linear_to_srgb, linear_to_srgb8
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.images import write_image
from worker.runtime import Sampler
from worker.tiles import MIN_ZOOM, render_tile
from worker.volume_writers import PngStream

FORMATS = ("tiff", "exr", "png", "pyramid")
_EXT = {"tiff": ".tif", "exr": ".exr", "png": ".png", "pyramid": ".zip"}
_ZIP_TIME = (2020, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class RegionLimits:
    max_pixels: int = 16384 * 16384     # single image (tiff, exr, png)
    max_tiles: int = 4096               # pyramid, all levels together


def _pyramid_levels(zoom: int, min_zoom: int, box: tuple[int, int, int, int]):
    """[(z, x0, y0, x1, y1)] tiles covering the box at each zoom from min_zoom to zoom."""
    x0, y0, x1, y1 = box
    levels = []
    for z in range(min_zoom, zoom + 1):
        f = 2 ** (zoom - z)
        levels.append((z, x0 // f, y0 // f, -(-x1 // f), -(-y1 // f)))
    return levels


def render_region(sampler: Sampler, code: np.ndarray, seed: int, *, zoom: int,
                  box: tuple[int, int, int, int], size: int = 256, fmt: str = "tiff",
                  out_path: str | os.PathLike, min_zoom: int | None = None,
                  plane: str = "xy", offset: float = 0.0, pixels_per_unit: float | None = None,
                  limits: RegionLimits = RegionLimits(),
                  progress: Callable[[float], None] | None = None,
                  should_cancel: Callable[[], bool] | None = None) -> Path:
    """Render tiles ``box = (x0, y0, x1, y1)`` at ``zoom`` into ``out_path`` (see module doc)."""
    if fmt not in FORMATS:
        raise InvalidParameter(f"region format must be one of {FORMATS}, got {fmt!r}")
    x0, y0, x1, y1 = map(int, box)
    if x1 <= x0 or y1 <= y0:
        raise InvalidParameter("box must satisfy x1 > x0 and y1 > y0")
    tile_kw = dict(pixels_per_unit=pixels_per_unit, plane=plane, offset=offset)

    def tile(z, x, y):
        return render_tile(sampler, code, seed, z, x, y, size, **tile_kw)

    def check_cancel():
        if should_cancel is not None and should_cancel():
            raise Canceled("region job canceled")

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out_path.parent, prefix=f".{out_path.name}.", suffix=_EXT[fmt])
    os.close(fd)
    try:
        if fmt == "pyramid":
            low = MIN_ZOOM if min_zoom is None else int(min_zoom)
            if not MIN_ZOOM <= low <= zoom:
                raise InvalidParameter(f"min_zoom must be in [{MIN_ZOOM}, {zoom}]")
            levels = _pyramid_levels(zoom, low, (x0, y0, x1, y1))
            _write_pyramid(tmp, levels, tile, size, (x0, y0, x1, y1), zoom, progress, check_cancel,
                           limits)
        else:
            width, height = (x1 - x0) * size, (y1 - y0) * size
            if width * height > limits.max_pixels:
                raise LimitExceeded(f"region of {width}x{height} pixels exceeds {limits.max_pixels}")
            rows = range(y0, y1)

            def stripes():
                for i, y in enumerate(rows):
                    check_cancel()
                    yield np.concatenate([tile(zoom, x, y) for x in range(x0, x1)], axis=1)
                    if progress is not None:
                        progress((i + 1) / len(rows))

            _write_image_stripes(tmp, fmt, width, height, size, stripes())
        os.chmod(tmp, 0o644)
        os.replace(tmp, out_path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return out_path


def _write_image_stripes(path: str, fmt: str, width: int, height: int, size: int, stripes) -> None:
    """Write (size, width, 3) linear stripes top to bottom as one PNG / TIFF / EXR."""
    if fmt == "png":
        with open(path, "wb") as f:
            png = PngStream(f, width, height)
            for stripe in stripes:
                png.write_rows(linear_to_srgb8(stripe))
            png.close()
        return
    spec = oiio.ImageSpec(width, height, 3, "uint16" if fmt == "tiff" else "half")
    spec.attribute("compression", "zip")
    tiled = size % 16 == 0
    if tiled:
        spec.tile_width = spec.tile_height = size
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise OSError(f"OpenImageIO cannot open {path}: {oiio.geterror()}")
    try:
        for k, stripe in enumerate(stripes):
            pixels = (linear_to_srgb(stripe) * 65535 + 0.5).astype(np.uint16) if fmt == "tiff" \
                else stripe.astype(np.float16)
            y = k * size
            ok = (out.write_tiles(0, width, y, y + size, 0, 1, pixels) if tiled
                  else out.write_scanlines(y, y + size, 0, pixels))
            if not ok:
                raise OSError(f"OpenImageIO failed writing rows {y}..{y + size}: {out.geterror()}")
    finally:
        out.close()


def _write_pyramid(path, levels, tile, size, box, zoom, progress, check_cancel, limits) -> None:
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
                "texspace": {"zoom": zoom, "box": list(box), "tile_size": size,
                             "levels": [list(lv) for lv in levels]}}
        z.writestr(zipfile.ZipInfo("tilejson.json", _ZIP_TIME), json.dumps(meta, indent=1))
