"""The one image reader: upload, fit, training and evaluation all decode through ``read_image``
(what they do with the pixels next, at the model's working resolution, is ``worker.photo``'s).

A leaf module: numpy, OpenImageIO and the standard library, plus the two other leaves
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

from worker.colour import linear_to_srgb, srgb_to_linear
from worker.errors import Busy, InvalidImage, LimitExceeded

MIN_SIDE = 16             # smaller uploads carry no usable texture
MAX_ASPECT = 16           # long side / short side of an upload (else upscaling explodes)
DECODE_BAND_PIXELS = 1 << 20   # pixels decoded (as float) at a time
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
