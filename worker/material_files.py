"""Material files beside a bake's maps: a MaterialX document (the OBJ zip's ``<stem>.mtlx``)
and a USDZ package (``format="usdz"``: mesh, UVs, normals and a bound UsdPreviewSurface
material with its textures inside).

Both name the same files the bake writes (``<stem>_basecolor.png`` and the derived maps
``<stem>_normal.png``, ``<stem>_roughness.png``, ``<stem>_ao.png``; ``worker/derived_maps.py``),
by paths relative to themselves, and say what each file's values are:

* base colour: 8-bit sRGB codes (MaterialX ``colorspace="srgb_texture"``, USD
  ``sourceColorSpace = "sRGB"``);
* normal: tangent space, +Y up (what ``normal_map`` writes, glTF's and USD's convention),
  ``(n + 1) / 2`` per channel, data (MaterialX ``normalmap`` node on a ``vector3`` image,
  which no colour transform touches; USD ``raw`` with scale 2 and bias -1);
* roughness, ambient occlusion: 0..1 data (MaterialX ``float`` images; USD ``raw``).

The material is dielectric (metalness 0) and, without a roughness map, fully rough (1), as
the GLB's glTF material is. MaterialX's ``standard_surface`` has no occlusion input, so the
document names the AO map in its ``doc`` string only (as the MTL names it in a comment);
UsdPreviewSurface takes it as ``occlusion``. The height map is connected to neither: a
displacement needs a height in scene units, and the colour-derived height has none (its
relief is in the normal map already).

USD layout: the stage is Y up, 1 metre per unit (the GLB's reading of the same vertices);
``/texspace`` (the default prim, an Xform) holds the mesh ``/texspace/mesh`` (triangles,
``subdivisionScheme = "none"`` so renderers keep the flat triangles and the file's
normals, vertex ``normals``, vertex ``primvars:st`` with v up) bound to
``/texspace/material``. The package is a USDZ (an uncompressed zip, 64-byte aligned, its
first member the root layer ``<stem>.usdc``), written by ``Sdf.ZipFileWriter``.

The libraries (MaterialX, ``usd-core``'s pxr) are imported inside the writers, so neither
the API's start-up nor a bake that makes no such file pays for them.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from worker.derived_maps import map_file
from worker.files import member_name

#: the maps a material connects (height is shipped beside, never connected: module doc)
MATERIAL_MAPS = ("normal", "roughness", "ao")
#: the USD prims of a bake's package
USD_ROOT, USD_MESH, USD_MATERIAL = "/texspace", "/texspace/mesh", "/texspace/material"
ROUGHNESS_WITHOUT_MAP = 1.0      # the GLB's roughnessFactor: fully rough, no highlight


def base_colour_file(stem: str) -> str:
    """The base colour PNG's name in a bake's files: ``<stem>_basecolor.png``."""
    return member_name(stem, "basecolor", ".png")


def materialx_document(stem: str, maps=()) -> str:
    """A MaterialX 1.39 document (XML text) with one ``surfacematerial`` named after
    ``stem``: a ``standard_surface`` whose base colour is ``<stem>_basecolor.png`` (sRGB)
    and, among ``maps``, whose normal is ``<stem>_normal.png`` through a tangent-space
    ``normalmap`` node and whose specular roughness is ``<stem>_roughness.png``; an AO or
    height map is named in the material's ``doc`` (module doc). Validated with
    ``Document.validate`` against MaterialX's standard libraries before it is returned."""
    import MaterialX as mx   # here, not at import: the API's start-up need not load it

    maps = set(maps)
    doc = mx.createDocument()
    doc.setColorSpace("lin_rec709")      # what unmarked colour inputs are; data inputs take no transform
    colour = doc.addNode("image", "base_color_image", "color3")
    colour.setInputValue("file", base_colour_file(stem), "filename").setColorSpace("srgb_texture")
    shader = doc.addNode("standard_surface", "surface", "surfaceshader")
    shader.setInputValue("base", 1.0, "float")                 # the baked colour as it is
    shader.addInput("base_color", "color3").setConnectedNode(colour)
    shader.setInputValue("metalness", 0.0, "float")
    if "normal" in maps:
        normal = doc.addNode("image", "normal_image", "vector3")
        normal.setInputValue("file", map_file("normal", stem), "filename")
        tangent_space = doc.addNode("normalmap", "normal_map", "vector3")
        tangent_space.addInput("in", "vector3").setConnectedNode(normal)
        shader.addInput("normal", "vector3").setConnectedNode(tangent_space)
    if "roughness" in maps:
        roughness = doc.addNode("image", "roughness_image", "float")
        roughness.setInputValue("file", map_file("roughness", stem), "filename")
        shader.addInput("specular_roughness", "float").setConnectedNode(roughness)
    else:
        shader.setInputValue("specular_roughness", ROUGHNESS_WITHOUT_MAP, "float")
    material = doc.addNode("surfacematerial", mx.createValidName(stem), "material")   # "oak-planks" -> "oak_planks"
    material.addInput("surfaceshader", "surfaceshader").setConnectedNode(shader)
    notes = ["texspace bake: base colour sRGB, normal map tangent space +Y up"]
    if "ao" in maps:
        notes.append(f"ambient occlusion (standard_surface has no input for it): {map_file('ao', stem)}")
    if "height" in maps:
        notes.append(f"height, not connected (no scene-unit scale): {map_file('height', stem)}")
    material.setDocString("; ".join(notes))
    _check_materialx(mx, doc)
    return mx.writeToXmlString(doc)


