"""The names job results are downloaded under: what a person finds in a downloads folder.

A result is named after its texture, then what it is and how it was made, parts joined by
``_`` (words inside a part by ``-``)::

    oak-planks_region_z6_1024px_seed7_tileable.png
    oak-planks_teapot_bake_2048px_seed0.zip
    oak-planks_volume_128px_seed3.vdb
    oak-planks_sampler.onnx

The texture's part is its name made a slug: a photo's extension dropped (an upload is
named after its file), letters and digits kept, everything else one ``-``, at most
``MAX_SLUG`` characters, the texture id's first 8 characters when nothing is left. The
stored name keeps non-ASCII letters (``béton-brut_...``); the storage key, the worker's
file and its zip members use the ASCII form (``ascii_only=True``), and the download sends both
(``content_disposition``: RFC 6266 ``filename`` and ``filename*``).
"""
from __future__ import annotations

import re
import unicodedata
from urllib.parse import quote

MAX_SLUG = 60
#: extensions an upload's name (its file's name) may end in; dropped from the slug
PHOTO_EXTENSIONS = frozenset({"png", "jpg", "jpeg", "webp", "tif", "tiff", "exr", "bmp", "gif"})
_WORDS = re.compile(r"[^\W_]+")   # letters and digits of any script; '_' separates parts


def slug(text: str | None, fallback: str, *, ascii_only: bool = False) -> str:
    """``text`` as lower-case words joined by ``-``, or ``fallback``; ``ascii_only``: accents
    dropped and other scripts removed (else their letters are kept)."""
    text = unicodedata.normalize("NFKC", text or "")
    stem, dot, ext = text.rpartition(".")
    if dot and stem and ext.lower() in PHOTO_EXTENSIONS:
        text = stem
    if ascii_only:
        text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    words = "-".join(_WORDS.findall(text.lower()))
    return words[:MAX_SLUG].strip("-") or fallback


def content_disposition(filename: str) -> str:
    """``attachment`` with ``filename`` (ASCII) and, for a non-ASCII name, RFC 6266's
    ``filename*`` (UTF-8, percent-encoded), which browsers and clients prefer."""
    folded = "".join(c for c in unicodedata.normalize("NFKD", filename) if not unicodedata.combining(c))
    plain = re.sub(r'[^\x20-\x7e]|["\\]', "_", folded)
    if filename.isascii() and plain == filename:
        return f'attachment; filename="{plain}"'
    return f"attachment; filename=\"{plain}\"; filename*=UTF-8''{quote(filename, safe='')}"


def _texture_part(texture_name: str | None, texture_id: str, ascii_only: bool) -> str:
    return slug(texture_name, texture_id[:8], ascii_only=ascii_only)


def _seed(seed: int) -> str:
    return f"seed{seed}"


def region_name(texture_name: str | None, texture_id: str, *, z: int, width: int, height: int, seed: int,
                plane: str, tileable: bool, ext: str, ascii_only: bool = False) -> str:
    """``<texture>_region_z<z>_<size>px[_<plane>]_seed<seed>[_tileable]<ext>``; size is the
    side of a square, else ``<width>x<height>``."""
    size = f"{width}px" if width == height else f"{width}x{height}px"
    parts = [_texture_part(texture_name, texture_id, ascii_only), "region", f"z{z}", size]
    parts += [plane] if plane != "xy" else []
    parts += [_seed(seed)] + (["tileable"] if tileable else [])
    return "_".join(parts) + ext


def volume_name(texture_name: str | None, texture_id: str, *, resolution: int, seed: int, ext: str,
                ascii_only: bool = False) -> str:
    """``<texture>_volume_<N>px_seed<seed><ext>`` (N voxels per side)."""
    return "_".join([_texture_part(texture_name, texture_id, ascii_only), "volume", f"{resolution}px", _seed(seed)]) + ext


def bake_name(texture_name: str | None, texture_id: str, *, mesh_filename: str, resolution: int, seed: int,
              ext: str, ascii_only: bool = False) -> str:
    """``<texture>_<mesh>_bake_<R>px_seed<seed><ext>``: the mesh's file name too, so bakes of
    one texture onto two meshes (and their zip members, named after the result) differ."""
    mesh = slug(mesh_filename.rpartition(".")[0] or mesh_filename, "mesh", ascii_only=ascii_only)
    return "_".join([_texture_part(texture_name, texture_id, ascii_only), mesh, "bake", f"{resolution}px", _seed(seed)]) + ext


def sampler_name(texture_name: str | None, texture_id: str, ascii_only: bool = False) -> str:
    """``<texture>_sampler.onnx``: a fit's sampler."""
    return f"{_texture_part(texture_name, texture_id, ascii_only)}_sampler.onnx"
