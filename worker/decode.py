"""The one image reader: upload, fit, training and evaluation all decode through ``read_image``,
bring a photo to the model's working resolution through ``resize_short_side`` and cut the
encoder's crops from it with ``encoder_crops`` (an upload's code and a fit's first code alike).

A leaf module: numpy, OpenImageIO, Pillow and the standard library, plus the two other leaves
``worker.errors`` and ``worker.colour`` (neither imports anything of the project), so
``model/`` may import it without reaching the rest of ``worker/`` (onnxruntime,
scikit-image; tests/test_imports.py holds the rule).

Reading goes through OpenImageIO, from a private temporary file (its Python binding has
no in-memory reader). Conventions of what comes out:

* float32 (H, W, 3), **sRGB-encoded** 0..1, RGB order: what the encoder expects.
* The format is recognised from the first bytes (PNG, JPEG, TIFF, EXR, WebP, GIF, BMP),
  never from the file name; anything else is refused.
* Declared width x height (and channel count) are checked against ``max_pixels`` from
  the header, *before* any pixel is decoded (decompression bombs), and so is the aspect
  ratio (at most ``MAX_ASPECT``: a 16 x 1,000,000 strip would be upscaled to gigapixels).
* Decoding goes in bands of scanlines into the one (H, W, 3) float32 output, so a decode
  costs the output plus ~``DECODE_BAND_PIXELS`` pixels. With a ``PixelBudget`` (the API's)
  the outputs of concurrent decodes hold at most that many pixels together: a decode
  waits for room, at most the budget's ``wait_seconds`` and only behind fewer than
  ``max_waiting`` others (else ``Busy``: 503 + Retry-After), and its pixels count until
  the returned array is freed.
* 8/16-bit integer data are normalised by OIIO to 0..1. Float data (EXR, float TIFF)
  are taken as linear light: NaN/inf become 0, values are clipped to 0..1 (no tone
  mapping) and sRGB-encoded.
* Grayscale is replicated to RGB. Alpha is composited over mid grey (sRGB 0.5) in
  encoded values, like a browser showing the picture on a grey page, so transparent
  regions do not become a black or white texture. CMYK JPEG/TIFF are converted to RGB
  by OIIO itself. Animated GIF/WebP: the first frame (subimage 0). EXIF orientation is
  not applied (the pixels as stored).
"""
from __future__ import annotations

import math
import os
import tempfile
import threading
import weakref

import numpy as np
import OpenImageIO as oiio
from PIL import Image

from worker.colour import linear_to_srgb, srgb_to_linear
from worker.errors import Busy, InvalidImage, LimitExceeded

MIN_SIDE = 16             # smaller uploads carry no usable texture
MAX_ASPECT = 16           # long side / short side of an upload (else upscaling explodes)
DECODE_BAND_PIXELS = 1 << 20   # pixels decoded (as float) at a time
RESIZE_DIRECT_PIXELS = 1 << 22  # larger images are box-reduced in bands before resizing
MAX_WORK_PIXELS = 1 << 24       # resize_short_side refuses to produce more pixels than this
MID_GREY = np.float32(0.5)
SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".webp", ".gif", ".bmp")  # names of those formats
_MAGIC = (  # (prefix, offset, extension)
    (b"\x89PNG\r\n\x1a\n", 0, "png"),
    (b"\xff\xd8\xff", 0, "jpg"),
    (b"II*\x00", 0, "tif"),
    (b"MM\x00*", 0, "tif"),
    (b"v/1\x01", 0, "exr"),
    (b"WEBP", 8, "webp"),
    (b"GIF8", 0, "gif"),
    (b"BM", 0, "bmp"),
)


def sniff_format(data: bytes) -> str:
    """File extension for the image format recognised from ``data``'s magic bytes."""
    for magic, offset, ext in _MAGIC:
        if data[offset:offset + len(magic)] == magic and (ext != "webp" or data[:4] == b"RIFF"):
            return ext
    raise InvalidImage("unrecognised image format (expected PNG, JPEG, TIFF, EXR, WebP, GIF or BMP)")


class PixelBudget:
    """A weighted semaphore counted in pixels: ``take(n)`` blocks until n fit (a request
    larger than the whole budget waits until it runs alone), at most ``wait_seconds``
    (None: for ever), and only while fewer than ``max_waiting`` others wait (None: any
    number; each waiter holds a thread and its upload's bytes); else it returns 0."""

    def __init__(self, pixels: int, wait_seconds: float | None = None, max_waiting: int | None = None) -> None:
        self.pixels = int(pixels)
        self.wait_seconds = wait_seconds
        self.max_waiting = max_waiting
        self.used = 0
        self.waiting = 0
        self._cond = threading.Condition()

    def take(self, n: int) -> int:
        """Pixels held (n, capped at the budget), or 0: no room within ``wait_seconds``, or
        ``max_waiting`` others already waiting."""
        n = min(int(n), self.pixels)
        with self._cond:
            if self.used + n > self.pixels:
                if self.max_waiting is not None and self.waiting >= self.max_waiting:
                    return 0
                self.waiting += 1
                try:
                    if not self._cond.wait_for(lambda: self.used + n <= self.pixels, timeout=self.wait_seconds):
                        return 0
                finally:
                    self.waiting -= 1
            self.used += n
        return n

    def give(self, n: int) -> None:
        with self._cond:
            self.used -= n
            self._cond.notify_all()


