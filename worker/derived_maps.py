"""Derived maps of a synthesised texture: height, tangent-space normal, roughness and
ambient occlusion, estimated from its colour.

They are *derived* from the colour, not synthesised: the texture space models colour
only, so a dark crack is taken as low and a bright bump as high, busy detail as rough.
Good for bump and parallax detail on stone, bark, plaster; wrong where brightness is not
relief (a painted stripe on a flat wall).

* ``height``: the Rec. 709 luminance of the linear colour, ``Y = 0.2126 R + 0.7152 G +
  0.0722 B``, at the texture's own pixel scale (one height sample per colour pixel),
  stretched to the image's own range: ``(Y - min) / (max - min)`` over the image (over the
  covered texels of a bake's atlas, ``mask``), so the 16-bit greyscale PNG uses 0..65535
  (linear values, no sRGB curve). The range, in luminance (0..1), is written into the PNG
  (``tEXt`` chunks ``texspace:height_min`` / ``texspace:height_max``, ``height_png``) and
  reported with the job; ``Y = min + value / 65535 * (max - min)`` undoes it. Two exports
  of one texture therefore differ by their stretch, not in shape.
* ``normal``: from that height's gradient in pixel units, ``n = normalise(-s dh/dx,
  -s dh/dy, 1)``, x to the right and y **up** (OpenGL / glTF / Blender convention: green
  = +Y; flip the green channel for DirectX / Unreal). ``s`` is ``strength``: the height
  map's full range rises ``s`` pixels (default ``DEFAULT_NORMAL_STRENGTH``: mean |xy| of
  0.14-0.46 over the nine validation photos at the working resolution, median 0.25;
  luminance without the stretch at the old default gave 0.04-0.46, concrete 0.04, nearly
  flat). Central differences; the border uses one-sided differences, or wraps around with
  ``wrap=True`` (tileable textures, so the normal map tiles too). Written as 8-bit RGB
  PNG, ``(n + 1) / 2`` per channel, linear. For a bake the gradient is taken in UV space,
  so the tangent frame is the atlas's u (right) and v (up) axes.
* ``roughness``: busy fine detail reads as a rough surface, smooth even colour as a
  smoother one: the local RMS of the high-pass (``FINE_RADIUS`` px box) of the
  square-root luminance over a ``ROUGHNESS_WINDOW`` px box, mapped on a log scale from
  ``ROUGHNESS_RANGE[0]`` (an RMS of ``ROUGHNESS_RMS[0]`` or less) to ``ROUGHNESS_RANGE[1]``
  (``ROUGHNESS_RMS[1]`` or more); not stretched per image, so a glazed tile stays smoother
  than gravel. Medians over the nine validation photos at the working resolution: concrete
  0.53, floor tiles 0.66, wood 0.78, brick 0.92, granite and gravel 0.95. 8-bit grey PNG,
  linear (glTF's roughness, 0..1).
* ``ao``: ambient occlusion of the height field taken ``AO_DEPTH`` pixels deep over its
  range: at each scale ``r`` of ``AO_RADII`` the mean height of the ``2r + 1`` box around a
  texel gives the elevation ``atan(depth * (mean - h) / r)`` of the horizon around it, a
  hollow's; the highest over the scales is the horizon, and the cosine-weighted sky it
  hides is ``sin^2`` of its elevation: ``ao = cos^2``. 8-bit grey PNG, linear (1 = open sky).
  On the validation photos at the working resolution: mean 0.81 (gravel) to 0.98
  (concrete), 5th percentile 0.30 (floor tiles' grout) to 0.92.

Blurs are separable box filters (``scipy.ndimage.uniform_filter``), wrapping with
``wrap=True``; with a ``mask`` only masked texels are averaged (a bake's atlas: its
background does not darken or brighten the charts' edges).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from worker.colour import LUMA_709
from worker.errors import InvalidParameter
from worker.files import member_name
from worker.images import png_bytes

DEFAULT_NORMAL_STRENGTH = 4.0
MAX_NORMAL_STRENGTH = 100.0
MAX_WHOLE_PIXELS = 4096 * 4096   # images held whole in memory (maps, mip chains): 192 MB float32 RGB
MAP_NAMES = ("ao", "height", "normal", "roughness")
FINE_RADIUS = 2                  # px: the high-pass roughness reads (detail finer than a 5 px box)
ROUGHNESS_WINDOW = 9             # px: the box its local RMS is taken over
ROUGHNESS_RANGE = (0.45, 0.95)   # roughness at and below ROUGHNESS_RMS[0] .. at and above [1]
ROUGHNESS_RMS = (0.004, 0.06)    # sqrt-luminance RMS of fine detail: smooth .. fully rough (log scale)
AO_RADII = (1, 2, 4, 8, 16, 32)  # px: half-widths of the boxes whose mean height is the horizon
AO_DEPTH = 8.0                   # px: how deep the height map's range is taken to be for its AO
HEIGHT_MIN_KEY, HEIGHT_MAX_KEY = "texspace:height_min", "texspace:height_max"
FLAT_RANGE = 1e-6                # a height range below this is a flat image (all 0)


@dataclass
class DerivedMaps:
    """The maps asked for, as arrays: ``height`` (H, W) float32 0..1 (stretched over
    ``height_range``), ``normal`` (H, W, 3) unit vectors, ``roughness`` and ``ao`` (H, W)
    float32 0..1. ``height_range``: (min, max) luminance the height map spans, or None
    when it was not asked for."""
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    height_range: tuple[float, float] | None = None

    def files(self, stem: str = "") -> dict[str, bytes]:
        """{file name (``map_file``): PNG bytes}, in MAP_NAMES order."""
        encoders = {"height": lambda h: height_png(h, self.height_range), "normal": normal_png,
                    "roughness": grey8_png, "ao": grey8_png}
        return {map_file(name, stem): encoders[name](self.arrays[name]) for name in MAP_NAMES if name in self.arrays}


def check_strength(strength: float) -> None:
    if not (np.isfinite(strength) and 0 < strength <= MAX_NORMAL_STRENGTH):
        raise InvalidParameter(f"normal strength must be in (0, {MAX_NORMAL_STRENGTH:g}], got {strength}")


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
        raise InvalidParameter(f"expected an (H, W, 3) image, got shape {rgb.shape}")
    return rgb


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear colour. rgb : (H, W, 3) float linear 0..1 -> (H, W) float32 0..1."""
    rgb = _check_rgb(rgb)
    return np.clip(np.asarray(rgb, dtype=np.float32) @ LUMA_709, 0.0, 1.0)


