"""Result files: the one table of the formats texspace writes (file extension and media
type by format name), the fixed time stamped on zip members and images, and atomic writing (under a
temporary name in the target folder, renamed into place only when complete, so readers
never see half a file and a re-run simply overwrites).

The table also says which formats each output offers (``OFFERED``): the writers, the API's
schema, the CLI and the page (through ``GET /v1/limits``) all read them from here.
"""
from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

#: the time of every zip member: fixed, so identical content gives identical zips
ZIP_TIME = (2020, 1, 1, 0, 0, 0)
#: the same time as the ``DateTime`` of every image OpenImageIO writes (EXR ``capDate``,
#: TIFF DateTime), which it would otherwise stamp with the time of writing
IMAGE_DATETIME = "{:04d}:{:02d}:{:02d} {:02d}:{:02d}:{:02d}".format(*ZIP_TIME)
#: the media type of bytes whose format is not in the table
OCTET_STREAM = "application/octet-stream"


@dataclass(frozen=True)
class FileFormat:
    extension: str                  # with the dot: what files of the format are named
    media_type: str                 # what the API serves them as
    aliases: tuple[str, ...] = ()   # other extensions that name the format (the CLI's -o)


#: format name -> file format. Zips: a raw volume (volume.raw + volume.json), an obj bake
#: (obj + mtl + mtlx + png), a tile pyramid, and any output with extra files (maps, GPU textures)
FORMATS: dict[str, FileFormat] = {
    "png": FileFormat(".png", "image/png"),
    "webp": FileFormat(".webp", "image/webp"),
    "exr": FileFormat(".exr", "image/x-exr"),
    "tiff": FileFormat(".tif", "image/tiff", (".tiff",)),
    "jpeg": FileFormat(".jpg", "image/jpeg"),
    "gif": FileFormat(".gif", "image/gif"),
    "bmp": FileFormat(".bmp", "image/bmp"),
    "npy": FileFormat(".npy", "application/x-npy"),
    "nrrd": FileFormat(".nrrd", OCTET_STREAM),
    "vdb": FileFormat(".vdb", "application/x-vdb"),
    "flipbook": FileFormat(".png", "image/png"),
    "dds": FileFormat(".dds", "image/vnd-ms.dds"),
    "ktx2": FileFormat(".ktx2", "image/ktx2"),
    "glb": FileFormat(".glb", "model/gltf-binary"),
    "usdz": FileFormat(".usdz", "model/vnd.usdz+zip"),
    "zip": FileFormat(".zip", "application/zip"),
    "raw": FileFormat(".zip", "application/zip"),
    "obj": FileFormat(".zip", "application/zip"),
    "pyramid": FileFormat(".zip", "application/zip"),
    "onnx": FileFormat(".onnx", OCTET_STREAM),
    "glsl": FileFormat(".glsl", "text/x-glsl; charset=utf-8"),
    "wgsl": FileFormat(".wgsl", "text/wgsl; charset=utf-8"),
}


#: output -> the formats it offers, in the order the API lists them (the first is the
#: default where the output has one); each is a key of ``FORMATS``
OFFERED: dict[str, tuple[str, ...]] = {
    "tile": ("png", "webp", "exr"),
    "volume": ("npy", "exr", "tiff", "raw", "nrrd", "dds", "flipbook", "vdb"),
    "region": ("png", "exr", "tiff", "pyramid", "dds", "ktx2"),
    "bake": ("glb", "obj", "usdz"),
    "gpu_texture": ("dds", "ktx2"),  # a bake's or a region's extra texture, a region format too
    "shader": ("glsl", "wgsl"),
}


def extension(fmt: str) -> str:
    """The file extension (with the dot) of format ``fmt``."""
    return FORMATS[fmt].extension


def media_type(fmt: str) -> str:
    """The media type of format ``fmt``; application/octet-stream for one not in the table."""
    known = FORMATS.get(fmt)
    return known.media_type if known else OCTET_STREAM


def media_type_of_extension(ext: str) -> str:
    """The media type of a file ending in ``ext`` (``"png"`` or ``".png"``): the first
    format named so; application/octet-stream for an unknown extension."""
    ext = "." + ext.lower().lstrip(".")
    return next((f.media_type for f in FORMATS.values() if ext == f.extension or ext in f.aliases), OCTET_STREAM)


def extensions(formats: Iterable[str]) -> dict[str, tuple[str, ...]]:
    """Format -> every extension that names it (the first is what files are written as),
    for ``formats`` in their order."""
    return {fmt: (FORMATS[fmt].extension, *FORMATS[fmt].aliases) for fmt in formats}


def member_stem(path: str | os.PathLike) -> str:
    """The stem a result's zip members are named after: the result file's own stem (the
    service names results after their texture, ``service/download_names.py``), reduced to
    characters every unzip tool and OBJ reader takes (``mtllib``, ``map_Kd`` end at a blank),
    so two results extracted into one folder do not overwrite each other."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", Path(path).stem).strip("-.") or "texture"


def member_name(stem: str, role: str, ext: str) -> str:
    """A zip member of the result ``stem``: ``<stem>_<role><ext>`` (``oak_normal.png``), or
    ``<stem><ext>`` without a role (``oak.obj``)."""
    return f"{stem}_{role}{ext}" if role else f"{stem}{ext}"


@contextmanager
def atomic_output(path: str | os.PathLike, suffix: str = "") -> Iterator[str]:
    """Yield a temporary path (str) in ``path``'s folder (created if missing), ending in
    ``suffix`` (writers that pick the format by extension need it). When the block
    succeeds the file is made world-readable (0644: the API process reads results a
    worker wrote) and renamed to ``path``; when it raises, the temporary file is removed
    and the exception propagates."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o644)  # mkstemp makes 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