def read_image(data: bytes, *, max_pixels: int, min_side: int = MIN_SIDE,
               budget: PixelBudget | None = None) -> np.ndarray:
    """Decode an image file's bytes. Returns (H, W, 3) float32 sRGB-encoded 0..1.

    Raises InvalidImage (empty, unknown, truncated, too small, aspect ratio over
    MAX_ASPECT), LimitExceeded (width * height > max_pixels, checked from the header
    before decoding) or Busy (``budget`` had no room within its ``wait_seconds``).
    """
    if not data:
        raise InvalidImage("empty upload (0 bytes)")
    ext = sniff_format(data)
    with tempfile.TemporaryDirectory(prefix="texspace-img-") as tmp:
        path = os.path.join(tmp, "upload." + ext)
        with open(path, "wb") as f:
            f.write(data)
        inp = oiio.ImageInput.open(path)
        if inp is None:
            message = _without(oiio.geterror().strip(), tmp)
            # OIIO's own bomb guards (absolute size; size claimed vs file size) fired first.
            if ("exceeds" in message and "limit" in message) or "header claims" in message:
                raise LimitExceeded("image too large: " + " ".join(message.splitlines()[:2]))
            raise InvalidImage(f"cannot read {ext} image: {message or 'corrupt header'}")
        try:
            spec = inp.spec()
            w, h, c = spec.width, spec.height, spec.nchannels
            if spec.depth > 1:
                raise InvalidImage("volume images are not accepted as exemplars")
            if w * h > max_pixels:
                raise LimitExceeded(f"image is {w}x{h} = {w * h} pixels, limit is {max_pixels}")
            if min(w, h) < min_side:
                raise InvalidImage(f"image is {w}x{h}; both sides must be at least {min_side} pixels")
            if max(w, h) > MAX_ASPECT * min(w, h):
                raise InvalidImage(f"image is {w}x{h}; the long side may be at most {MAX_ASPECT} "
                                   "times the short side")
            if not 1 <= c <= 16:
                raise InvalidImage(f"unsupported channel count {c}")
            held = _take(budget, w * h) if budget is not None else 0
            try:
                out = _decode_bands(inp, ext, spec, tmp)
            except BaseException:
                if held:
                    budget.give(held)
                raise
            if held:
                weakref.finalize(out, budget.give, held)
        finally:
            inp.close()
    return out


def _take(budget: PixelBudget, pixels: int) -> int:
    held = budget.take(pixels)
    if not held:
        wait = budget.wait_seconds or 0.0
        raise Busy(f"other uploads are being decoded: no room for {pixels} more pixels within {wait:g} s, "
                   f"or {budget.max_waiting} uploads already waiting (TEXSPACE_DECODE_BUDGET_PIXELS)",
                   retry_after=max(1, math.ceil(wait)))
    return held


def _without(message: str, folder: str) -> str:
    """A decoder's message without our temporary folder: a problem's detail shows no server path."""
    return message.replace(os.path.join(folder, ""), "").replace(folder, "")


def _decode_bands(inp, ext: str, spec, folder: str = "") -> np.ndarray:  # noqa: ANN001 (OIIO objects)
    """Decode in bands of scanlines into one (H, W, 3) float32 sRGB array (``folder``: the
    temporary one the upload was written to, cut out of error messages)."""
    w, h, c = spec.width, spec.height, spec.nchannels
    is_float = spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)
    out = np.empty((h, w, 3), dtype=np.float32)
    rows = max(1, DECODE_BAND_PIXELS // w)
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        band = inp.read_scanlines(0, 0, spec.y + y0, spec.y + y1, 0, 0, c, "float")
        if band is None or inp.has_error:
            raise InvalidImage(f"corrupt or truncated {ext} image: {_without(inp.geterror().strip(), folder)}")
        band = np.asarray(band, dtype=np.float32).reshape(y1 - y0, w, c)
        out[y0:y1] = _to_srgb_rgb(band, is_float, spec.alpha_channel)
    return out


def _to_srgb_rgb(px: np.ndarray, is_float: bool, alpha_channel: int) -> np.ndarray:
    """(H, W, C) decoded values -> (H, W, 3) float32 sRGB-encoded, per the module rules.

    OIIO returns colour premultiplied by alpha (it associates PNG/TIFF alpha on read),
    so compositing over grey is ``rgb + grey * (1 - alpha)``.
    """
    c = px.shape[2]
    if alpha_channel < 0 and c in (2, 4):
        alpha_channel = c - 1   # gray+alpha / RGBA without an explicit alpha tag
    colour = [i for i in range(c) if i != alpha_channel][:3]
    rgb = px[:, :, colour]
    if rgb.shape[2] < 3:
        rgb = np.repeat(rgb[:, :, :1], 3, axis=2)
    if is_float:
        rgb = np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0)
    if 0 <= alpha_channel < c:
        alpha = np.clip(np.nan_to_num(px[:, :, alpha_channel:alpha_channel + 1]), 0.0, 1.0)
        grey = srgb_to_linear(MID_GREY) if is_float else MID_GREY
        rgb = rgb + grey * (1.0 - alpha)
    if is_float:
        rgb = linear_to_srgb(rgb)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32, copy=False)


