"""Extra outputs of a bake: derived maps and a mipmapped GPU texture of the atlas.

Called at the end of ``worker.bake.bake_mesh`` (its write stage) with the linear atlas
(``R x R x 3``, gutter filled) and the texels it covers (the height map's range and the
maps' blurs are taken over those). Every member is named after the result (``<stem>`` = its
file's stem, ``worker.files.member_stem``), so two bakes extracted into one folder keep
their files. Where each output goes:

* OBJ zip: members ``<stem>_normal.png``, ``<stem>_height.png``, ``<stem>_roughness.png``,
  ``<stem>_ao.png`` (``worker/derived_maps.py``) and ``<stem>_basecolor.dds|ktx2``
  (``worker/gpu_textures.py``) are added; the MTL gains ``map_Bump <stem>_normal.png``
  (what Blender's OBJ importer reads as a tangent-space normal map), ``norm
  <stem>_normal.png`` (the PBR MTL extension other tools read), ``map_Pr
  <stem>_roughness.png`` (PBR MTL roughness, which Blender reads) and a comment naming the
  AO map (MTL has no occlusion keyword). The height map is not referenced from the MTL
  (MTL's ``bump`` is a height map to some tools and a normal map to others, and the normal
  map holds the same relief). The zip's MaterialX document ``<stem>.mtlx`` is rewritten to
  connect the normal and roughness maps too (``worker/material_files.py``).
* GLB: the normal map is embedded as the material's ``normalTexture`` (glTF's own
  convention: tangent space, +Y up, which is what ``normal_map`` writes) with a TANGENT
  attribute; roughness and AO are packed into one embedded "ORM" PNG (R = occlusion, G =
  roughness, B = metallic 0), set as the ``occlusionTexture`` (R) and the
  ``metallicRoughnessTexture`` (G, B; ``metallicFactor`` 0, ``roughnessFactor`` 1) for the
  maps asked for. A KTX2 texture is embedded too, as the base colour's
  ``KHR_texture_basisu`` source (``glb_with_basisu_texture``): viewers that know the
  extension load the KTX2, others (Blender 3.4) the PNG beside it. glTF has no height map
  and no DDS, so when ``height`` or ``dds`` is asked for the result becomes a zip of
  ``<stem>.glb`` plus ``<stem>_height.png`` / ``<stem>_basecolor.dds``.
* USDZ (``write_usdz_bake``): the normal, roughness and AO maps go inside the package
  beside the base colour, connected to its UsdPreviewSurface (``normal``, ``roughness``,
  ``occlusion``). USDZ takes neither a height map (not connected: no scene-unit scale) nor
  DDS / KTX2 files, so when they are asked for the result becomes a zip of
  ``<stem>.usdz`` plus ``<stem>_height.png`` / ``<stem>_basecolor.dds|ktx2``.

All rewrites are atomic (``worker/files.py``).
"""
from __future__ import annotations

import json
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worker.derived_maps import DerivedMaps, check_maps, derived_maps, encode_normals8, grey8, map_file
from worker.files import ZIP_TIME, atomic_output, extension, media_type, member_name, member_stem
from worker.gpu_textures import check_gpu_options, gpu_texture_bytes
from worker.images import png_bytes
from worker.material_files import MATERIAL_MAPS, base_colour_file, materialx_document, usdz_bytes

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


@dataclass(frozen=True)
class BakeOutputs:
    path: Path                                   # the result (a GLB may have become a zip)
    height_range: tuple[float, float] | None     # the height map's luminance (min, max), if one was made


def check_options(maps, gpu_format, dds_compression: str = "bc1") -> None:
    """InvalidParameter unless the extras asked for can be made (before any baking)."""
    check_maps(maps)
    check_gpu_options(gpu_format, dds_compression)


