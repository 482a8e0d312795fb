"""Image I/O: decoding uploads, encoding outputs.

Reading (``read_image``) is ``worker/decode.py``'s, the one reader that fitting,
training and evaluation use too (its docstring gives the conventions: float32 (H, W, 3)
sRGB-encoded 0..1, format from the bytes, limits checked from the header). This module
adds the process's decode budget: with ``set_decode_budget`` (the API) the outputs of
concurrent decodes hold at most that many pixels together; a decode waits for room at
most ``wait_seconds`` behind at most ``max_waiting`` others, else it raises ``Busy``
(503 + Retry-After): a waiting upload holds a threadpool thread and its bytes.

What happens to a photo between the two (its working resolution, evened lighting, the
encoder's crops, its code and colour table) is ``worker.photo``'s and ``worker.encode``'s.

Writing (``write_image``) takes *linear* float RGB (the sampler's output) and returns
bytes, its colour encoded first, then the file: PNG / WebP / JPEG are 8-bit sRGB (PNG:
``png_bytes``, Up filter + fast deflate; WebP / JPEG: Pillow; in memory, no metadata), EXR
is half float linear (OIIO, zip), TIFF is 16-bit sRGB (OIIO, zip). No timestamps are
written, so the same pixels always give the same bytes.
"""
from __future__ import annotations

import io
import os
import struct
import tempfile
import zlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import OpenImageIO as oiio
from PIL import Image
from skimage.transform import resize

from worker import decode
from worker.colour import linear_to_srgb, linear_to_srgb8, srgb_to_linear
from worker.decode import MIN_SIDE, PixelBudget
from worker.errors import InvalidParameter
from worker.files import IMAGE_DATETIME

OUTPUT_FORMATS = ("png", "webp", "jpeg", "exr", "tiff")
_budget: PixelBudget | None = None


def set_decode_budget(pixels: int | None, wait_seconds: float | None = None,
                      max_waiting: int | None = None) -> None:
    """Bound the pixels that this process's live decoded images hold together (None: no
    bound); a decode waits at most ``wait_seconds`` for room (None: for ever) behind at most
    ``max_waiting`` others (None: any number), else raises Busy. The API sets it
    (TEXSPACE_DECODE_BUDGET_PIXELS, _DECODE_WAIT_SECONDS, _DECODE_MAX_WAITING); code that
    keeps several decoded images alive at once must not (it would wait on itself)."""
    global _budget
    _budget = PixelBudget(pixels, wait_seconds, max_waiting) if pixels else None


def read_image(data: bytes, *, max_pixels: int, min_side: int = MIN_SIDE) -> np.ndarray:
    """``worker.decode.read_image`` under this process's decode budget. Returns (H, W, 3)
    float32 sRGB-encoded 0..1; raises InvalidImage, LimitExceeded or Busy."""
    return decode.read_image(data, max_pixels=max_pixels, min_side=min_side, budget=_budget)


def write_image(rgb: np.ndarray, fmt: str, *, colour: str = "linear", quality: int = 90) -> bytes:
    """Encode an image to bytes.

    rgb : (H, W, 3) float32, linear light 0..1 (``colour='linear'``, the sampler's output)
    or already sRGB-encoded (``colour='srgb'``, e.g. an uploaded exemplar).
    fmt : png | webp | jpeg | exr | tiff (see module docstring for bit depths).
    """
    if fmt not in OUTPUT_FORMATS:
        raise InvalidParameter(f"format must be one of {OUTPUT_FORMATS}, got {fmt!r}")
    if colour not in ("linear", "srgb"):
        raise InvalidParameter(f"colour must be 'linear' or 'srgb', got {colour!r}")
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InvalidParameter(f"rgb must be (H, W, 3), got {rgb.shape}")
    if fmt == "exr":  # half float linear
        pixels = rgb if colour == "linear" else srgb_to_linear(rgb)
    elif fmt == "tiff":  # 16-bit sRGB
        srgb = linear_to_srgb(rgb) if colour == "linear" else np.clip(rgb, 0, 1)
        pixels = (srgb * 65535 + 0.5).astype(np.uint16)
    elif colour == "linear":  # 8-bit sRGB
        pixels = linear_to_srgb8(rgb)
    else:
        pixels = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    if fmt == "exr":
        return _write_oiio(pixels, "exr", "half", {"compression": "zip"})
    if fmt == "tiff":
        return _write_oiio(pixels, "tif", "uint16", {"compression": "zip", "oiio:ColorSpace": "sRGB"})
    if fmt == "png":
        return png_bytes(pixels)
    buf = io.BytesIO()
    pil = Image.fromarray(pixels, "RGB")
    if fmt == "webp":
        pil.save(buf, "WEBP", quality=quality, method=4)
    else:
        pil.save(buf, "JPEG", quality=quality, optimize=False)
    return buf.getvalue()