def _check_materialx(mx, doc) -> None:
    """Validate ``doc`` with MaterialX's standard libraries imported (node definitions and
    types checked too); a failure is a bug here, not the user's, so it raises."""
    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    checked = doc.copy()
    checked.setDataLibrary(library)
    valid, message = checked.validate()
    if not valid:
        raise RuntimeError(f"MaterialX document invalid: {message}")


def usdz_bytes(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, normals: np.ndarray, stem: str,
               textures: dict[str, bytes]) -> bytes:
    """A USDZ package of the bake (module doc): ``vertices`` (V, 3), ``faces`` (F, 3) int,
    ``uv`` (V, 2) with v up, ``normals`` (V, 3); ``textures``: {file name: PNG bytes}, the
    base colour (``base_colour_file(stem)``) and any of the maps in MATERIAL_MAPS by their
    ``map_file`` names, each packed and connected to the material."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt   # here, not at import (module doc)

    colour = base_colour_file(stem)
    if colour not in textures:
        raise ValueError(f"the base colour {colour} is missing")
    with tempfile.TemporaryDirectory(prefix="texspace-usdz-") as folder:
        root = Path(folder) / member_name(stem, "", ".usdc")
        stage = Usd.Stage.CreateNew(str(root))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, USD_ROOT).GetPrim())

        mesh = UsdGeom.Mesh.Define(stage, USD_MESH)
        points = np.ascontiguousarray(vertices, dtype=np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*points.min(axis=0).tolist()),
                                             Gf.Vec3f(*points.max(axis=0).tolist())]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32).ravel()))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(uv, dtype=np.float32)))

        material = UsdShade.Material.Define(stage, USD_MATERIAL)
        surface = UsdShade.Shader.Define(stage, f"{USD_MATERIAL}/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
        surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        reader = UsdShade.Shader.Define(stage, f"{USD_MATERIAL}/st_reader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

        def texture(name: str, file: str, colour_space: str, output: str, output_type):
            """A UsdUVTexture of ``file`` read through the st primvar; its ``output``."""
            shader = UsdShade.Shader.Define(stage, f"{USD_MATERIAL}/{name}")
            shader.CreateIdAttr("UsdUVTexture")
            shader.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{file}"))
            shader.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
            shader.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
            for wrap in ("wrapS", "wrapT"):   # an atlas: past its border is the gutter's colour, not a repeat
                shader.CreateInput(wrap, Sdf.ValueTypeNames.Token).Set("clamp")
            return shader, shader.CreateOutput(output, output_type)

        _, rgb = texture("base_color_texture", colour, "sRGB", "rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
        if map_file("normal", stem) in textures:
            shader, rgb = texture("normal_texture", map_file("normal", stem), "raw", "rgb",
                                  Sdf.ValueTypeNames.Float3)
            # (n + 1) / 2 codes back to -1..1 (UsdPreviewSurface's normal: tangent space, +Y up)
            shader.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2, 2, 2, 1))
            shader.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1, -1, -1, 0))
            surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(rgb)
        roughness = surface.CreateInput("roughness", Sdf.ValueTypeNames.Float)
        if map_file("roughness", stem) in textures:
            roughness.ConnectToSource(texture("roughness_texture", map_file("roughness", stem), "raw", "r",
                                              Sdf.ValueTypeNames.Float)[1])
        else:
            roughness.Set(ROUGHNESS_WITHOUT_MAP)
        if map_file("ao", stem) in textures:
            surface.CreateInput("occlusion", Sdf.ValueTypeNames.Float).ConnectToSource(
                texture("occlusion_texture", map_file("ao", stem), "raw", "r", Sdf.ValueTypeNames.Float)[1])
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        stage.GetRootLayer().Save()

        package = Path(folder) / member_name(stem, "", ".usdz")
        writer = Sdf.ZipFileWriter.CreateNew(str(package))
        writer.AddFile(str(root), root.name)              # the root layer first, as USDZ requires
        for name, data in textures.items():
            (Path(folder) / name).write_bytes(data)
            writer.AddFile(str(Path(folder) / name), name)
        writer.Save()
        return package.read_bytes()