def add_bake_outputs(path: Path, fmt: str, image: np.ndarray, *, maps=(), gpu_format: str | None = None,
                     dds_compression: str = "bc1", strength: float, mask: np.ndarray | None = None) -> BakeOutputs:
    """Add the requested outputs to the bake result at ``path`` (see module doc); returns
    the result's path (a GLB becomes ``<stem>.zip`` when it cannot hold everything) and the
    height map's luminance range. ``mask``: (R, R) bool, the texels the mesh covers;
    ``dds_compression``: bc1 or bc7 for a DDS (``worker/gpu_textures.py``)."""
    check_options(maps, gpu_format, dds_compression)
    stem = member_stem(path)
    derived = derived_maps(image, maps, strength=strength, mask=mask)
    done = BakeOutputs(path, derived.height_range)
    if fmt == "obj":
        files = derived.files(stem)
    else:   # the GLB embeds normal, roughness and AO; the rest goes beside it
        files = derived.files(stem) if "height" in maps else {}
        files = {name: data for name, data in files.items() if name == map_file("height", stem)}
    if gpu_format is not None:
        files[member_name(stem, "basecolor", extension(gpu_format))] = gpu_texture_bytes(image, gpu_format,
                                                                                         dds_compression)
    if fmt == "obj":
        if maps:   # the MaterialX document connects the maps now in the zip
            files[member_name(stem, "", ".mtlx")] = materialx_document(stem, maps).encode()
        if files:
            _rewrite_zip(path, path, files, {}, mtl=(member_name(stem, "", ".mtl"), _mtl_lines(files, stem)))
        return done
    embedded = set(maps) & {"normal", "roughness", "ao"}
    if not files and not embedded:
        return done
    glb = path.read_bytes()
    if embedded:
        glb = glb_with_material_maps(glb, normal=derived.arrays.get("normal"),
                                     roughness=derived.arrays.get("roughness"), ao=derived.arrays.get("ao"))
    ktx2 = member_name(stem, "basecolor", extension("ktx2"))
    if ktx2 in files:
        glb = glb_with_basisu_texture(glb, files.pop(ktx2))
    if not files:
        with atomic_output(path) as tmp, open(tmp, "wb") as f:
            f.write(glb)
        return done
    zip_path = path.with_suffix(".zip")
    _rewrite_zip(None, zip_path, files, {member_name(stem, "", ".glb"): glb})
    path.unlink()
    return BakeOutputs(zip_path, derived.height_range)


def write_usdz_bake(path: Path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, normals: np.ndarray,
                    png: bytes, image: np.ndarray | None, *, maps=(), gpu_format: str | None = None,
                    dds_compression: str = "bc1", strength: float, mask: np.ndarray | None = None) -> BakeOutputs:
    """Write a USDZ bake to ``path`` (module doc): the mesh (``vertices`` (V, 3), ``faces``
    (F, 3), ``uv`` (V, 2) v up, ``normals`` (V, 3)), the base colour ``png`` and the
    requested maps of the linear atlas ``image`` (None when no map and no GPU texture is
    asked for) inside; a zip of ``<stem>.usdz`` and the files USDZ cannot hold when a height
    map or a GPU texture is asked for. Returns the result's path and the height range."""
    check_options(maps, gpu_format, dds_compression)
    stem = member_stem(path)
    derived = derived_maps(image, maps, strength=strength, mask=mask) if maps else DerivedMaps()
    files = derived.files(stem)
    inside = {base_colour_file(stem): png}
    inside.update({name: data for name, data in files.items() if name in {map_file(m, stem) for m in MATERIAL_MAPS}})
    package = usdz_bytes(vertices, faces, uv, normals, stem, inside)
    beside = {name: data for name, data in files.items() if name not in inside}
    if gpu_format is not None:
        beside[member_name(stem, "basecolor", extension(gpu_format))] = gpu_texture_bytes(image, gpu_format,
                                                                                          dds_compression)
    if not beside:
        with atomic_output(path) as tmp, open(tmp, "wb") as f:
            f.write(package)
        return BakeOutputs(path, derived.height_range)
    zip_path = path.with_suffix(".zip")
    _rewrite_zip(None, zip_path, beside, {member_name(stem, "", ".usdz"): package})
    return BakeOutputs(zip_path, derived.height_range)


def _mtl_lines(files: dict, stem: str) -> str:
    """The MTL lines naming the derived maps among ``files`` (module doc)."""
    normal, roughness, ao = (map_file(name, stem) for name in ("normal", "roughness", "ao"))
    lines = [f"map_Bump {normal}", f"norm {normal}"] if normal in files else []
    lines += [f"map_Pr {roughness}"] if roughness in files else []
    lines += [f"# ambient occlusion (no MTL keyword): map_ao {ao}"] if ao in files else []
    return "".join(line + "\n" for line in lines)


