"""Streaming writers for 3D texture volumes, one class per output format.

Every writer is fed slabs of whole z-slices in order, ``write(rgb)`` with
``rgb : (nz, N, N, 3) float32 linear``, and keeps nothing but the current slab, so
memory is O(slab) whatever N is. Array order everywhere is [z, y, x, channel]
(slice, row, column), x varying fastest in the files.

Layouts:

* ``npy``: float32 linear, shape (N, N, N, 3), C order. Header written first, slabs
  appended (the file is a valid .npy when closed; ``np.load(..., mmap_mode='r')`` works).
* ``exr``: multi-part OpenEXR, one part per z slice named ``slice_0000``...; float32
  linear RGB, zip compression. Part k holds slice z = k in channels
  ``slice_0000.Combined.R`` / ``.G`` / ``.B``: the layer.pass.channel names of a
  multilayer EXR, so Blender shows one layer per slice (bare ``R``, ``G``, ``B`` in every
  part made Blender 3.4 refuse the file: "too many channels in one pass"). Every part's header carries the
  volume's placement: ``boundsMin``, ``boundsMax``, ``voxelSize`` (v3f, world units; x, y,
  z), ``sliceIndex`` (int k), ``sliceZ`` (float, world z of the slice's voxel centres) and
  ``texspace:volume`` (string, JSON of ``volume_metadata``: the same values in double
  precision, ``resolution``, axis order, colour). OpenEXR has no double attributes.
* ``tiff``: multi-page TIFF, one page per z slice (page k = slice z = k); float32 linear
  RGB, zip compression; each page's ImageDescription is the JSON of ``volume_metadata``.
* ``vdb``: OpenVDB (``worker/vdb.py``): a vec3s grid ``Cd`` (linear RGB) and a float
  grid ``density`` (the colour's linear luminance, what Blender renders a volume by), voxel
  (i, j, k) = x, y, z index, transform ``ScaleTranslateMap`` from the bounds (index
  (i, j, k) maps to the voxel centre). Slabs are spooled to a temporary raw file beside
  the output (VDB stores x-major blocks, the volume arrives z-slice by z-slice) and
  encoded from it on close.
* ``raw``: a zip holding ``volume.raw`` (float32 little-endian linear RGB, [z][y][x][c],
  no header) and ``volume.json`` (shape, dtype, byte order, axis order, bounds, colour).
* ``nrrd``: NRRD 4 header written by hand (sizes ``3 N N N``, kinds
  ``RGB-color domain domain domain``, raw little-endian float32, space directions and
  origin from the bounds) followed by the data: pynrrd, 3D Slicer and ParaView read it.
* ``dds``: DirectDraw Surface volume texture in the legacy DirectX 9 layout: "DDS " +
  DDS_HEADER (DDSD_DEPTH, DDSCAPS2_VOLUME) with an uncompressed 32-bit pixel format
  (DDPF_RGB | DDPF_ALPHAPIXELS, masks R 0xff0000, G 0xff00, B 0xff, A 0xff000000: D3D9's
  A8R8G8B8, bytes B G R A, the layout every reader knows; ImageMagick ignores the masks
  and assumes it), one mip level, then the texels (sRGB-encoded, alpha 255) slice by slice. The
  DX10 header (R8G8B8A8_UNORM_SRGB, TEXTURE3D) it replaces opened in neither OpenImageIO
  nor ImageMagick ("unsupported"); now iinfo shows the N x N x N volume, though
  OpenImageIO and ImageMagick decode only slice 0.
* ``flipbook``: one 8-bit sRGB PNG holding the N slices as a grid of ``cols x rows``
  cells of N x N pixels, ``cols * rows == N`` exactly (cols = the smallest divisor of N
  that is >= sqrt(N)), slice 0 at the top-left, then left to right, top to bottom:
  what Unity's texture importer turns into a Texture3D with "Flipbook Columns/Rows"
  set to cols/rows. Written by a streaming PNG encoder, one grid row (``cols`` slices,
  8-bit) buffered at a time.
"""
from __future__ import annotations

import json
import math
import os
import struct
import zipfile
import zlib

import numpy as np
import OpenImageIO as oiio

from worker.colour import linear_to_srgb8
from worker.files import IMAGE_DATETIME, OFFERED, ZIP_TIME
from worker.vdb import write_vdb

VOLUME_FORMATS = OFFERED["volume"]


def flipbook_grid(n: int) -> tuple[int, int]:
    """(cols, rows) with cols * rows == n, cols the smallest divisor of n >= sqrt(n)."""
    cols = next(c for c in range(math.isqrt(n - 1) + 1 if n > 1 else 1, n + 1) if n % c == 0)
    return cols, n // cols