def _zlib_in_parts(data: np.ndarray, parts: int) -> bytes:
    """One zlib stream (level 1, run-length strategy) of ``data``, its parts deflated on
    ``parts`` threads (zlib releases the GIL). Each part but the last ends with a sync
    flush (byte-aligned, not final), so the raw streams concatenate into one; run-length
    matches reach back one byte, so the split costs a few bytes, not compression."""
    bounds = np.linspace(0, len(data), parts + 1).astype(int)

    def deflate(i: int) -> bytes:
        compressor = zlib.compressobj(1, zlib.DEFLATED, -15, 9, zlib.Z_RLE)
        last = i == parts - 1
        return (compressor.compress(data[bounds[i]:bounds[i + 1]])
                + compressor.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH))

    if parts == 1:
        pieces = [deflate(0)]
    else:
        with ThreadPoolExecutor(parts, thread_name_prefix="png") as pool:
            pieces = list(pool.map(deflate, range(parts)))
    header = b"\x78\x01"                                            # deflate, 32 KiB window, fastest
    return header + b"".join(pieces) + struct.pack(">I", zlib.adler32(data))


def png_bytes(pixels: np.ndarray, parts: int = 2, text: dict[str, str] | None = None) -> bytes:
    """(H, W, 3) RGB or (H, W) grey, uint8 or uint16 -> PNG bytes: every row with the Up
    filter (numpy, one subtraction) and zlib level 1 with the run-length strategy,
    deflated in ``parts`` pieces at once (images of 2^18 pixels or more). The bench mesh's 2048^2 atlas, one part: 0.1 s and
    4.2 MB, against Pillow's adaptive filters 0.44 s / 4.1 MB at level 1, 0.95 s / 3.9 MB
    at level 3, 2.6 s / 3.6 MB at level 6 (same image, same run; docs/PERFORMANCE.md).
    A 256^2 tile: 2 ms against Pillow's 8-15 ms at level 6, 1-5% more bytes (textures
    are noise to deflate: level 6 saved no more than that). ``text``: {keyword: value}
    written as ``tEXt`` chunks before the pixels (Latin-1)."""
    if pixels.dtype not in (np.uint8, np.uint16) or pixels.shape[2:] not in ((), (3,)) or pixels.ndim < 2:
        raise InvalidParameter(f"png_bytes takes (H, W) or (H, W, 3) uint8 or uint16, got {pixels.shape} {pixels.dtype}")
    h, w = pixels.shape[:2]
    # samples big-endian, as PNG stores them; the Up filter works on bytes, whatever the depth
    rows = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder(">")).view(np.uint8).reshape(h, -1)
    filtered = np.empty((h, rows.shape[1] + 1), dtype=np.uint8)
    filtered[:, 0] = 2                                               # filter type Up
    filtered[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])          # uint8 wraps, as PNG wants
    data = _zlib_in_parts(filtered.reshape(-1), parts if h * w >= 1 << 18 else 1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    depth, colour_type = 8 * pixels.dtype.itemsize, 2 if pixels.ndim == 3 else 0  # RGB or grey
    header = struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, 0)  # no interlace
    notes = b"".join(chunk(b"tEXt", key.encode("latin-1") + b"\0" + value.encode("latin-1"))
                     for key, value in (text or {}).items())
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + notes + chunk(b"IDAT", data)
            + chunk(b"IEND", b""))


def _write_oiio(pixels: np.ndarray, ext: str, dtype: str, attrs: dict[str, str]) -> bytes:
    """Write (H, W, 3) pixels through OIIO to a temp file and return its bytes."""
    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, dtype)
    spec.attribute("DateTime", IMAGE_DATETIME)
    for key, value in attrs.items():
        spec.attribute(key, value)
    with tempfile.TemporaryDirectory(prefix="texspace-out-") as tmp:
        path = os.path.join(tmp, "image." + ext)
        write_oiio_file(path, pixels, spec)
        with open(path, "rb") as f:
            return f.read()


def write_oiio_file(path: str, pixels: np.ndarray, spec: oiio.ImageSpec) -> None:
    """Write one image with OIIO; raise OSError with OIIO's message on failure."""
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise OSError(f"OpenImageIO cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(np.ascontiguousarray(pixels))
    out.close()
    if not ok:
        raise OSError(f"OpenImageIO failed writing {path}: {out.geterror()}")


def thumbnail(image: np.ndarray, *, max_side: int = 256, fmt: str = "webp") -> bytes:
    """Small preview of an sRGB exemplar (H, W, 3) float32: longest side <= max_side."""
    h, w = image.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    if scale < 1.0:
        shape = (max(1, round(h * scale)), max(1, round(w * scale)), 3)
        image = resize(image, shape, order=1, anti_aliasing=True, preserve_range=True)
    return write_image(image.astype(np.float32), fmt, colour="srgb")