def _rewrite_zip(source: Path | None, target: Path, files: dict, first: dict,
                 mtl: tuple[str, str] = ("", "")) -> None:
    """Write ``target``: the members ``first``, then those of the zip ``source``, then
    ``files``; ``mtl``: (member, lines) to append to that MTL member."""
    members = dict(first)
    if source is not None:
        with zipfile.ZipFile(source) as z:
            members.update({name: z.read(name) for name in z.namelist()})
    mtl_name, mtl_extra = mtl
    if mtl_extra and mtl_name in members:
        members[mtl_name] = members[mtl_name] + mtl_extra.encode()
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


def _add_tangents(gltf: dict, prim: dict, binary: bytes, append) -> None:
    """A TANGENT accessor (``vertex_tangents``) for a primitive with positions, normals, UVs
    and indices but no tangents; ``append`` stores its bytes."""
    attrs = prim["attributes"]
    if "TANGENT" in attrs or not {"POSITION", "NORMAL", "TEXCOORD_0"} <= set(attrs) or "indices" not in prim:
        return
    positions, normals, st = (_accessor(gltf, binary, attrs[k]).astype(np.float64)
                              for k in ("POSITION", "NORMAL", "TEXCOORD_0"))
    faces = _accessor(gltf, binary, prim["indices"]).reshape(-1, 3).astype(np.int64)
    uv = np.stack([st[:, 0], 1.0 - st[:, 1]], axis=1)        # glTF t points down the image
    tangents = vertex_tangents(positions, normals, uv, faces)
    view = append(tangents.tobytes(), target=34962)
    gltf.setdefault("accessors", []).append(
        {"bufferView": view, "componentType": 5126, "count": len(tangents), "type": "VEC4"})
    attrs["TANGENT"] = len(gltf["accessors"]) - 1


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


def glb_with_material_maps(glb: bytes, *, normal: np.ndarray | None = None, roughness: np.ndarray | None = None,
                           ao: np.ndarray | None = None) -> bytes:
    """The GLB with the given maps embedded in every material (module doc): ``normal``
    (R, R, 3) unit vectors as ``normalTexture``, with a TANGENT attribute (``vertex_tangents``)
    on each primitive that has none, so viewers need not guess the tangent frame;
    ``roughness`` and ``ao`` (R, R) 0..1 packed into one ORM PNG, the
    ``metallicRoughnessTexture`` and / or ``occlusionTexture``. Each image is appended to the
    binary chunk as a new bufferView, image and texture (the base colour's sampler reused)."""
    gltf, binary = _glb_split(glb)
    views = gltf.setdefault("bufferViews", [])

    def append(data: bytes, **extra) -> int:
        """Append ``data`` to the binary chunk as a new bufferView (4-byte aligned); its index."""
        nonlocal binary
        binary += b"\0" * (-len(binary) % 4)
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data), **extra})
        binary += data
        return len(views) - 1

    def add_texture(png: bytes, name: str) -> int:
        append(png)
        gltf.setdefault("images", []).append({"bufferView": len(views) - 1, "mimeType": media_type("png"),
                                              "name": name})
        texture = {"source": len(gltf["images"]) - 1}
        samplers = [t["sampler"] for t in gltf.get("textures", []) if "sampler" in t]
        if samplers:
            texture["sampler"] = samplers[0]
        gltf.setdefault("textures", []).append(texture)
        return len(gltf["textures"]) - 1

    if normal is not None:
        for mesh in gltf.get("meshes", []):
            for prim in mesh["primitives"]:
                _add_tangents(gltf, prim, binary, append)
        index = add_texture(png_bytes(encode_normals8(normal)), "normal")
        for material in gltf.get("materials", []):
            material["normalTexture"] = {"index": index}
    if roughness is not None or ao is not None:
        size = (roughness if roughness is not None else ao).shape
        full = np.full(size, 255, np.uint8)
        orm = np.stack([grey8(ao) if ao is not None else full, grey8(roughness) if roughness is not None else full,
                        np.zeros(size, np.uint8)], axis=-1)     # metallic 0
        index = add_texture(png_bytes(orm), "occlusion-roughness-metallic")
        for material in gltf.get("materials", []):
            if ao is not None:
                material["occlusionTexture"] = {"index": index}
            if roughness is not None:
                pbr = material.setdefault("pbrMetallicRoughness", {})
                pbr.update(metallicRoughnessTexture={"index": index}, metallicFactor=0.0, roughnessFactor=1.0)
    binary += b"\0" * (-len(binary) % 4)
    gltf.setdefault("buffers", [{}])[0]["byteLength"] = len(binary)
    return _glb_join(gltf, binary)


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
