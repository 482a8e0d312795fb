"""Large 2D renders of the infinite plane: one big image, or a zipped tile pyramid.

The region is the pixel rectangle [x0, x0 + width) x [y0, y0 + height) of the zoom-``z``
raster of ``worker/tiles.py`` (any integers, not tile aligned); its pixel values are
exactly those of the tiles covering it (same sampling and anti-aliasing).

Formats:

* ``tiff``: scanline (strip) TIFF, 16-bit sRGB, zip compression, via OpenImageIO.
* ``exr``: tiled OpenEXR, half-float linear, zip compression, via OpenImageIO.
* ``png``: 8-bit sRGB, written by a streaming encoder (one row of tiles in memory).
* ``pyramid``: a zip of ``{z}/{x}/{y}.png`` tiles of ``size`` pixels for every zoom from
  ``min_zoom`` to ``z`` (the tiles covering the rectangle at each level, each rendered exactly like the tile
  endpoint, so the bytes match it) plus ``tilejson.json`` (TileJSON 3.0.0, xyz scheme,
  plus a ``texspace`` object with the box and tile size).
* ``dds`` / ``ktx2``: mipmapped GPU textures (BC1 or, ``dds_compression="bc7"``, BC7 blocks / Basis
  Universal UASTC) with the full mip chain
  averaged in linear light (``worker/gpu_textures.py``).

Derived maps (``maps``: any of ``height``, ``normal``, ``roughness``, ``ao``,
``worker/derived_maps.py``): the result is then a zip of ``<stem>_basecolor.<ext>`` (the
image in ``fmt``) plus ``<stem>_<map>.png`` for each, ``<stem>`` being the result file's own
(``worker.files.member_stem``); ``wrap_maps=True`` (a tileable region) makes the maps'
gradients and blurs wrap around the borders. GPU formats and derived maps need the whole image in memory, so
they are limited to ``RegionLimits.max_whole_pixels``.

Tileable (``tileable=True``): a square image on the xy plane, rendered by the texture's
tileable sampler with period ``width / (pixels_per_unit * 2^(z - NATIVE_ZOOM))`` world units
(the image's width at its zoom: above the native zoom, the same texture in more pixels), so
the image repeats exactly: tiled 2 x 2 it has no seam (the column after the last
is the first). The sampler rounds each octave's frequency so that a whole number of its
cells spans the period (``TextureField.periodic_lattice``): coarse octaves move most, and
small images most (at 256 x 256 the coarsest octaves keep few cells per period).

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
from worker.derived_maps import DEFAULT_NORMAL_STRENGTH, MAP_NAMES, MAX_WHOLE_PIXELS, derived_map_files
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.files import IMAGE_DATETIME, OFFERED, ZIP_TIME, atomic_output, extension, member_name, member_stem
from worker.gpu_textures import GPU_FORMATS, check_gpu_options, gpu_texture_bytes
from worker.images import write_image
from worker.runtime import Sampler, periodic_sampler
from worker.tiles import (MAX_ZOOM, MIN_ZOOM, NATIVE_ZOOM, render_tile, render_window,
                          resolve_pixels_per_unit, supersample_for)
from worker.volume_writers import PngStream

REGION_FORMATS = OFFERED["region"]
BLOCK = 256                  # pixels per side of one sampler call / one EXR tile


@dataclass(frozen=True)
class RegionLimits:
    max_pixels: int = 16384 * 16384     # single image (tiff, exr, png)
    max_tiles: int = 4096               # pyramid, all levels together
    max_whole_pixels: int = MAX_WHOLE_PIXELS   # dds, ktx2 or derived maps: one array in memory


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
                  maps: tuple[str, ...] = (), normal_strength: float = DEFAULT_NORMAL_STRENGTH,
                  wrap_maps: bool = False, tileable: bool = False, dds_compression: str = "bc1",
                  limits: RegionLimits = RegionLimits(),
                  progress: Callable[[float], None] | None = None,
                  should_cancel: Callable[[], bool] | None = None) -> Path:
    """Render pixels [x0, x0+width) x [y0, y0+height) of zoom z into ``out_path``.

    fmt : png | tiff | exr | dds | ktx2 (one image) or pyramid (zip of ``size`` tiles, see
    module doc). maps : derived maps to add (the result is then a zip, see module doc).
    tileable : the image repeats seamlessly (module doc): needs plane xy,
    width == height, a single image, and a tileable sampler (a ``ModelRuntime`` or a
    ``SamplerSession`` of sampler_tileable.onnx); derived maps then wrap too.
    dds_compression : bc1 or bc7, for ``fmt="dds"`` (``worker/gpu_textures.py``).
    Returns the final path, written atomically.
    """
    if fmt not in REGION_FORMATS:
        raise InvalidParameter(f"region format must be one of {REGION_FORMATS}, got {fmt!r}")
    if maps and fmt == "pyramid":
        raise InvalidParameter("derived maps come with a single image, not a pyramid")
    check_gpu_options(fmt if fmt in GPU_FORMATS else None, dds_compression)
    if set(maps) - set(MAP_NAMES):
        raise InvalidParameter(f"unknown derived maps {sorted(set(maps) - set(MAP_NAMES))}; choose from {MAP_NAMES}")
    if not MIN_ZOOM <= z <= MAX_ZOOM:
        raise InvalidParameter(f"zoom {z} outside [{MIN_ZOOM}, {MAX_ZOOM}]")
    if width < 1 or height < 1:
        raise InvalidParameter("width and height must be positive")
    ppu = resolve_pixels_per_unit(sampler, pixels_per_unit)
    if tileable:
        check_tileable(z=z, width=width, height=height, fmt=fmt, plane=plane)
        # one period across the image: its width in world units at this zoom
        sampler, wrap_maps = periodic_sampler(sampler, width / (ppu * 2.0 ** (z - NATIVE_ZOOM))), True

    def check_cancel():
        if should_cancel is not None and should_cancel():
            raise Canceled("region job canceled")

    out_path = Path(out_path)
    with atomic_output(out_path, suffix=extension(fmt)) as tmp:
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

            if maps or fmt in GPU_FORMATS:
                if width * height > limits.max_whole_pixels:
                    raise LimitExceeded(f"{fmt} or derived maps of {width}x{height} pixels exceed "
                                        f"{limits.max_whole_pixels} pixels")
                image = np.concatenate(list(stripes()), axis=0)
                _write_whole(tmp, fmt, image, maps, normal_strength, wrap_maps, member_stem(out_path),
                             dds_compression)
            else:
                _write_image_stripes(tmp, fmt, width, height, stripes())
    return out_path


def check_tileable(*, z: int, width: int, height: int, fmt: str, plane: str) -> None:
    """InvalidParameter unless a tileable region can be made of these arguments: the
    sampler has one period for x and y (square image) on plane xy; any zoom (above the
    native one, more pixels for the same period's worth of texture)."""
    if width != height:
        raise InvalidParameter(f"a tileable region must be square (one period for x and y), got {width}x{height}")
    if plane != "xy":
        raise InvalidParameter(f"a tileable region lies in the xy plane (the one the period wraps), not {plane}")
    if fmt == "pyramid":
        raise InvalidParameter("a tileable region is one image, not a pyramid")


def _write_whole(path: str, fmt: str, image: np.ndarray, maps, strength: float, wrap: bool, stem: str,
                 dds_compression: str = "bc1") -> None:
    """One image in memory: a GPU texture, or the zip of the colour image and its maps
    (members named after ``stem``)."""
    files = derived_map_files(image, maps, strength=strength, wrap=wrap, stem=stem)   # checks maps first
    if not maps:
        with open(path, "wb") as f:
            f.write(gpu_texture_bytes(image, fmt, dds_compression))
        return
    if fmt in GPU_FORMATS:
        colour = gpu_texture_bytes(image, fmt, dds_compression)
    else:
        colour_path = f"{path}.colour{extension(fmt)}"
        try:
            _write_image_stripes(colour_path, fmt, image.shape[1], image.shape[0],
                                 (image[y:y + BLOCK] for y in range(0, image.shape[0], BLOCK)))
            with open(colour_path, "rb") as f:
                colour = f.read()
        finally:
            if os.path.exists(colour_path):
                os.unlink(colour_path)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:   # PNG/EXR/TIFF compress
        colour_name = member_name(stem, "basecolor", extension(fmt))
        for name, data in {colour_name: colour, **files}.items():
            method = zipfile.ZIP_DEFLATED if fmt in GPU_FORMATS and name == colour_name else zipfile.ZIP_STORED
            z.writestr(zipfile.ZipInfo(name, ZIP_TIME), data, compress_type=method)


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
    spec.attribute("DateTime", IMAGE_DATETIME)
    if fmt == "exr":
        spec.tile_width = spec.tile_height = BLOCK
    # TIFF stays in strips: Blender 3.4 (Debian 12) shows a tiled 16-bit TIFF as coloured
    # stripes, and every TIFF reader knows strips
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise OSError(f"OpenImageIO cannot open {path}: {oiio.geterror()}")
    try:
        for k, stripe in enumerate(stripes):
            y = k * BLOCK
            if fmt == "tiff":
                pixels = (linear_to_srgb(stripe) * 65535 + 0.5).astype(np.uint16)
                written = out.write_scanlines(y, y + len(stripe), 0, np.ascontiguousarray(pixels))
            else:
                written = out.write_tiles(0, width, y, y + len(stripe), 0, 1,
                                          np.ascontiguousarray(stripe.astype(np.float16)))
            if not written:
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
                    info = zipfile.ZipInfo(f"{level}/{x}/{y}.png", ZIP_TIME)
                    z.writestr(info, write_image(tile(level, x, y), "png"))
                done += xb - xa
                if progress is not None:
                    progress(done / total)
        meta = {"tilejson": "3.0.0", "scheme": "xyz", "tiles": ["{z}/{x}/{y}.png"],
                "minzoom": levels[0][0], "maxzoom": zoom,
                "texspace": {"zoom": zoom, "tile_size": size,
                             "levels": [list(lv) for lv in levels]}}
        z.writestr(zipfile.ZipInfo("tilejson.json", ZIP_TIME), json.dumps(meta, indent=1))
