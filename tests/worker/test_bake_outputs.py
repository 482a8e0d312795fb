"""Bake extras: derived maps and mipmapped GPU textures of the atlas (worker/bake_outputs.py)."""
import io
import json
import os
import shutil
import struct
import subprocess
import zipfile

import numpy as np
import pytest
from PIL import Image

from tests.worker.gpu_readers import assert_block_compressed_close, read_dds_levels, read_ktx2
from worker.bake import bake_mesh
from worker.bake_outputs import vertex_tangents
from worker.derived_maps import decode_normals8
from worker.errors import InvalidParameter
from worker.gpu_textures import mip_sizes

RES = 64


def bake(waves, meshes, tmp_path, fmt, **options):
    return bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny_uv.obj").read_bytes(), filename="bunny_uv.obj",
                     resolution=RES, fmt=fmt, out_path=tmp_path / f"baked.{'glb' if fmt == 'glb' else 'zip'}",
                     **options)


def glb_parts(data: bytes):
    magic, version, length = struct.unpack_from("<3I", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, = struct.unpack_from("<I", data, 12)
    gltf = json.loads(data[20:20 + json_len])
    bin_len, bin_type = struct.unpack_from("<2I", data, 20 + json_len)
    assert bin_type == 0x004E4942 and gltf["buffers"][0]["byteLength"] == bin_len
    return gltf, data[28 + json_len:28 + json_len + bin_len]


def image_of(gltf, binary, index):
    view = gltf["bufferViews"][gltf["images"][index]["bufferView"]]
    return Image.open(io.BytesIO(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]))


def check_normals(png: Image.Image):
    n = decode_normals8(np.asarray(png))
    assert n.shape == (RES, RES, 3) and np.abs(np.linalg.norm(n, axis=-1) - 1).max() < 0.02
    assert (n[..., 2] > 0).all()


def test_glb_embeds_the_normal_map(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "glb", maps=("normal",), normal_strength=2.0)
    assert result.path == tmp_path / "baked.glb" and sorted(p.name for p in tmp_path.iterdir()) == ["baked.glb"]
    gltf, binary = glb_parts(result.path.read_bytes())
    material = gltf["materials"][0]
    normal_texture = gltf["textures"][material["normalTexture"]["index"]]
    base_texture = gltf["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    assert normal_texture["source"] != base_texture["source"]
    check_normals(image_of(gltf, binary, normal_texture["source"]))
    assert image_of(gltf, binary, base_texture["source"]).size == (RES, RES)
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
    # a TANGENT per vertex (so viewers do not generate one): unit, orthogonal to NORMAL, w = +-1
    attrs = gltf["meshes"][0]["primitives"][0]["attributes"]

    def accessor(index, width):
        view = gltf["bufferViews"][gltf["accessors"][index]["bufferView"]]
        return np.frombuffer(binary, "<f4", count=gltf["accessors"][index]["count"] * width,
                             offset=view["byteOffset"]).reshape(-1, width)
    tangent, normal = accessor(attrs["TANGENT"], 4), accessor(attrs["NORMAL"], 3)
    assert len(tangent) == len(normal) and np.allclose(np.linalg.norm(tangent[:, :3], axis=1), 1, atol=1e-5)
    assert np.abs((tangent[:, :3] * normal).sum(axis=1)).max() < 1e-4 and set(np.unique(tangent[:, 3])) <= {-1, 1}


def test_tangents_follow_u_and_v_up():
    quad = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], float)
    normals = np.tile([0.0, 0, 1], (4, 1))
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    upright = vertex_tangents(quad, normals, np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), faces)
    assert np.allclose(upright, [[1, 0, 0, 1]] * 4)        # u along +x, v along +y = cross(n, t)
    mirrored = vertex_tangents(quad, normals, np.array([[1, 0], [0, 0], [0, 1], [1, 1]], float), faces)
    assert np.allclose(mirrored, [[-1, 0, 0, -1]] * 4)     # u along -x: handedness flips