class VolumeWriter:
    """Base: ``write(rgb slab)`` repeatedly (slices in order), then ``close()``."""

    def __init__(self, path: str, n: int, bounds: np.ndarray):
        self.path, self.n, self.bounds = path, n, bounds

    def write(self, rgb: np.ndarray) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class NpyWriter(VolumeWriter):
    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.file = open(path, "wb")
        header = {"descr": "<f4", "fortran_order": False, "shape": (n, n, n, 3)}
        np.lib.format.write_array_header_1_0(self.file, header)

    def write(self, rgb):
        self.file.write(np.ascontiguousarray(rgb, dtype="<f4").data)

    def close(self):
        self.file.close()


_V3F = oiio.TypeDesc(oiio.BASETYPE.FLOAT, oiio.AGGREGATE.VEC3, oiio.VECSEMANTICS.VECTOR)


def volume_metadata(n: int, bounds: np.ndarray, k: int | None = None) -> dict:
    """What EXR / TIFF pages carry about the volume (slice ``k``'s fields when given)."""
    step = (bounds[1] - bounds[0]) / n
    meta = {"resolution": [n, n, n], "bounds_min": bounds[0].tolist(), "bounds_max": bounds[1].tolist(),
            "voxel_size": step.tolist(), "axes": ["z", "y", "x", "channel"], "colour": "linear"}
    if k is not None:
        meta.update(slice=k, slice_z=float(bounds[0, 2] + (k + 0.5) * step[2]))
    return meta


class OiioPagesWriter(VolumeWriter):
    """Multi-part EXR or multi-page TIFF through OpenImageIO, one subimage per slice."""

    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.specs = []
        exr = str(path).endswith(".exr")
        step = (bounds[1] - bounds[0]) / n
        for k in range(n):
            spec = oiio.ImageSpec(n, n, 3, "float")
            spec.attribute("compression", "zip")
            spec.attribute("name", f"slice_{k:04d}")
            spec.attribute("DateTime", IMAGE_DATETIME)
            if exr:
                spec.channelnames = tuple(f"slice_{k:04d}.Combined.{c}" for c in "RGB")
            meta = volume_metadata(n, bounds, k)
            if exr:   # OpenEXR attributes cannot be doubles: float32 vectors + the exact JSON
                for name, value in (("boundsMin", bounds[0]), ("boundsMax", bounds[1]), ("voxelSize", step)):
                    spec.attribute(name, _V3F, tuple(float(v) for v in value))
                spec.attribute("sliceIndex", k)
                spec.attribute("sliceZ", float(meta["slice_z"]))
                spec.attribute("texspace:volume", json.dumps(meta))
            else:
                spec.attribute("ImageDescription", json.dumps(meta))
            self.specs.append(spec)
        self.out = oiio.ImageOutput.create(path)
        if self.out is None or not self.out.open(path, self.specs):
            raise OSError(f"OpenImageIO cannot open {path}: {oiio.geterror()}")
        self.k = 0

    def write(self, rgb):
        for page in rgb:
            if self.k and not self.out.open(self.path, self.specs[self.k], "AppendSubimage"):
                raise OSError(f"OpenImageIO cannot append slice {self.k}: {self.out.geterror()}")
            if not self.out.write_image(np.ascontiguousarray(page)):
                raise OSError(f"OpenImageIO failed on slice {self.k}: {self.out.geterror()}")
            self.k += 1

    def close(self):
        self.out.close()


def _volume_json(n: int, bounds: np.ndarray) -> dict:
    return {"file": "volume.raw", "shape": [n, n, n, 3], "dtype": "float32", "byte_order": "little",
            "axes": ["z", "y", "x", "channel"], "channels": ["R", "G", "B"], "colour": "linear",
            "bounds_min": bounds[0].tolist(), "bounds_max": bounds[1].tolist()}


class RawZipWriter(VolumeWriter):
    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.zip = zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True)
        info = zipfile.ZipInfo("volume.json", ZIP_TIME)
        self.zip.writestr(info, json.dumps(_volume_json(n, bounds), indent=1))
        self.raw = self.zip.open(zipfile.ZipInfo("volume.raw", ZIP_TIME), "w", force_zip64=True)

    def write(self, rgb):
        self.raw.write(np.ascontiguousarray(rgb, dtype="<f4").data)

    def close(self):
        self.raw.close()
        self.zip.close()


class NrrdWriter(VolumeWriter):
    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        step = (bounds[1] - bounds[0]) / n
        origin = bounds[0] + step / 2   # NRRD's origin is the first sample's centre
        dirs = " ".join(f"({','.join(repr(float(v)) for v in row)})" for row in np.diag(step))
        header = (
            "NRRD0004\n# texspace volume: linear RGB\n"
            "type: float\ndimension: 4\nspace: right-anterior-superior\n"
            f"sizes: 3 {n} {n} {n}\nkinds: RGB-color domain domain domain\n"
            f"space directions: none {dirs}\n"
            f"space origin: ({','.join(repr(float(v)) for v in origin)})\n"
            "endian: little\nencoding: raw\n\n")
        self.file = open(path, "wb")
        self.file.write(header.encode("ascii"))

    def write(self, rgb):
        self.file.write(np.ascontiguousarray(rgb, dtype="<f4").data)

    def close(self):
        self.file.close()


