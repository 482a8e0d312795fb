"""Extra outputs of a bake: derived maps and a mipmapped GPU texture of the atlas.

Called at the end of ``worker.bake.bake_mesh`` (its write stage) with the linear atlas
(``R x R x 3``, gutter filled). Where each output goes:

* OBJ zip: members ``normal.png`` / ``height.png`` (``worker/derived_maps.py``) and
  ``texture.dds`` / ``texture.ktx2`` (``worker/gpu_textures.py``) are added;
  ``model.mtl`` gains ``norm normal.png`` (the PBR MTL extension Blender and others read
  as a tangent-space normal map). ``height.png`` is not referenced from the MTL (MTL's
  ``bump`` means a height map to some tools and a normal map to others).
* GLB: the normal map is embedded as the material's ``normalTexture`` (glTF's own
  convention: tangent space, +Y up, which is what ``normal_map`` writes; viewers derive
  tangents from the UVs). A KTX2 texture is embedded too, as the base colour's
  ``KHR_texture_basisu`` source (``glb_with_basisu_texture``): viewers that know the
  extension load the KTX2, others (Blender 3.4) the PNG beside it. glTF has no height map
  and no DDS, so when ``height`` or ``dds`` is asked for the result becomes a zip of
  ``model.glb`` plus ``height.png`` / ``texture.dds``.

All rewrites are atomic (``worker/files.py``).
"""
from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import numpy as np

from worker.derived_maps import MAP_NAMES, derived_map_files
from worker.errors import InvalidParameter
from worker.files import ZIP_TIME, atomic_output, extension, media_type
from worker.gpu_textures import FORMATS as GPU_FORMATS
from worker.gpu_textures import gpu_texture_bytes

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def check_options(maps, gpu_format) -> None:
    if set(maps) - set(MAP_NAMES):
        raise InvalidParameter(f"unknown derived maps {sorted(set(maps) - set(MAP_NAMES))}; choose from {MAP_NAMES}")
    if gpu_format is not None and gpu_format not in GPU_FORMATS:
        raise InvalidParameter(f"GPU texture format must be one of {GPU_FORMATS}, got {gpu_format!r}")


def add_bake_outputs(path: Path, fmt: str, image: np.ndarray, *, maps=(), gpu_format: str | None = None,
                     strength: float) -> Path:
    """Add the requested outputs to the bake result at ``path`` (see module doc); returns the
    result's path (a GLB becomes ``<stem>.zip`` when it cannot hold everything)."""
    check_options(maps, gpu_format)
    files = derived_map_files(image, maps, strength=strength)
    if gpu_format is not None:
        files[f"texture{extension(gpu_format)}"] = gpu_texture_bytes(image, gpu_format)
    if not files:
        return path
    if fmt == "obj":
        _rewrite_zip(path, path, files, {}, mtl_extra="norm normal.png\n" if "normal.png" in files else "")
        return path
    glb = path.read_bytes()
    if "normal.png" in files:
        glb = glb_with_normal_texture(glb, files.pop("normal.png"))
    if "texture.ktx2" in files:
        glb = glb_with_basisu_texture(glb, files.pop("texture.ktx2"))
    if not files:
        with atomic_output(path) as tmp, open(tmp, "wb") as f:
            f.write(glb)
        return path
    zip_path = path.with_suffix(".zip")
    _rewrite_zip(None, zip_path, files, {"model.glb": glb})
    path.unlink()
    return zip_path


def _rewrite_zip(source: Path | None, target: Path, files: dict, first: dict, mtl_extra: str = "") -> None:
    members = dict(first)
    if source is not None:
        with zipfile.ZipFile(source) as z:
            members.update({name: z.read(name) for name in z.namelist()})
    if mtl_extra and "model.mtl" in members:
        members["model.mtl"] = members["model.mtl"] + mtl_extra.encode()
    members.update(files)
    with atomic_output(target) as tmp, zipfile.ZipFile(tmp, "w") as z:
        for name, data in members.items():
            z.writestr(zipfile.ZipInfo(name, ZIP_TIME), data, compress_type=zipfile.ZIP_DEFLATED)


