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

from tests.worker.gpu_readers import assert_block_compressed_close, read_bc7_dds, read_dds_levels, read_ktx2
from worker.bake import bake_mesh
from worker.bake_outputs import vertex_tangents
from worker.derived_maps import ROUGHNESS_RANGE, decode_normals8, read_height_range
from worker.errors import InvalidParameter
from worker.files import extension
from worker.gpu_textures import mip_sizes

RES = 64


def bake(waves, meshes, tmp_path, fmt, **options):
    return bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny_uv.obj").read_bytes(), filename="bunny_uv.obj",
                     resolution=RES, fmt=fmt, out_path=tmp_path / f"baked{extension(fmt)}",
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
        assert sorted(z.namelist()) == ["baked.glb", "baked_height.png"]
        gltf, binary = glb_parts(z.read("baked.glb"))
        height = Image.open(io.BytesIO(z.read("baked_height.png")))
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


def test_glb_with_material_maps_and_a_ktx2_stays_a_glb(waves, meshes, tmp_path):
    """Normal, ORM and the KTX2 all go inside: the material keeps its normal, occlusion and
    metallic-roughness textures, the base colour gains its basisu source."""
    result = bake(waves, meshes, tmp_path, "glb", maps=("ao", "normal", "roughness"), gpu_format="ktx2")
    assert result.path == tmp_path / "baked.glb" and sorted(p.name for p in tmp_path.iterdir()) == ["baked.glb"]
    gltf, binary = glb_parts(result.path.read_bytes())
    material = gltf["materials"][0]
    pbr = material["pbrMetallicRoughness"]
    assert [i["mimeType"] for i in gltf["images"]] == ["image/png"] * 3 + ["image/ktx2"]
    assert material["occlusionTexture"]["index"] == pbr["metallicRoughnessTexture"]["index"]
    check_normals(image_of(gltf, binary, gltf["textures"][material["normalTexture"]["index"]]["source"]))
    base = gltf["textures"][pbr["baseColorTexture"]["index"]]
    assert base["extensions"]["KHR_texture_basisu"]["source"] == 3 and gltf["extensionsUsed"] == ["KHR_texture_basisu"]
    for texture in gltf["textures"]:     # only the base colour has a KTX2
        assert ("extensions" in texture) == (texture is base)


def test_obj_zip_gets_the_maps_and_a_dds(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "obj", maps=("height", "normal"), gpu_format="dds")
    with zipfile.ZipFile(result.path) as z:
        names = set(z.namelist())
        mtl = z.read("baked.mtl").decode()
        z.extract("baked_basecolor.dds", tmp_path / "x")
        png = np.asarray(Image.open(io.BytesIO(z.read("baked_basecolor.png"))).convert("RGB"))
        check_normals(Image.open(io.BytesIO(z.read("baked_normal.png"))))
    assert {"baked.obj", "baked.mtl", "baked_basecolor.png", "baked_height.png", "baked_normal.png",
            "baked_basecolor.dds"} <= names
    # Blender's OBJ importer reads map_Bump as the normal map; other tools read norm
    assert "map_Kd baked_basecolor.png" in mtl and "map_Bump baked_normal.png" in mtl
    assert "norm baked_normal.png" in mtl
    levels = read_dds_levels(tmp_path / "x" / "baked_basecolor.dds")
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(RES, RES)
    # level 0 is the baked atlas itself, in BC1 blocks; blocks across a chart's edge hold
    # three colours (chart, padding, background) that one line cannot, hence the worst case
    assert_block_compressed_close(levels[0][..., :3], png, mean=16, worst=255)


def test_glb_with_a_bc7_dds_becomes_a_zip(waves, meshes, tmp_path):
    """``dds_compression="bc7"``: the zip's DDS is BC7 in the DX10 header, sRGB, every level."""
    result = bake(waves, meshes, tmp_path, "glb", gpu_format="dds", dds_compression="bc7")
    with zipfile.ZipFile(result.path) as z:
        assert sorted(z.namelist()) == ["baked.glb", "baked_basecolor.dds"]
        header, levels = read_bc7_dds(z.read("baked_basecolor.dds"))
        gltf, binary = glb_parts(z.read("baked.glb"))
    assert (header["dxgi_format"], header["width"], header["height"], header["mips"]) == (99, RES, RES, 7)
    png = np.asarray(image_of(gltf, binary, 0).convert("RGB"))
    # chart edges hold three colours in a block (see the BC1 test): bounded, and far closer on average
    assert_block_compressed_close(levels[0][..., :3], png, mean=8, worst=255)


