"""Derived maps of a synthesised texture: a height map and a tangent-space normal map.

They are *derived* from the colour, not synthesised: the texture space models colour
only, so a dark crack is taken as low and a bright bump as high. Good for bump and
parallax detail on stone, bark, plaster; wrong where brightness is not relief (a
painted stripe on a flat wall).

* ``height``: the Rec. 709 luminance of the linear colour, ``Y = 0.2126 R + 0.7152 G +
  0.0722 B``, in 0..1 (1 = high), at the texture's own pixel scale (one height sample per
  colour pixel). No per-image normalisation, so two exports of the same texture agree
  where they overlap. Written as 16-bit greyscale PNG, linear values (no sRGB curve).
* ``normal``: from the height's gradient in pixel units, ``n = normalise(-s dh/dx,
  -s dh/dy, 1)``, x to the right and y **up** (OpenGL / glTF / Blender convention: green
  = +Y; flip the green channel for DirectX / Unreal). ``s`` is ``strength`` (height units
  per pixel step; default ``DEFAULT_NORMAL_STRENGTH``). Central differences; the border
  uses one-sided differences, or wraps around with ``wrap=True`` (tileable textures, so
  the normal map tiles too). Written as 8-bit RGB PNG, ``(n + 1) / 2`` per channel, linear.
  For a bake the gradient is taken in UV space, so the tangent frame is the atlas's u
  (right) and v (up) axes, which is what glTF viewers assume when a mesh has no tangents.
"""
from __future__ import annotations

import numpy as np

from worker.colour import LUMA_709
from worker.errors import InvalidParameter
from worker.files import member_name
from worker.images import png_bytes

DEFAULT_NORMAL_STRENGTH = 4.0
MAX_WHOLE_PIXELS = 4096 * 4096   # images held whole in memory (maps, mip chains): 192 MB float32 RGB
MAP_NAMES = ("height", "normal")


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
        raise InvalidParameter(f"expected an (H, W, 3) image, got shape {rgb.shape}")
    return rgb


def height_map(rgb: np.ndarray) -> np.ndarray:
    """Height from linear colour. rgb : (H, W, 3) float linear 0..1 -> (H, W) float32 0..1."""
    rgb = _check_rgb(rgb)
    return np.clip(np.asarray(rgb, dtype=np.float32) @ LUMA_709, 0.0, 1.0)


def normal_map(height: np.ndarray, strength: float = DEFAULT_NORMAL_STRENGTH,
               wrap: bool = False) -> np.ndarray:
    """Unit tangent-space normals of a height field, OpenGL convention (+Y up).

    height : (H, W) float, rows top to bottom. Returns (H, W, 3) float32, unit length,
    z > 0. ``wrap``: central differences across the border too (periodic images).
    """
    h = np.asarray(height, dtype=np.float32)
    if h.ndim != 2 or min(h.shape) < 1:
        raise InvalidParameter(f"expected an (H, W) height map, got shape {h.shape}")
    if not (np.isfinite(strength) and strength > 0):
        raise InvalidParameter(f"normal strength must be positive, got {strength}")
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


def encode_normals8(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> (H, W, 3) uint8 codes ``round((n + 1) / 2 * 255)``."""
    return np.clip(np.rint((np.asarray(normals) + 1.0) * 127.5), 0, 255).astype(np.uint8)


def decode_normals8(codes: np.ndarray) -> np.ndarray:
    """Inverse of ``encode_normals8`` (up to quantisation): (H, W, 3) float32 in -1..1."""
    return np.asarray(codes, dtype=np.float32) / 127.5 - 1.0


def height_png(height: np.ndarray) -> bytes:
    """16-bit greyscale PNG of a 0..1 height map (linear values)."""
    return png_bytes((np.clip(height, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16))


def normal_png(normals: np.ndarray) -> bytes:
    """8-bit RGB PNG of unit normals (``encode_normals8``)."""
    return png_bytes(encode_normals8(normals))


def map_file(name: str, stem: str = "") -> str:
    """The PNG file name of derived map ``name`` in a result named ``stem``."""
    return member_name(stem, name, ".png") if stem else f"{name}.png"


def derived_map_files(rgb: np.ndarray, maps, *, strength: float = DEFAULT_NORMAL_STRENGTH,
                      wrap: bool = False, stem: str = "") -> dict[str, bytes]:
    """{file name: PNG bytes} for the requested ``maps`` (a subset of MAP_NAMES) of a
    linear (H, W, 3) colour image: ``<stem>_height.png`` and/or ``<stem>_normal.png``
    (``height.png``, ``normal.png`` without a stem)."""
    unknown = set(maps) - set(MAP_NAMES)
    if unknown:
        raise InvalidParameter(f"unknown derived maps {sorted(unknown)}; choose from {MAP_NAMES}")
    if not maps:
        return {}
    height = height_map(rgb)
    files = {}
    if "height" in maps:
        files[map_file("height", stem)] = height_png(height)
    if "normal" in maps:
        files[map_file("normal", stem)] = normal_png(normal_map(height, strength, wrap=wrap))
    return files