def working_shape(height: int, width: int, short_side: int) -> tuple[int, int]:
    """(rows, cols) of an image of that size resized so its shorter side is ``short_side``
    (the longer side rounded, never below the shorter)."""
    scale = short_side / min(height, width)
    return max(short_side, round(height * scale)), max(short_side, round(width * scale))


def resize_short_side(image: np.ndarray, short_side: int) -> np.ndarray:
    """Resize (H, W, 3) float32 sRGB 0..1 so min(H, W) == short_side: the model's working
    resolution, for training, fitting, the upload's encoder crops and colour table, and
    evaluation alike.

    Lanczos-3 (Pillow's filter, support widened by the shrink factor): a pass along x, then
    one along y, each clipped to 0..1, as the 8-bit Pillow resize the space was trained
    through does. Another filter is not a detail: the upload path once used scikit-image's
    bilinear resize with a Gaussian pre-blur, and on the validation gravel the VGG Gram error
    between the two 256-px versions of the same photo (1.55) was most of a fit's error
    against it (1.9): the encoder and the fits were judged against a softer photo than the
    one they learnt from. Images over ``RESIZE_DIRECT_PIXELS`` that shrink by 2 or more are
    first box-reduced in bands (bounded memory) to a short side in [short_side,
    2 * short_side)."""
    h, w = image.shape[:2]
    shape = working_shape(h, w, short_side)
    if shape == (h, w):
        return image
    if shape[0] * shape[1] > MAX_WORK_PIXELS:
        raise LimitExceeded(f"resizing {w}x{h} to a short side of {short_side} gives "
                            f"{shape[0] * shape[1]} pixels, limit is {MAX_WORK_PIXELS}")
    factor = min(h, w) // short_side
    if h * w > RESIZE_DIRECT_PIXELS and factor >= 2:
        image = _box_reduce(image, factor)
    out = np.empty(shape + (3,), np.float32)
    for c in range(3):
        channel = Image.fromarray(np.ascontiguousarray(image[..., c], dtype=np.float32))
        across = np.clip(np.asarray(channel.resize((shape[1], channel.height), Image.Resampling.LANCZOS)), 0, 1)
        down = Image.fromarray(across).resize((shape[1], shape[0]), Image.Resampling.LANCZOS)
        out[..., c] = np.clip(np.asarray(down), 0, 1)
    return out


def encoder_crops(image: np.ndarray, *, short_side: int, size: int = 128, grid: int = 3) -> np.ndarray:
    """Crops of an sRGB image for the encoder.

    The image is resized so its shorter side is ``max(short_side, size)`` (the model's
    working resolution: features keep the scale seen in training), then a regular
    ``grid x grid`` lattice of ``size`` crops is taken, first and last flush with the
    borders, evenly spaced between (a side with room for only one crop gives one
    position; duplicates are dropped). Values map 0..1 -> -1..1 (``2x - 1``).

    image : (H, W, 3) float32 sRGB 0..1. Returns (N, 3, size, size) float32, N <= grid^2.
    """
    work = resize_short_side(image, max(short_side, size))
    h, w = work.shape[:2]
    rows = np.unique(np.round(np.linspace(0, h - size, grid)).astype(int))
    cols = np.unique(np.round(np.linspace(0, w - size, grid)).astype(int))
    windows = np.lib.stride_tricks.sliding_window_view(work, (size, size), axis=(0, 1))
    crops = windows[rows[:, None], cols[None, :]]          # (R, C, 3, size, size)
    crops = crops.reshape(-1, 3, size, size)
    return (crops * np.float32(2) - np.float32(1)).astype(np.float32)


def _box_reduce(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean of factor x factor blocks of (H, W, 3) float32, a band of rows at a time
    (trailing rows / columns that fill no whole block are dropped)."""
    h, w = image.shape[0] // factor, image.shape[1] // factor
    out = np.empty((h, w, 3), dtype=np.float32)
    rows = max(1, DECODE_BAND_PIXELS // (w * factor * factor))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        band = image[r0 * factor:r1 * factor, :w * factor]
        out[r0:r1] = band.reshape(r1 - r0, factor, w, factor, 3).mean(axis=(1, 3), dtype=np.float32)
    return out
