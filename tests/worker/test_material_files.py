"""Material files of a bake (worker/material_files.py), opened with the real libraries: the
OBJ zip's MaterialX document with MaterialX (validated against its standard libraries), the
USDZ with pxr (mesh, UVs, binding, shaders, and USD's own validators), each texture path
resolved to a file in the archive and each colour space checked."""
from __future__ import annotations

import io
import struct
import subprocess
import sys
import zipfile

import MaterialX as mx
import numpy as np
from PIL import Image
from pxr import Sdf, Usd, UsdGeom, UsdShade, UsdValidation

from tests.worker.test_bake_outputs import RES, bake, glb_parts, image_of


# --- MaterialX in the OBJ zip ------------------------------------------------------------

def read_materialx(text: str):
    """The document, validated with MaterialX's standard libraries (node definitions too)."""
    doc = mx.createDocument()
    mx.readFromXmlString(doc, text)
    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    doc.setDataLibrary(library)
    valid, message = doc.validate()
    assert valid, message
    return doc


def upstream(node, name: str):
    """The node connected to ``node``'s input ``name`` (None when it holds a value)."""
    connected = node.getInput(name)
    return None if connected is None else connected.getConnectedNode()


def test_obj_zip_carries_a_materialx_standard_surface(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "obj", maps=("ao", "height", "normal", "roughness"))
    with zipfile.ZipFile(result.path) as z:
        names = set(z.namelist())
        doc = read_materialx(z.read("baked.mtlx").decode())
    materials = doc.getMaterialNodes()
    assert [m.getName() for m in materials] == ["baked"]
    shader = upstream(materials[0], "surfaceshader")
    assert shader.getCategory() == "standard_surface"
    assert shader.getInputValue("metalness") == 0.0 and shader.getInputValue("base") == 1.0

    def image_file(node) -> str:
        assert node.getCategory() == "image"
        file = node.getInput("file")
        assert file.getValueString() in names, file.getValueString()     # resolves in the zip
        return file.getValueString()

    colour = upstream(shader, "base_color")
    assert image_file(colour) == "baked_basecolor.png" and colour.getType() == "color3"
    assert colour.getInput("file").getColorSpace() == "srgb_texture"
    # data maps: vector3 / float images, which MaterialX's colour management leaves as they are
    normal_map = upstream(shader, "normal")
    assert normal_map.getCategory() == "normalmap"
    normal = upstream(normal_map, "in")
    assert image_file(normal) == "baked_normal.png" and normal.getType() == "vector3"
    roughness = upstream(shader, "specular_roughness")
    assert image_file(roughness) == "baked_roughness.png" and roughness.getType() == "float"
    for data in (normal, roughness):
        assert data.getInput("file").getColorSpace() == ""
    assert doc.getColorSpace() == "lin_rec709"
    # no standard_surface input for occlusion or displacement: named in the material's doc
    note = materials[0].getDocString()
    assert "baked_ao.png" in note and "baked_height.png" in note and {"baked_ao.png", "baked_height.png"} <= names


def test_obj_zip_materialx_without_maps_is_the_base_colour_alone(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "obj")
    with zipfile.ZipFile(result.path) as z:
        assert sorted(z.namelist()) == ["baked.mtl", "baked.mtlx", "baked.obj", "baked_basecolor.png"]
        doc = read_materialx(z.read("baked.mtlx").decode())
    shader = upstream(doc.getMaterialNodes()[0], "surfaceshader")
    assert upstream(shader, "base_color").getInput("file").getValueString() == "baked_basecolor.png"
    assert upstream(shader, "normal") is None and shader.getInputValue("specular_roughness") == 1.0   # as the GLB


# --- USDZ ----------------------------------------------------------------------------------

def validation_errors(stage) -> list[str]:
    """Every error USD's registered validators (usdchecker's) find on the stage."""
    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(stage)]


def package_layout(path) -> list[str]:
    """The USDZ's member names, checking what the format requires: stored (no compression)
    and each file's data 64-byte aligned."""
    with zipfile.ZipFile(path) as z, open(path, "rb") as f:
        for info in z.infolist():
            assert info.compress_type == zipfile.ZIP_STORED, info.filename
            f.seek(info.header_offset)
            name_length, extra_length = struct.unpack("<2H", f.read(30)[26:30])
            assert (info.header_offset + 30 + name_length + extra_length) % 64 == 0, info.filename
        return z.namelist()


def texture_file(shader, path) -> str:
    """The member a UsdUVTexture's file resolves to inside the package at ``path``."""
    asset = shader.GetInput("file").Get()
    assert asset.resolvedPath.startswith(f"{path}[") and asset.resolvedPath.endswith("]"), asset
    return asset.resolvedPath[len(str(path)) + 1:-1]


def source(shader_input):
    """(shader, output name) connected to a shader input."""
    connected, output, _ = shader_input.GetConnectedSource()
    return UsdShade.Shader(connected.GetPrim()), output