def vertex_tangents(vertices: np.ndarray, normals: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """glTF TANGENT (V, 4) float32: xyz the unit direction of increasing u, orthogonal to the
    normal; w = +-1 so that ``cross(normal, xyz) * w`` points along increasing v (image up).

    vertices, normals : (V, 3); uv : (V, 2) with v up; faces : (F, 3) int. Per-face tangents
    (not normalised, so larger faces weigh more) are summed per vertex, then
    Gram-Schmidt against the normal; a vertex with none gets any unit vector orthogonal to it.
    """
    p, t = vertices[faces], uv[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=np.abs(det) > 1e-20)[:, None]
    face_t = (e1 * d2[:, 1:] - e2 * d1[:, 1:]) * inv
    face_b = (e2 * d1[:, :1] - e1 * d2[:, :1]) * inv
    tan, bit = np.zeros_like(vertices, dtype=np.float64), np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(tan, faces[:, k], face_t)
        np.add.at(bit, faces[:, k], face_b)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    tan -= n * (n * tan).sum(axis=1, keepdims=True)
    length = np.linalg.norm(tan, axis=1)
    bad = length < 1e-12
    if bad.any():   # any unit vector orthogonal to the normal
        helper = np.where(np.abs(n[bad, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        tan[bad] = np.cross(n[bad], helper)
        length[bad] = np.linalg.norm(tan[bad], axis=1)
    tan /= length[:, None]
    w = np.where((np.cross(n, tan) * bit).sum(axis=1) < 0, -1.0, 1.0)
    return np.concatenate([tan, w[:, None]], axis=1).astype(np.float32)


def _accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    """A tightly packed float32 / uint32 accessor as an array (what ``worker.bake`` writes)."""
    acc = gltf["accessors"][index]
    view = gltf["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = {5126: "<f4", 5125: "<u4", 5123: "<u2"}[acc["componentType"]]
    if view.get("byteStride") not in (None, width * np.dtype(dtype).itemsize):
        raise ValueError("interleaved glTF buffers are not supported")
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, dtype, count=acc["count"] * width, offset=start).reshape(acc["count"], width)


def glb_with_normal_texture(glb: bytes, png: bytes) -> bytes:
    """The GLB with ``png`` appended to its binary chunk and set as every material's
    ``normalTexture`` (a new bufferView, image and texture; the base colour's sampler is
    reused when it has one), and a TANGENT attribute (``vertex_tangents``) on each
    primitive that has none, so viewers need not guess the tangent frame."""
    magic, version, length = struct.unpack_from("<3I", glb)
    json_len, json_type = struct.unpack_from("<2I", glb, 12)
    if magic != GLB_MAGIC or version != 2 or json_type != JSON_CHUNK:
        raise ValueError("not a glTF 2.0 binary")
    gltf = json.loads(glb[20:20 + json_len])
    at = 20 + json_len
    binary = b""
    if at < length:
        bin_len, bin_type = struct.unpack_from("<2I", glb, at)
        if bin_type != BIN_CHUNK:
            raise ValueError("second GLB chunk is not BIN")
        binary = glb[at + 8:at + 8 + bin_len]
    views = gltf.setdefault("bufferViews", [])

    def append(data: bytes, **extra) -> int:
        nonlocal binary
        binary += b"\0" * (-len(binary) % 4)
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data), **extra})
        binary += data
        return len(views) - 1

    for mesh in gltf.get("meshes", []):
        for prim in mesh["primitives"]:
            attrs = prim["attributes"]
            if "TANGENT" in attrs or not {"POSITION", "NORMAL", "TEXCOORD_0"} <= set(attrs) or "indices" not in prim:
                continue
            positions, normals, st = (_accessor(gltf, binary, attrs[k]).astype(np.float64)
                                      for k in ("POSITION", "NORMAL", "TEXCOORD_0"))
            faces = _accessor(gltf, binary, prim["indices"]).reshape(-1, 3).astype(np.int64)
            uv = np.stack([st[:, 0], 1.0 - st[:, 1]], axis=1)        # glTF t points down the image
            tangents = vertex_tangents(positions, normals, uv, faces)
            view = append(tangents.tobytes(), target=34962)
            gltf.setdefault("accessors", []).append(
                {"bufferView": view, "componentType": 5126, "count": len(tangents), "type": "VEC4"})
            attrs["TANGENT"] = len(gltf["accessors"]) - 1
    append(png)
    binary += b"\0" * (-len(binary) % 4)
    buffers = gltf.setdefault("buffers", [{}])
    buffers[0]["byteLength"] = len(binary)
    gltf.setdefault("images", []).append({"bufferView": len(gltf["bufferViews"]) - 1, "mimeType": media_type("png"),
                                          "name": "normal"})
    texture = {"source": len(gltf["images"]) - 1}
    samplers = [t["sampler"] for t in gltf.get("textures", []) if "sampler" in t]
    if samplers:
        texture["sampler"] = samplers[0]
    gltf.setdefault("textures", []).append(texture)
    for material in gltf.get("materials", []):
        material["normalTexture"] = {"index": len(gltf["textures"]) - 1}
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<2I", len(text), JSON_CHUNK) + text + struct.pack("<2I", len(binary), BIN_CHUNK) + binary
    return struct.pack("<3I", GLB_MAGIC, 2, 12 + len(body)) + body


def glb_with_basisu_texture(glb: bytes, ktx2: bytes) -> bytes:
    """The GLB with ``ktx2`` (Basis Universal, ``worker.gpu_textures.ktx2_bytes``) appended
    to its binary chunk as an ``image/ktx2`` image and named by every base-colour texture's
    ``KHR_texture_basisu`` extension. The texture keeps its PNG ``source`` as the fallback,
    so the extension is used, not required: every glTF loader still opens the file."""
    gltf, binary = _glb_split(glb)
    binary += b"\0" * (-len(binary) % 4)
    gltf.setdefault("bufferViews", []).append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(ktx2)})
    binary += ktx2 + b"\0" * (-len(ktx2) % 4)
    gltf.setdefault("buffers", [{}])[0]["byteLength"] = len(binary)
    gltf.setdefault("images", []).append({"bufferView": len(gltf["bufferViews"]) - 1,
                                          "mimeType": media_type("ktx2"), "name": "base colour (KTX2)"})
    colour = {m["pbrMetallicRoughness"]["baseColorTexture"]["index"] for m in gltf.get("materials", [])
              if "baseColorTexture" in m.get("pbrMetallicRoughness", {})}
    for index in sorted(colour):
        gltf["textures"][index].setdefault("extensions", {})["KHR_texture_basisu"] = {
            "source": len(gltf["images"]) - 1}
    used = gltf.setdefault("extensionsUsed", [])
    if colour and "KHR_texture_basisu" not in used:
        used.append("KHR_texture_basisu")
    return _glb_join(gltf, binary)


def _glb_split(glb: bytes) -> tuple[dict, bytes]:
    """(glTF JSON, BIN chunk) of a glTF 2.0 binary."""
    magic, version, length = struct.unpack_from("<3I", glb)
    json_len, json_type = struct.unpack_from("<2I", glb, 12)
    if magic != GLB_MAGIC or version != 2 or json_type != JSON_CHUNK:
        raise ValueError("not a glTF 2.0 binary")
    at, binary = 20 + json_len, b""
    if at < length:
        bin_len, bin_type = struct.unpack_from("<2I", glb, at)
        if bin_type != BIN_CHUNK:
            raise ValueError("second GLB chunk is not BIN")
        binary = glb[at + 8:at + 8 + bin_len]
    return json.loads(glb[20:20 + json_len]), binary


def _glb_join(gltf: dict, binary: bytes) -> bytes:
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<2I", len(text), JSON_CHUNK) + text + struct.pack("<2I", len(binary), BIN_CHUNK) + binary
    return struct.pack("<3I", GLB_MAGIC, 2, 12 + len(body)) + body