def test_glb_with_height_becomes_a_zip_and_embeds_the_ktx2(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "glb", maps=("height", "normal"), gpu_format="ktx2")
    assert result.path == tmp_path / "baked.zip" and sorted(p.name for p in tmp_path.iterdir()) == ["baked.zip"]
    with zipfile.ZipFile(result.path) as z:
        assert sorted(z.namelist()) == ["height.png", "model.glb"]
        gltf, binary = glb_parts(z.read("model.glb"))
        height = Image.open(io.BytesIO(z.read("height.png")))
    assert "normalTexture" in gltf["materials"][0] and height.size == (RES, RES) and height.mode.startswith("I")
    # the base colour: the PNG as the texture's source (the fallback), the KTX2 as its basisu source
    base = gltf["textures"][gltf["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    ktx_image = gltf["images"][base["extensions"]["KHR_texture_basisu"]["source"]]
    assert gltf["extensionsUsed"] == ["KHR_texture_basisu"] and "extensionsRequired" not in gltf
    assert ktx_image["mimeType"] == "image/ktx2" and gltf["images"][base["source"]]["mimeType"] == "image/png"
    view = gltf["bufferViews"][ktx_image["bufferView"]]
    header, levels = read_ktx2(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]])
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(RES, RES) and header["dfd"]["model"] == 166   # UASTC
    colour = np.asarray(image_of(gltf, binary, base["source"]).convert("RGB"))
    # level 0 is the baked atlas itself, in UASTC blocks (chart edges: see the DDS test below)
    assert_block_compressed_close(levels[0][..., :3], colour, mean=16, worst=255)


def test_glb_with_only_a_ktx2_stays_a_glb(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "glb", gpu_format="ktx2")
    gltf, _ = glb_parts(result.path.read_bytes())
    assert result.path.suffix == ".glb" and [i["mimeType"] for i in gltf["images"]] == ["image/png", "image/ktx2"]


def test_obj_zip_gets_the_maps_and_a_dds(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "obj", maps=("height", "normal"), gpu_format="dds")
    with zipfile.ZipFile(result.path) as z:
        names = set(z.namelist())
        mtl = z.read("model.mtl").decode()
        z.extract("texture.dds", tmp_path / "x")
        png = np.asarray(Image.open(io.BytesIO(z.read("texture.png"))).convert("RGB"))
        check_normals(Image.open(io.BytesIO(z.read("normal.png"))))
    assert {"model.obj", "model.mtl", "texture.png", "height.png", "normal.png", "texture.dds"} <= names
    assert "map_Kd texture.png" in mtl and "norm normal.png" in mtl
    levels = read_dds_levels(tmp_path / "x" / "texture.dds")
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(RES, RES)
    # level 0 is the baked atlas itself, in BC1 blocks; blocks across a chart's edge hold
    # three colours (chart, padding, background) that one line cannot, hence the worst case
    assert_block_compressed_close(levels[0][..., :3], png, mean=16, worst=255)


def test_bad_options_are_refused_before_baking(waves, meshes, tmp_path):
    with pytest.raises(InvalidParameter):
        bake(waves, meshes, tmp_path, "glb", maps=("roughness",))
    with pytest.raises(InvalidParameter):
        bake(waves, meshes, tmp_path, "obj", gpu_format="astc")
    assert waves.calls == [] and list(tmp_path.iterdir()) == []


VALIDATOR_DIR = os.environ.get("TEXSPACE_GLTF_VALIDATOR_DIR")   # as in test_bake.py


@pytest.mark.skipif(not (VALIDATOR_DIR and shutil.which("node")),
                    reason="Khronos glTF validator not installed (npm install gltf-validator; "
                           "set TEXSPACE_GLTF_VALIDATOR_DIR to that folder)")
def test_normal_mapped_glb_passes_the_khronos_validator(waves, meshes, tmp_path):
    """0 errors and 0 warnings: with the TANGENT attribute there is no
    MESH_PRIMITIVE_GENERATED_TANGENT_SPACE warning. One carries a KHR_texture_basisu KTX2:
    the validator (2.0.0-dev.3.10, the newest on npm) supports neither the extension nor
    KTX2 images, and says so in two warnings (and a note); the rest of the file stays clean."""
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
              ".then(r=>console.log(JSON.stringify(r.issues)))")
    for name in ("bunny.obj", "bunny_uv.obj", "textured_sphere_smooth.obj"):
        result = bake_mesh(waves, None, 0, mesh_bytes=(meshes / name).read_bytes(), filename=name, resolution=64,
                           out_path=tmp_path / f"{name}.glb", maps=("normal",),
                           gpu_format="ktx2" if name == "bunny_uv.obj" else None)
        out = subprocess.run(["node", "-e", script, str(result.path)], cwd=VALIDATOR_DIR, capture_output=True,
                             text=True, timeout=120, check=True)
        issues = json.loads(out.stdout)
        unsupported = [(m["code"], m.get("pointer")) for m in issues["messages"] if m["severity"] == 1]
        if name == "bunny_uv.obj":
            assert sorted(unsupported) == [("IMAGE_UNRECOGNIZED_FORMAT", "/images/2"),
                                           ("VALUE_NOT_IN_LIST", "/images/2/mimeType")], issues["messages"][:5]
        else:
            assert unsupported == [], issues["messages"][:5]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == len(unsupported), issues["messages"][:5]