def test_glb_material_uses_roughness_and_occlusion(waves, meshes, tmp_path):
    """Every embedded map has its glTF slot: roughness in G and occlusion in R of one ORM
    image (metallic 0 in B); trimesh reads the same slots back."""
    import trimesh

    result = bake(waves, meshes, tmp_path, "glb", maps=("ao", "normal", "roughness"))
    assert result.path == tmp_path / "baked.glb" and result.height_range is None   # no zip: all embedded
    gltf, binary = glb_parts(result.path.read_bytes())
    material = gltf["materials"][0]
    pbr = material["pbrMetallicRoughness"]
    orm_index = pbr["metallicRoughnessTexture"]["index"]
    assert material["occlusionTexture"]["index"] == orm_index and "normalTexture" in material
    assert (pbr["metallicFactor"], pbr["roughnessFactor"]) == (0.0, 1.0)
    orm = np.asarray(image_of(gltf, binary, gltf["textures"][orm_index]["source"]).convert("RGB"))
    covered = result.covered
    occlusion, roughness, metallic = (orm[..., k][covered] / 255 for k in range(3))
    assert orm.shape == (RES, RES, 3) and (metallic == 0).all()
    assert ((roughness >= ROUGHNESS_RANGE[0] - 1 / 255) & (roughness <= ROUGHNESS_RANGE[1] + 1 / 255)).all()
    assert 0 <= occlusion.min() and occlusion.max() <= 1 and occlusion.mean() > 0.5 and occlusion.std() > 0
    scene = trimesh.load(result.path, file_type="glb")
    loaded = next(iter(scene.geometry.values())).visual.material
    assert loaded.metallicRoughnessTexture is not None and loaded.occlusionTexture is not None
    only_ao = bake(waves, meshes, tmp_path / "ao", "glb", maps=("ao",))
    ao_material = glb_parts(only_ao.path.read_bytes())[0]["materials"][0]
    assert "occlusionTexture" in ao_material and "metallicRoughnessTexture" not in ao_material["pbrMetallicRoughness"]


def test_obj_mtl_names_roughness_and_ao_and_the_height_range(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "obj", maps=("ao", "height", "roughness"))
    with zipfile.ZipFile(result.path) as z:
        mtl = z.read("baked.mtl").decode()
        height = z.read("baked_height.png")
        roughness = np.asarray(Image.open(io.BytesIO(z.read("baked_roughness.png"))))
        ao = np.asarray(Image.open(io.BytesIO(z.read("baked_ao.png"))))
    assert "map_Pr baked_roughness.png" in mtl and "map_ao baked_ao.png" in mtl.split("# ")[-1]
    assert roughness.shape == ao.shape == (RES, RES) and roughness.dtype == ao.dtype == np.uint8
    low, high = result.height_range
    assert read_height_range(height) == pytest.approx((low, high)) and 0 <= low < high <= 1
    codes = np.asarray(Image.open(io.BytesIO(height)))[result.covered]
    assert (codes.min(), codes.max()) == (0, 65535)          # the covered texels use the full range


def test_bad_options_are_refused_before_baking(waves, meshes, tmp_path):
    with pytest.raises(InvalidParameter):
        bake(waves, meshes, tmp_path, "glb", maps=("gloss",))
    with pytest.raises(InvalidParameter):
        bake(waves, meshes, tmp_path, "obj", gpu_format="astc")
    with pytest.raises(InvalidParameter):
        bake(waves, meshes, tmp_path, "obj", gpu_format="ktx2", dds_compression="bc7")
    assert waves.calls == [] and list(tmp_path.iterdir()) == []


VALIDATOR_DIR = os.environ.get("TEXSPACE_GLTF_VALIDATOR_DIR")   # as in test_bake.py


@pytest.mark.skipif(not (VALIDATOR_DIR and shutil.which("node")),
                    reason="Khronos glTF validator not installed (npm install gltf-validator; "
                           "set TEXSPACE_GLTF_VALIDATOR_DIR to that folder)")
def test_material_mapped_glb_passes_the_khronos_validator(waves, meshes, tmp_path):
    """0 errors and 0 warnings with normal, roughness and occlusion maps: with the TANGENT
    attribute there is no MESH_PRIMITIVE_GENERATED_TANGENT_SPACE warning. One carries a
    KHR_texture_basisu KTX2 too: the validator (2.0.0-dev.3.10, the newest on npm) supports
    neither the extension nor KTX2 images, and says so in two warnings (and a note); the
    rest of the file stays clean."""
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
              ".then(r=>console.log(JSON.stringify(r.issues)))")
    for name in ("bunny.obj", "bunny_uv.obj", "textured_sphere_smooth.obj"):
        result = bake_mesh(waves, None, 0, mesh_bytes=(meshes / name).read_bytes(), filename=name, resolution=64,
                           out_path=tmp_path / f"{name[:-4]}.glb", maps=("ao", "normal", "roughness"),
                           gpu_format="ktx2" if name == "bunny_uv.obj" else None)
        out = subprocess.run(["node", "-e", script, str(result.path)], cwd=VALIDATOR_DIR, capture_output=True,
                             text=True, timeout=120, check=True)
        issues = json.loads(out.stdout)
        unsupported = [(m["code"], m.get("pointer")) for m in issues["messages"] if m["severity"] == 1]
        if name == "bunny_uv.obj":
            # images: base colour, normal, ORM, then the KTX2
            assert sorted(unsupported) == [("IMAGE_UNRECOGNIZED_FORMAT", "/images/3"),
                                           ("VALUE_NOT_IN_LIST", "/images/3/mimeType")], issues["messages"][:5]
        else:
            assert unsupported == [], issues["messages"][:5]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == len(unsupported), issues["messages"][:5]