def dds_volume_header(n: int) -> bytes:
    """'DDS ' + DDS_HEADER for an n^3 uncompressed RGBA8 volume, one mip (module doc)."""
    flags = 0x1 | 0x2 | 0x4 | 0x8 | 0x1000 | 0x800000   # CAPS HEIGHT WIDTH PITCH PIXELFORMAT DEPTH
    pixel_format = struct.pack("<2I4s5I", 32, 0x40 | 0x1, b"\0\0\0\0", 32,   # DDPF_RGB | ALPHAPIXELS
                               0xFF0000, 0xFF00, 0xFF, 0xFF000000)
    caps, caps2 = 0x1000 | 0x8, 0x200000                # TEXTURE | COMPLEX, VOLUME
    header = struct.pack("<7I11I", 124, flags, n, n, n * 4, n, 1, *([0] * 11))
    return b"DDS " + header + pixel_format + struct.pack("<5I", caps, caps2, 0, 0, 0)


class DdsWriter(VolumeWriter):
    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.file = open(path, "wb")
        self.file.write(dds_volume_header(n))

    def write(self, rgb):
        rgba = np.empty(rgb.shape[:3] + (4,), dtype=np.uint8)
        rgba[..., 2::-1] = linear_to_srgb8(rgb)          # B G R, then A
        rgba[..., 3] = 255
        self.file.write(rgba.data)

    def close(self):
        self.file.close()


class VdbWriter(VolumeWriter):
    """OpenVDB: slabs are spooled to ``<path>.spool`` (raw float32, [z][y][x][c]) and
    encoded by ``worker.vdb.write_vdb`` from a memory map of it on close."""

    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.spool_path = f"{path}.spool"
        self.spool = open(self.spool_path, "wb")
        self.k = 0

    def write(self, rgb):
        self.spool.write(np.ascontiguousarray(rgb, dtype="<f4").data)
        self.k += len(rgb)

    def close(self):
        try:
            self.spool.close()
            if self.k == self.n:   # a canceled or failed volume is not encoded
                volume = np.memmap(self.spool_path, dtype="<f4", mode="r", shape=(self.n,) * 3 + (3,))
                with open(self.path, "wb") as f:
                    write_vdb(f, volume, self.bounds)
                del volume
        finally:
            if os.path.exists(self.spool_path):
                os.unlink(self.spool_path)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


class PngStream:
    """Minimal streaming 8-bit RGB PNG encoder (sRGB chunk, filter 0, zlib level 6).

    ``write_rows(rows (h, width, 3) uint8)`` in top-to-bottom order, then ``close()``.
    Memory is one batch of rows; output bytes depend only on the pixels.
    """

    def __init__(self, file, width: int, height: int):
        self.file, self.width, self.height, self.rows_done = file, width, height, 0
        ihdr = struct.pack(">2I5B", width, height, 8, 2, 0, 0, 0)
        file.write(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"sRGB", b"\x00"))
        self.zlib = zlib.compressobj(6)

    def write_rows(self, rows: np.ndarray) -> None:
        h = rows.shape[0]
        lines = np.zeros((h, 1 + self.width * 3), dtype=np.uint8)   # column 0: filter type 0
        lines[:, 1:] = rows.reshape(h, -1)
        data = self.zlib.compress(lines.data)
        if data:
            self.file.write(_png_chunk(b"IDAT", data))
        self.rows_done += h

    def close(self) -> None:
        if self.rows_done != self.height:
            raise ValueError(f"PNG got {self.rows_done} rows, header says {self.height}")
        self.file.write(_png_chunk(b"IDAT", self.zlib.flush()) + _png_chunk(b"IEND", b""))


class FlipbookWriter(VolumeWriter):
    """Flipbook PNG. Slices are converted to 8-bit one at a time into a one-grid-row
    buffer (cols * N * N * 3 bytes), which is streamed out as N PNG rows when full."""

    def __init__(self, path, n, bounds):
        super().__init__(path, n, bounds)
        self.cols, self.rows = flipbook_grid(n)
        self.file = open(path, "wb")
        self.png = PngStream(self.file, self.cols * n, self.rows * n)
        self.grid_row = np.empty((n, self.cols, n, 3), dtype=np.uint8)   # [y, col, x, c]
        self.k = 0

    def write(self, rgb):
        for page in rgb:
            self.grid_row[:, self.k % self.cols] = linear_to_srgb8(page)
            self.k += 1
            if self.k % self.cols == 0:
                self.png.write_rows(self.grid_row.reshape(self.n, -1, 3))

    def close(self):
        try:
            self.png.close()
        finally:
            self.file.close()


WRITERS: dict[str, type[VolumeWriter]] = {
    "npy": NpyWriter, "exr": OiioPagesWriter, "tiff": OiioPagesWriter, "raw": RawZipWriter,
    "nrrd": NrrdWriter, "dds": DdsWriter, "flipbook": FlipbookWriter, "vdb": VdbWriter,
}