def test_usdz_bake_opens_in_usd_with_its_mesh_and_material(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path / "u", "usdz", maps=("ao", "normal", "roughness"))
    assert result.path == tmp_path / "u" / "baked.usdz" and result.height_range is None
    members = package_layout(result.path)
    assert members[0] == "baked.usdc"                      # the root layer first
    assert sorted(members[1:]) == ["baked_ao.png", "baked_basecolor.png", "baked_normal.png", "baked_roughness.png"]
    stage = Usd.Stage.Open(str(result.path))
    assert validation_errors(stage) == []
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/texspace"

    # the same mesh as the GLB bake: positions, triangles, normals, UVs (glTF's t = 1 - v)
    gltf, binary = glb_parts(bake(waves, meshes, tmp_path / "g", "glb").path.read_bytes())
    primitive = gltf["meshes"][0]["primitives"][0]

    def accessor(index, dtype, width):
        acc = gltf["accessors"][index]
        return np.frombuffer(binary, dtype, count=acc["count"] * width,
                             offset=gltf["bufferViews"][acc["bufferView"]]["byteOffset"]).reshape(-1, width)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/texspace/mesh"))
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    assert len(counts) == result.faces and (counts == 3).all()
    assert np.array_equal(indices, accessor(primitive["indices"], "<u4", 1).reshape(-1, 3))
    assert np.array_equal(np.asarray(mesh.GetPointsAttr().Get()), accessor(primitive["attributes"]["POSITION"], "<f4", 3))
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none" and mesh.GetNormalsInterpolation() == "vertex"
    assert np.allclose(np.asarray(mesh.GetNormalsAttr().Get()), accessor(primitive["attributes"]["NORMAL"], "<f4", 3))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetTypeName() == Sdf.ValueTypeNames.TexCoord2fArray and st.GetInterpolation() == "vertex"
    gltf_uv = accessor(primitive["attributes"]["TEXCOORD_0"], "<f4", 2)
    assert np.allclose(np.asarray(st.Get()), np.stack([gltf_uv[:, 0], 1 - gltf_uv[:, 1]], axis=1), atol=1e-6)

    # the material bound to the mesh: a UsdPreviewSurface reading each texture through st
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == "/texspace/material"
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface" and surface.GetInput("metallic").Get() == 0.0
    found = {}
    for slot, output, space in (("diffuseColor", "rgb", "sRGB"), ("normal", "rgb", "raw"),
                                ("roughness", "r", "raw"), ("occlusion", "r", "raw")):
        texture, name = source(surface.GetInput(slot))
        assert texture.GetIdAttr().Get() == "UsdUVTexture" and name == output, slot
        assert texture.GetInput("sourceColorSpace").Get() == space, slot
        reader, _ = source(texture.GetInput("st"))
        assert reader.GetIdAttr().Get() == "UsdPrimvarReader_float2" and reader.GetInput("varname").Get() == "st"
        found[slot] = texture_file(texture, result.path)
    assert found == {"diffuseColor": "baked_basecolor.png", "normal": "baked_normal.png",
                     "roughness": "baked_roughness.png", "occlusion": "baked_ao.png"}
    normal_texture, _ = source(surface.GetInput("normal"))
    assert tuple(normal_texture.GetInput("scale").Get()) == (2, 2, 2, 1)
    assert tuple(normal_texture.GetInput("bias").Get()) == (-1, -1, -1, 0)
    # the packed base colour is the GLB's, pixel for pixel
    with zipfile.ZipFile(result.path) as z:
        packed = np.asarray(Image.open(io.BytesIO(z.read("baked_basecolor.png"))).convert("RGB"))
    assert packed.shape == (RES, RES, 3) and np.array_equal(packed, np.asarray(image_of(gltf, binary, 0).convert("RGB")))


def test_usdz_without_maps_is_rough_and_textured(waves, meshes, tmp_path):
    result = bake(waves, meshes, tmp_path, "usdz")
    assert package_layout(result.path) == ["baked.usdc", "baked_basecolor.png"]
    stage = Usd.Stage.Open(str(result.path))
    assert validation_errors(stage) == []
    surface = UsdShade.Material(stage.GetPrimAtPath("/texspace/material")).ComputeSurfaceSource()[0]
    assert surface.GetInput("roughness").Get() == 1.0 and not surface.GetInput("normal")
    assert texture_file(source(surface.GetInput("diffuseColor"))[0], result.path) == "baked_basecolor.png"


def test_usdz_with_height_and_gpu_textures_becomes_a_zip(waves, meshes, tmp_path):
    """USDZ holds neither a height map (not connected) nor DDS / KTX2: they go beside it."""
    result = bake(waves, meshes, tmp_path, "usdz", maps=("height", "normal"), gpu_format="dds")
    assert result.path == tmp_path / "baked.zip" and sorted(p.name for p in tmp_path.iterdir()) == ["baked.zip"]
    assert result.height_range is not None
    with zipfile.ZipFile(result.path) as z:
        assert sorted(z.namelist()) == ["baked.usdz", "baked_basecolor.dds", "baked_height.png"]
        z.extract("baked.usdz", tmp_path / "x")
    package = tmp_path / "x" / "baked.usdz"
    assert sorted(package_layout(package)) == ["baked.usdc", "baked_basecolor.png", "baked_normal.png"]
    stage = Usd.Stage.Open(str(package))
    assert validation_errors(stage) == []
    surface = UsdShade.Material(stage.GetPrimAtPath("/texspace/material")).ComputeSurfaceSource()[0]
    assert texture_file(source(surface.GetInput("normal"))[0], package) == "baked_normal.png"


def test_the_libraries_load_only_when_a_file_is_written():
    """The API and the worker start without MaterialX, pxr or etcpak: each is imported inside
    the function that writes with it."""
    script = ("import sys, service.main, service.job_kinds, worker.bake, worker.regions; "
              "print(sorted(m for m in ('MaterialX', 'pxr', 'etcpak') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip() == "[]"