def height_map(rgb: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Height stretched to 0..1 over the image's (the ``mask``ed texels') luminance range.

    rgb : (H, W, 3) float linear 0..1; mask : (H, W) bool or None. Returns ((H, W) float32
    0..1, (min, max) luminance); a flat image is all 0. Texels outside the mask are clipped.
    """
    y = luminance(rgb)
    inside = y if mask is None or not np.any(mask) else y[np.asarray(mask, bool)]
    low, high = float(inside.min()), float(inside.max())
    if high - low < FLAT_RANGE:
        return np.zeros_like(y), (low, high)
    return np.clip((y - low) / np.float32(high - low), 0.0, 1.0), (low, high)


def normal_map(height: np.ndarray, strength: float = DEFAULT_NORMAL_STRENGTH,
               wrap: bool = False) -> np.ndarray:
    """Unit tangent-space normals of a height field, OpenGL convention (+Y up).

    height : (H, W) float, rows top to bottom. Returns (H, W, 3) float32, unit length,
    z > 0. ``wrap``: central differences across the border too (periodic images).
    """
    h = np.asarray(height, dtype=np.float32)
    if h.ndim != 2 or min(h.shape) < 1:
        raise InvalidParameter(f"expected an (H, W) height map, got shape {h.shape}")
    check_strength(strength)
    if wrap:
        dx = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) * 0.5
        drow = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) * 0.5
    else:
        dx = np.gradient(h, axis=1) if h.shape[1] > 1 else np.zeros_like(h)
        drow = np.gradient(h, axis=0) if h.shape[0] > 1 else np.zeros_like(h)
    # y up = -row, so dh/dy = -dh/drow and n_y = -s dh/dy = +s dh/drow
    n = np.stack([-strength * dx, strength * drow, np.ones_like(h)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def _box_mean(values: np.ndarray, radius: int, wrap: bool, weight: np.ndarray | None) -> np.ndarray:
    """Mean over the (2 radius + 1)^2 box around each texel (of the weighted texels only)."""
    mode, size = ("wrap" if wrap else "reflect"), 2 * radius + 1
    if weight is None:
        return ndimage.uniform_filter(values, size, mode=mode)
    total = ndimage.uniform_filter(values * weight, size, mode=mode)
    return total / np.maximum(ndimage.uniform_filter(weight, size, mode=mode), np.float32(1e-6))


def roughness_map(rgb: np.ndarray, wrap: bool = False, mask: np.ndarray | None = None) -> np.ndarray:
    """Roughness from the colour's fine detail (module doc). (H, W, 3) linear -> (H, W) float32."""
    weight = None if mask is None else np.asarray(mask, np.float32)
    tone = np.sqrt(luminance(rgb))
    fine = tone - _box_mean(tone, FINE_RADIUS, wrap, weight)
    rms = np.sqrt(np.maximum(_box_mean(fine * fine, ROUGHNESS_WINDOW // 2, wrap, weight), 0.0))
    smooth, rough = ROUGHNESS_RMS
    share = np.log(np.maximum(rms, smooth) / smooth) / np.log(rough / smooth)
    low, high = ROUGHNESS_RANGE
    return np.clip(low + (high - low) * share, low, high).astype(np.float32)


def ambient_occlusion(height: np.ndarray, depth: float = AO_DEPTH, wrap: bool = False,
                      mask: np.ndarray | None = None) -> np.ndarray:
    """Ambient occlusion of a 0..1 height field ``depth`` pixels deep over its range
    (module doc). (H, W) -> (H, W) float32, 1 = open sky."""
    h = np.asarray(height, dtype=np.float32)
    weight = None if mask is None else np.asarray(mask, np.float32)
    steepest = np.zeros_like(h)     # tan of the highest horizon seen at any scale
    for radius in AO_RADII:
        np.maximum(steepest, (_box_mean(h, radius, wrap, weight) - h) * np.float32(depth / radius), out=steepest)
    return (1.0 / (1.0 + steepest * steepest)).astype(np.float32)     # 1 - sin^2(atan(t)) = cos^2


def encode_normals8(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> (H, W, 3) uint8 codes ``round((n + 1) / 2 * 255)``."""
    return np.clip(np.rint((np.asarray(normals) + 1.0) * 127.5), 0, 255).astype(np.uint8)


def decode_normals8(codes: np.ndarray) -> np.ndarray:
    """Inverse of ``encode_normals8`` (up to quantisation): (H, W, 3) float32 in -1..1."""
    return np.asarray(codes, dtype=np.float32) / 127.5 - 1.0


def grey8(values: np.ndarray) -> np.ndarray:
    """(H, W) 0..1 -> (H, W) uint8, rounded."""
    return np.clip(np.rint(np.asarray(values) * 255.0), 0, 255).astype(np.uint8)


def height_png(height: np.ndarray, height_range: tuple[float, float] | None = None) -> bytes:
    """16-bit greyscale PNG of a 0..1 height map (linear values), its luminance range in
    ``tEXt`` chunks (``HEIGHT_MIN_KEY``, ``HEIGHT_MAX_KEY``) and a Description saying how to undo it."""
    text = {}
    if height_range is not None:
        low, high = height_range
        text = {HEIGHT_MIN_KEY: f"{low:.9g}", HEIGHT_MAX_KEY: f"{high:.9g}",
                "Description": f"height = {low:.9g} + value / 65535 * {high - low:.9g} "
                               "(Rec. 709 linear luminance of the texture, 0..1)",
                "Software": "texspace"}
    return png_bytes((np.clip(height, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16), text=text)


def read_height_range(png: bytes) -> tuple[float, float] | None:
    """(min, max) luminance stated in a height PNG's ``tEXt`` chunks (``height_png``), or None."""
    text, at = {}, 8
    while at + 8 <= len(png):
        length, kind = struct.unpack_from(">I4s", png, at)
        if kind == b"tEXt":
            key, _, value = png[at + 8:at + 8 + length].partition(b"\0")
            text[key.decode("latin-1")] = value.decode("latin-1")
        if kind in (b"IDAT", b"IEND"):
            break
        at += 12 + length
    try:
        return float(text[HEIGHT_MIN_KEY]), float(text[HEIGHT_MAX_KEY])
    except (KeyError, ValueError):
        return None


def normal_png(normals: np.ndarray) -> bytes:
    """8-bit RGB PNG of unit normals (``encode_normals8``)."""
    return png_bytes(encode_normals8(normals))


def grey8_png(values: np.ndarray) -> bytes:
    """8-bit greyscale PNG of a 0..1 map (linear values: roughness, ambient occlusion)."""
    return png_bytes(grey8(values))


def map_file(name: str, stem: str = "") -> str:
    """The PNG file name of derived map ``name`` in a result named ``stem``."""
    return member_name(stem, name, ".png") if stem else f"{name}.png"


def check_maps(maps) -> None:
    unknown = set(maps) - set(MAP_NAMES)
    if unknown:
        raise InvalidParameter(f"unknown derived maps {sorted(unknown)}; choose from {MAP_NAMES}")


def derived_maps(rgb: np.ndarray, maps, *, strength: float = DEFAULT_NORMAL_STRENGTH, wrap: bool = False,
                 mask: np.ndarray | None = None) -> DerivedMaps:
    """The requested ``maps`` (a subset of MAP_NAMES) of a linear (H, W, 3) colour image.
    ``wrap``: a periodic image (blurs and gradients wrap); ``mask``: (H, W) bool, the texels
    that hold the surface (a bake's atlas), over which the height range and blurs are taken."""
    check_maps(maps)
    check_strength(strength)
    result = DerivedMaps()
    if not maps:
        return result
    rgb = _check_rgb(rgb)
    if mask is not None and not np.any(mask):
        mask = None
    if {"height", "normal", "ao"} & set(maps):
        height, height_range = height_map(rgb, mask)
        if "height" in maps:
            result.arrays["height"], result.height_range = height, height_range
        if "normal" in maps:
            result.arrays["normal"] = normal_map(height, strength, wrap=wrap)
        if "ao" in maps:
            result.arrays["ao"] = ambient_occlusion(height, wrap=wrap, mask=mask)
    if "roughness" in maps:
        result.arrays["roughness"] = roughness_map(rgb, wrap=wrap, mask=mask)
    return result


def derived_map_files(rgb: np.ndarray, maps, *, strength: float = DEFAULT_NORMAL_STRENGTH,
                      wrap: bool = False, stem: str = "", mask: np.ndarray | None = None) -> dict[str, bytes]:
    """{file name: PNG bytes} for the requested ``maps`` of a linear (H, W, 3) colour image:
    ``<stem>_height.png``, ``<stem>_normal.png``, ... (``height.png``, ... without a stem)."""
    return derived_maps(rgb, maps, strength=strength, wrap=wrap, mask=mask).files(stem)
