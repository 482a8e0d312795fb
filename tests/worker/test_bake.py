"""UV bakes: atlas choice and cache, coverage, gutter, colours through the saved file,
vertex normals, bad meshes."""
import io
import json
import os
import shutil
import struct
import subprocess
import time
import zipfile

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy import ndimage
from skimage.draw import polygon

from worker import atlas
from worker.bake import BakeLimits, bake_mesh, bake_texture, load_mesh, obj_face_problem, read_mesh, read_plain_obj
from worker.colour import linear_to_srgb8
from worker.errors import AtlasFailed, Canceled, InvalidMesh, InvalidParameter, LimitExceeded
from worker.raster import uv_to_texel
from worker.triplanar import projected_points, sample_triplanar, triplanar_weights

RES = 128


class Counting:
    """Wraps a sampler and records how many points it was asked for."""

    def __init__(self, inner):
        self.inner, self.points = inner, 0
        self.pixels_per_unit = inner.pixels_per_unit

    def sample(self, points, code, seed):
        self.points += len(points)
        return self.inner.sample(points, code, seed)


def glb_texture_and_mesh(path):
    mesh = trimesh.load(str(path), force="mesh", process=False)
    image = np.asarray(mesh.visual.material.baseColorTexture.convert("RGB"))
    return mesh, image


def chart_mask(uv, faces, res):
    """Independent rasteriser (skimage polygon, centre-inside rule) of all UV triangles."""
    mask = np.zeros((res, res), bool)
    for tri in uv_to_texel(uv[faces], res):
        rr, cc = polygon(tri[:, 1] - 0.5, tri[:, 0] - 0.5, (res, res))
        mask[rr, cc] = True
    return mask


def copies_a_nearest_covered_texel(image: np.ndarray, covered: np.ndarray, dist: np.ndarray,
                                    reach: int = 4) -> np.ndarray:
    """(R, R) bool: the texel's colour is that of some covered texel at its distance
    ``dist`` from coverage (ties between equally near texels may go either way)."""
    R = len(covered)
    padded = np.pad(image, ((reach, reach), (reach, reach), (0, 0)))
    padded_cov = np.pad(covered, reach)
    found = np.zeros(covered.shape, bool)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            window = (slice(reach + dy, reach + dy + R), slice(reach + dx, reach + dx + R))
            same = (padded[window] == image).all(axis=2) & padded_cov[window]
            found |= same & np.isclose(np.hypot(dy, dx), dist)
    return found


def test_uvless_mesh_gets_an_atlas_and_a_loadable_glb(runtime, code, meshes, tmp_path):
    seen = []
    result = bake_mesh(runtime, code, 2, mesh_bytes=(meshes / "bunny.obj").read_bytes(),
                       filename="bunny.obj", resolution=RES, out_path=tmp_path / "b.glb",
                       progress=seen.append)
    assert result.uv_source == "xatlas" and result.faces == 902
    assert seen == sorted(seen) and seen[-1] == 1.0
    mesh, image = glb_texture_and_mesh(result.path)
    assert len(mesh.faces) == 902 and image.shape == (RES, RES, 3)
    assert np.allclose(mesh.visual.material.baseColorFactor, 255)   # white: texture not darkened
    assert os.listdir(tmp_path) == ["b.glb"]


def test_mesh_uvs_kept_and_coverage_exact(runtime, code, meshes, tmp_path):
    data = (meshes / "bunny_uv.obj").read_bytes()
    vertices, faces, uv = load_mesh(data, "bunny_uv.obj")
    counting = Counting(runtime)
    result = bake_mesh(counting, code, 2, mesh_bytes=data, filename="bunny_uv.obj", resolution=RES,
                       out_path=tmp_path / "b.glb", padding=4)
    assert result.uv_source == "mesh"
    mesh, image = glb_texture_and_mesh(result.path)
    assert np.allclose(mesh.visual.uv, uv, atol=1e-6)              # the mesh's own UVs, unchanged
    # Covered texels == an independent rasterisation of the charts: no holes inside a chart,
    # nothing outside; and the sampler ran on covered texels only.
    mask = chart_mask(uv, faces, RES)
    assert (result.covered != mask).sum() <= 0.002 * mask.sum()
    assert counting.points == result.covered.sum()
    # Gutter: every texel within the padding copies a nearest covered texel (never black).
    dist = ndimage.distance_transform_edt(~result.covered)
    near = (dist <= 4) & ~result.covered
    assert near.sum() > 0 and copies_a_nearest_covered_texel(image, result.covered, dist)[near].all()
    assert image[near].max(axis=1).min() > 0
    assert (image[dist > 4] == 0).all()                              # beyond the padding: untouched


def test_colours_land_where_the_surface_is(waves, meshes, tmp_path):
    # A strongly varying texture shows any UV mix-up (e.g. a missing v flip) at once.
    data = (meshes / "bunny_uv.obj").read_bytes()
    result = bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny_uv.obj", resolution=512,
                       scale=20.0, out_path=tmp_path / "w.glb")
    mesh, image = glb_texture_and_mesh(result.path)
    tri_uv, tri_xyz = mesh.visual.uv[mesh.faces], mesh.vertices[mesh.faces]
    centre_uv, centre_xyz = tri_uv.mean(axis=1), tri_xyz.mean(axis=1)
    col, row = np.floor(uv_to_texel(centre_uv, 512)).astype(int).T
    inside = result.covered[row, col]
    assert inside.mean() > 0.9
    expected = linear_to_srgb8(waves.sample(centre_xyz[inside] * 20.0, None, 0)).astype(int)
    error = np.abs(image[row[inside], col[inside]].astype(int) - expected).mean()
    flipped = np.abs(image[511 - row[inside], col[inside]].astype(int) - expected).mean()
    assert error < 6 and flipped > 5 * error


def test_obj_zip_with_exr(runtime, code, meshes, tmp_path):
    result = bake_mesh(runtime, code, 2, mesh_bytes=(meshes / "cube.obj").read_bytes(),
                       filename="cube.obj", resolution=64, fmt="obj", exr=True,
                       out_path=tmp_path / "c.zip")
    assert result.uv_source == "xatlas"                 # the cube's 6 faces share one UV square
    folder = tmp_path / "unzipped"
    zipfile.ZipFile(result.path).extractall(folder)
    # members named after the result, so two bakes extracted into one folder keep their files
    assert sorted(os.listdir(folder)) == ["c.mtl", "c.mtlx", "c.obj", "c_basecolor.exr", "c_basecolor.png"]
    mtl = (folder / "c.mtl").read_text()
    assert "Kd 1 1 1" in mtl and "map_Kd c_basecolor.png" in mtl and "mtllib c.mtl" in (folder / "c.obj").read_text()
    mesh = trimesh.load(str(folder / "c.obj"), process=False, force="mesh")
    assert len(mesh.faces) == 12 and mesh.visual.uv.shape == (len(mesh.vertices), 2)
    assert Image.open(folder / "c_basecolor.png").size == (64, 64)


def test_other_mesh_types(waves, meshes, tmp_path):
    bunny = trimesh.load(str(meshes / "bunny.obj"), process=False, force="mesh")
    for ext in ("ply", "stl", "glb"):
        result = bake_mesh(waves, None, 0, mesh_bytes=bunny.export(file_type=ext),
                           filename=f"bunny.{ext}", resolution=64, out_path=tmp_path / f"{ext}.glb")
        assert result.faces == 902 and result.covered.sum() > 0


BAD_MESHES = [
    ("nan.obj", b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "NaN"),
    ("range.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n",
     r"face 2 \(line 5\) names vertex 9; the file has 3 vertices"),
    ("range-slashes.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 4/1\n",
     r"face 1 \(line 5\) names vertex 4; the file has 3 vertices"),
    ("zero.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 0\n",      # trimesh reads 0 as
     r"face 2 \(line 6\) names vertex 0; the file has 4 vertices"),               # vertex 4: a wrong face
    ("zero-flat.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "names vertex 0"),  # was "degenerate"
    ("nofaces.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("flat.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate"),
    ("garbage.glb", b"glTF not really" * 10, "cannot parse"),
    ("empty.obj", b"", "empty"),
    ("mesh.fbx", b"anything", "unsupported"),
    ("huge.obj", b"v 0 0 0\nv 1e100 0 0\nv 0 1e100 0\nf 1 2 3\n", "beyond"),        # was 500 (overflow)
    ("far.obj", b"v 1e30 0 0\nv 1e60 0 0\nv 0 1e45 0\nv 0 0 1e30\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 4\n",
     "beyond"),                                                                    # was 120 s of xatlas
]


@pytest.mark.parametrize("filename, data, message", BAD_MESHES)
def test_bad_meshes(filename, data, message):
    with pytest.raises(InvalidMesh, match=message):
        load_mesh(data, filename)


def test_obj_face_problem_names_the_face_and_its_line():
    """What a bad OBJ's upload is told (``read_mesh`` asks only when the mesh failed)."""
    assert obj_face_problem(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n") is None
    assert obj_face_problem(b"v 0 0 0\nv 1 0 0\nf -1 -2 -3\nv 0 1 0\n") == \
        "face 1 (line 3) names vertex -3; 2 vertices come before it"
    assert obj_face_problem(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n") == \
        "face 1 (line 4) has a corner 'x' that is not a vertex number"


def test_lone_zeros_outside_faces_are_no_vertex_zero():
    """Zero coordinates, zero texture indices and zeros in comments load as they are."""
    vertices, faces, uv = load_mesh(b"# f 0 1 2\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
                                    b"f 1/1 2/2 3/3\n", "zeros.obj")
    assert faces.tolist() == [[0, 1, 2]] and vertices[0].tolist() == [0, 0, 0]


def test_mesh_limits(meshes):
    with pytest.raises(LimitExceeded, match="902 faces"):
        load_mesh((meshes / "bunny.obj").read_bytes(), "bunny.obj", BakeLimits(max_faces=900))


def test_plain_obj_reads_as_trimesh_does(meshes):
    """The fast path for v/f-only OBJs gives trimesh's arrays, bit for bit (so the atlas
    cache, keyed by them, hits either way); anything else falls back to trimesh."""
    rng = np.random.default_rng(4)
    bunny = trimesh.load(str(meshes / "bunny.obj"), process=False, force="mesh")
    vertices = np.vstack([bunny.vertices + rng.normal(0, 1e-3, bunny.vertices.shape), [[5.0, 5.0, 5.0]]])
    buf = io.StringIO()      # an unreferenced vertex (the last) and exponent notation
    np.savetxt(buf, vertices, fmt="v %.9g %.9e %.7f")
    np.savetxt(buf, bunny.faces + 1, fmt="f %d %d %d")
    data = buf.getvalue().encode()
    want = trimesh.load(io.BytesIO(data), file_type="obj", process=False)
    got = read_plain_obj(data)
    assert got is not None and np.array_equal(got[0], want.vertices) and np.array_equal(got[1], want.faces)
    assert len(got[0]) == len(vertices) - 1
    assert np.array_equal(read_plain_obj(data.rstrip(b"\n"))[1], want.faces)      # no final newline
    written = bunny.export(file_type="obj", include_normals=False).encode()   # a comment and "o bunny" first
    assert written.startswith(b"#") and b"\no bunny\n" in written
    loaded = trimesh.load(io.BytesIO(written), file_type="obj", process=False, force="mesh")
    vertices, faces = read_plain_obj(written)
    assert np.array_equal(vertices, loaded.vertices) and np.array_equal(faces, loaded.faces)
    assert read_plain_obj(b"# only a comment") is None
    mesh = read_mesh(data, "plain.obj")
    assert np.array_equal(mesh.vertices, want.vertices) and mesh.uv is None and mesh.normals is None
    square = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"
    for other in (square + b"f 1 2 3 4\nf 1 2\n",         # a quad and a short line: same count of numbers
                  square + b"f 1 2 3\nf -1 -2 -3\n",      # relative indices
                  square + b"f 1/1 2/2 3/3\n",             # texture indices
                  square + b"vn 0 0 1\nf 1 2 3\n",
                  square.replace(b"\n", b"\r\n") + b"f 1 2 3\r\n",
                  square + b"f 1 2 3 \n",
                  square + b"usemtl stone\nf 1 2 3\n",
                  square + b"f 1 2 3\nv 2 2 2\n",
                  b"v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 0 1 0 1 0 0\nf 1 2 3\n"):   # vertex colours
        assert read_plain_obj(other) is None, other
    assert read_mesh(square + b"f 1 2 3 4\n", "quad.obj").faces.shape == (2, 3)   # trimesh's path


@pytest.fixture
def atlas_fault(monkeypatch):
    """Make the xatlas child fail: atlas_fault("segfault" | "abort" | "hang")."""
    from worker import atlas

    def set_fault(fault):
        monkeypatch.setattr(atlas, "CHILD_MODULE", "tests.worker.atlas_child_faults")
        monkeypatch.setenv("TEXSPACE_TEST_ATLAS_FAULT", fault)

    yield set_fault


@pytest.mark.parametrize("fault", ["segfault", "abort"])
def test_an_atlas_crash_is_contained_and_the_bake_takes_box_charts(waves, meshes, tmp_path, fault, atlas_fault,
                                                                   monkeypatch, caplog):
    data = (meshes / "bunny.obj").read_bytes()
    atlas_fault(fault)
    result = bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                       out_path=tmp_path / "x.glb")
    assert result.uv_source == "box" and result.path.is_file() and result.faces == 902
    assert "signal" in caplog.text and "box-projected charts" in caplog.text
    monkeypatch.undo()
    # this process is alive and the next bake gets xatlas's atlas
    assert bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                     out_path=tmp_path / "y.glb").uv_source == "xatlas"


def test_an_atlas_past_its_share_of_the_budget_gives_way_to_box_charts(waves, meshes, tmp_path, atlas_fault):
    atlas_fault("hang")
    started = time.monotonic()
    result = bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny.obj").read_bytes(), filename="bunny.obj",
                       resolution=64, out_path=tmp_path / "x.glb", limits=BakeLimits(atlas_timeout=4))
    assert result.uv_source == "box" and time.monotonic() - started < 4  # xatlas had half of it


def noisy_sphere(subdivisions: int = 4, noise: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere whose vertices are moved by ``noise`` edge lengths at random: a scan's
    noise, on which xatlas cuts thousands of charts and runs for minutes at 100k faces."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces, np.int64)
    edge = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1).mean()
    return vertices + np.random.default_rng(0).normal(0, noise * edge, vertices.shape), faces


@pytest.mark.parametrize("noise, overlap", [(0.0, 0.0), (0.3, 0.01)])
def test_box_charts_cover_every_face_with_little_overlap_or_stretch(noise, overlap):
    """A clean surface's charts overlap nowhere; a scan's noise folds the surface over itself
    in places (front, back, front), and those folds' front faces share a few texels."""
    from worker.box_charts import box_charts

    vertices, faces = noisy_sphere(noise=noise)
    vmap, new_faces, uv = box_charts(vertices, faces, resolution=512, padding=2)
    assert new_faces.shape == faces.shape and uv.min() >= 0 and uv.max() <= 1
    assert np.array_equal(vmap[new_faces], faces)  # each face keeps its corners
    quality = atlas.atlas_quality(vertices[vmap], new_faces, uv)
    assert quality["uv_degenerate_area"] == 0 and quality["stretch_l2"] < 1.2 and quality["uv_area"] > 0.15
    # rasterise every face's UV triangle at the packing resolution, counting the faces on each texel
    n = 512
    hits = np.zeros((n, n), np.int32)
    texel = (np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="xy"), -1) + 0.5) / n
    for tri in uv[new_faces]:
        lo, hi = np.floor(tri.min(0) * n).astype(int), np.ceil(tri.max(0) * n).astype(int)
        window = texel[lo[1]:hi[1], lo[0]:hi[0]]
        a, b, c = tri
        d = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        w1 = ((window[..., 0] - a[0]) * (c[1] - a[1]) - (window[..., 1] - a[1]) * (c[0] - a[0])) / d
        w2 = ((b[0] - a[0]) * (window[..., 1] - a[1]) - (b[1] - a[1]) * (window[..., 0] - a[0])) / d
        inside = (w1 > 1e-9) & (w2 > 1e-9) & (w1 + w2 < 1 - 1e-9)
        hits[lo[1]:hi[1], lo[0]:hi[0]] += inside
    assert (hits > 1).sum() <= overlap * (hits > 0).sum()


def test_cancel(waves, meshes, tmp_path):
    with pytest.raises(Canceled):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny_uv.obj").read_bytes(),
                  filename="bunny_uv.obj", resolution=64, out_path=tmp_path / "x.glb",
                  should_cancel=lambda: True)
    assert os.listdir(tmp_path) == []


def test_cancel_ends_the_atlas_child(waves, meshes, tmp_path, atlas_fault):
    """A cancel while xatlas runs kills its child within a poll, not at the atlas timeout."""
    atlas_fault("hang")
    started = time.monotonic()
    with pytest.raises(Canceled, match="atlas"):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny.obj").read_bytes(), filename="bunny.obj",
                  resolution=64, out_path=tmp_path / "x.glb",
                  should_cancel=lambda: time.monotonic() - started > 1.0)
    assert time.monotonic() - started < 10


# --- vertex normals (meshes that shade well) --------------------------------------------

def glb_json_and_arrays(path):
    """The glTF JSON of a GLB and its accessors as numpy arrays (float32 / uint32 only)."""
    data = path.read_bytes()
    json_len, = struct.unpack_from("<I", data, 12)
    gltf = json.loads(data[20:20 + json_len])
    binary = data[28 + json_len:]
    dtypes, widths = {5126: np.float32, 5125: np.uint32}, {"SCALAR": 1, "VEC2": 2, "VEC3": 3}
    arrays = []
    for acc in gltf["accessors"]:
        view = gltf["bufferViews"][acc["bufferView"]]
        flat = np.frombuffer(binary, dtypes[acc["componentType"]], acc["count"] * widths[acc["type"]],
                             view["byteOffset"] + acc.get("byteOffset", 0))
        arrays.append(flat.reshape(acc["count"], -1))
    return gltf, arrays


def test_glb_carries_smooth_unit_normals_shared_across_seams(waves, meshes, tmp_path):
    result = bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny.obj").read_bytes(), filename="bunny.obj",
                       resolution=64, out_path=tmp_path / "b.glb")
    gltf, arrays = glb_json_and_arrays(result.path)
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
    position, normal = arrays[attributes["POSITION"]], arrays[attributes["NORMAL"]]
    assert normal.shape == position.shape and np.abs(np.linalg.norm(normal, axis=1) - 1).max() < 1e-6
    # xatlas split vertices at chart seams: every copy of a position has the same normal (no seam shading)
    _, weld = np.unique(position, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    assert len(np.unique(weld)) < len(position)
    first = np.zeros(weld.max() + 1, int)
    first[weld[::-1]] = np.arange(len(weld))[::-1]
    assert np.abs(normal - normal[first[weld]]).max() < 1e-6
    # and they are the area-weighted mean of the original bunny's face normals
    bunny = trimesh.load(str(meshes / "bunny.obj"), process=False, force="mesh")
    tri = bunny.vertices[bunny.faces]
    summed = np.zeros_like(bunny.vertices)
    np.add.at(summed, bunny.faces.ravel(), np.repeat(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), 3, axis=0))
    summed /= np.linalg.norm(summed, axis=1, keepdims=True)
    index = {tuple(np.float32(p)): n for p, n in zip(bunny.vertices, summed)}
    reference = np.array([index[tuple(p)] for p in position])
    assert np.abs(reference - normal).max() < 1e-5
    assert ((summed[bunny.faces[:, 0]] * bunny.face_normals).sum(axis=1) > 0).mean() > 0.95   # outward


def test_mesh_normals_are_kept_in_glb_and_obj(waves, meshes, tmp_path):
    """An OBJ with vn (and a GLB with NORMAL) keeps its own normals: here deliberately not
    smooth ones (each points away from the origin), so a recomputation would show."""
    source = trimesh.load(str(meshes / "bunny_uv.obj"), process=False, force="mesh")
    own = source.vertices / np.linalg.norm(source.vertices, axis=1, keepdims=True)
    text = io.StringIO()
    np.savetxt(text, source.vertices, fmt="v %.9g %.9g %.9g")
    np.savetxt(text, source.visual.uv, fmt="vt %.9g %.9g")
    np.savetxt(text, own, fmt="vn %.9g %.9g %.9g")
    np.savetxt(text, np.repeat(source.faces + 1, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    obj = text.getvalue().encode()
    assert read_mesh(obj, "own.obj").normals is not None
    assert read_mesh((meshes / "bunny_uv.obj").read_bytes(), "bunny_uv.obj").normals is None
    glb_in = trimesh.Trimesh(source.vertices, source.faces, vertex_normals=own, process=False).export(
        file_type="glb", include_normals=True)
    for data, name, fmt in ((obj, "own.obj", "glb"), (obj, "own.obj", "obj"), (glb_in, "own.glb", "glb")):
        result = bake_mesh(waves, None, 0, mesh_bytes=data, filename=name, resolution=64, fmt=fmt,
                           out_path=tmp_path / f"{name[:-4]}.{fmt}")
        if fmt == "glb":
            gltf, arrays = glb_json_and_arrays(result.path)
            attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
            position, normal = arrays[attributes["POSITION"]], arrays[attributes["NORMAL"]]
        else:
            folder = tmp_path / f"{name}-unzipped"
            zipfile.ZipFile(result.path).extractall(folder)
            assert "\nvn " in (folder / "own.obj").read_text()
            mesh = trimesh.load(str(folder / "own.obj"), process=False)
            position, normal = mesh.vertices, mesh.vertex_normals
        expected = position / np.linalg.norm(position, axis=1, keepdims=True)
        assert np.abs(normal - expected).max() < 1e-5, (name, fmt)


def test_degenerate_mesh_uvs_get_an_atlas(waves, meshes, tmp_path):
    source = trimesh.load(str(meshes / "bunny_uv.obj"), process=False, force="mesh")
    uv = np.array(source.visual.uv)
    uv[source.faces[:300].ravel()] = 0.5                     # a third of the faces collapse to a point
    text = io.StringIO()
    np.savetxt(text, source.vertices, fmt="v %.9g %.9g %.9g")
    np.savetxt(text, uv, fmt="vt %.9g %.9g")
    np.savetxt(text, np.repeat(source.faces + 1, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
    result = bake_mesh(waves, None, 0, mesh_bytes=text.getvalue().encode(), filename="d.obj", resolution=64,
                       out_path=tmp_path / "d.glb")
    assert result.uv_source == "xatlas"


VALIDATOR_DIR = os.environ.get("TEXSPACE_GLTF_VALIDATOR_DIR")   # a folder with node_modules/gltf-validator


@pytest.mark.skipif(not (VALIDATOR_DIR and shutil.which("node")),
                    reason="Khronos glTF validator not installed (npm install gltf-validator; "
                           "set TEXSPACE_GLTF_VALIDATOR_DIR to that folder)")
def test_glb_passes_the_khronos_validator(waves, meshes, tmp_path):
    script = ("const v=require('gltf-validator');const fs=require('fs');"
              "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
              ".then(r=>console.log(JSON.stringify(r.issues)))")
    for name in ("bunny.obj", "bunny_uv.obj", "textured_sphere_smooth.obj"):
        result = bake_mesh(waves, None, 0, mesh_bytes=(meshes / name).read_bytes(), filename=name, resolution=64,
                           out_path=tmp_path / f"{name}.glb")
        out = subprocess.run(["node", "-e", script, str(result.path)], cwd=VALIDATOR_DIR, capture_output=True,
                             text=True, timeout=120, check=True)
        issues = json.loads(out.stdout)
        assert (issues["numErrors"], issues["numWarnings"]) == (0, 0), issues["messages"][:5]


# --- UV atlas cache --------------------------------------------------------------------

def test_second_bake_of_a_mesh_loads_its_atlas(waves, meshes, tmp_path, monkeypatch):
    data = (meshes / "bunny.obj").read_bytes()
    cache = tmp_path / "atlas-cache"
    first = bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                      out_path=tmp_path / "1.glb", atlas_cache_dir=cache)
    assert len(list(cache.glob("*.npz"))) == 1

    def no_child(*args, **kwargs):
        raise AssertionError("xatlas ran although its atlas is cached")

    monkeypatch.setattr(atlas, "_run_child", no_child)
    second = bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                       out_path=tmp_path / "2.glb", atlas_cache_dir=cache)
    assert second.uv_source == "xatlas" and second.timings["atlas"] < 1.0
    assert first.path.read_bytes() == second.path.read_bytes()
    # other options (here the packing resolution) are another entry
    with pytest.raises(AssertionError, match="cached"):
        bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=128,
                  out_path=tmp_path / "3.glb", atlas_cache_dir=cache)


def test_atlas_cache_damage_and_bound(meshes, tmp_path):
    vertices, faces, _ = load_mesh((meshes / "bunny.obj").read_bytes(), "bunny.obj")
    cache = tmp_path / "c"
    vmap, new_faces, uv, method = atlas.parametrize(vertices, faces, resolution=64, padding=2, cache_dir=cache)
    (entry,) = cache.glob("*.npz")
    entry.write_bytes(b"not an npz")                        # a damaged entry is a miss, then rewritten
    again = atlas.parametrize(vertices, faces, resolution=64, padding=2, cache_dir=cache)
    assert np.array_equal(again[1], new_faces) and np.allclose(again[2], uv) and method == again[3] == "xatlas"
    assert entry.stat().st_size > 100
    other = vertices * 2.0                                   # another mesh, a cache of one entry's size
    atlas.parametrize(other, faces, resolution=64, padding=2, cache_dir=cache,
                      cache_bytes=entry.stat().st_size + 10)
    assert len(list(cache.glob("*.npz"))) == 1 and not entry.exists()
    quality = atlas.atlas_quality(vertices[vmap], new_faces, uv)
    assert 0.3 < quality["uv_area"] < 1 and 1.0 <= quality["stretch_l2"] < 1.5


def test_chunked_sampling_gives_the_same_atlas(waves, meshes):
    """Points, sampling and encoding are pipelined chunk by chunk: any chunk size, same bytes."""
    vertices, faces, uv = load_mesh((meshes / "bunny_uv.obj").read_bytes(), "bunny_uv.obj")
    outputs = [bake_texture(waves, None, 0, uv[faces], vertices[faces], resolution=96, padding=3, scale=20.0,
                            chunk=chunk, linear=True) for chunk in (1 << 18, 1000, 997)]
    srgb, covered, linear = outputs[0]
    assert covered.sum() > 3000 and waves.calls[1:3] == [1000, 1000]
    for other in outputs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(outputs[0], other))
    assert np.array_equal(srgb[covered], linear_to_srgb8(linear[covered]))


class XStripes:
    """A texture whose pattern lies in the xy plane along x only, as a lattice fit's rows
    (of bricks seen from the side) do: colour = stripes of x; y and z are ignored."""

    pixels_per_unit = 256.0

    def sample(self, points, code, seed):
        value = (0.5 + 0.5 * np.sin(points[:, 0] * 2.0)).astype(np.float32)
        return np.repeat(value[:, None], 3, axis=1)


def quad_facing(axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of a unit square in the plane normal to ``axis`` (at 0.5), UVs over [0, 1]^2."""
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    u, v = [a for a in range(3) if a != axis]
    xyz = np.full((4, 3), 0.5)
    xyz[:, u], xyz[:, v] = uv[:, 0], uv[:, 1]
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return uv[faces], xyz[faces]


@pytest.mark.parametrize("axis", [0, 1])
def test_triplanar_shows_the_xy_pattern_on_faces_the_solid_leaves_plain(axis):
    # Facing x, a surface of the solid sits at one x: the stripes vanish (a brick wall's side
    # as one colour). Triplanar reads the xy plane at (z, y) or (x, z), where they show.
    tri_uv, tri_xyz = quad_facing(axis)
    bake = dict(resolution=64, padding=2, scale=10.0)
    solid, covered, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, **bake)
    triplanar, _, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, projection="triplanar", **bake)
    if axis == 0:
        assert np.ptp(solid[covered]) == 0
    else:  # facing y the solid still varies with x: triplanar reads the same x
        np.testing.assert_array_equal(triplanar[covered], solid[covered])
    assert np.ptp(triplanar[covered]) > 200


def test_triplanar_on_a_face_facing_z_is_the_solid_and_blends_at_45_degrees():
    tri_uv, tri_xyz = quad_facing(2)
    bake = dict(resolution=64, padding=2, scale=10.0)
    solid, covered, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, **bake)
    triplanar, _, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, projection="triplanar", **bake)
    np.testing.assert_array_equal(triplanar[covered], solid[covered])
    points = np.random.default_rng(0).uniform(-3, 3, (100, 3))
    normals = np.tile([np.sqrt(0.5), 0.0, np.sqrt(0.5)], (100, 1))  # between x and z: half each
    stripes = XStripes()
    expected = 0.5 * stripes.sample(projected_points(points, 0), None, 0) + 0.5 * stripes.sample(points, None, 0)
    np.testing.assert_allclose(sample_triplanar(stripes, points, normals, None, 0), expected, atol=1e-6)


def test_triplanar_weights_and_projections():
    normals = np.array([[1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, 0], [0.6, 0.8, 0], [0.1, 0.0, 0.995]])
    weights = triplanar_weights(normals)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    np.testing.assert_array_equal(weights[:4], [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1]])
    assert 0 < weights[4, 0] < weights[4, 1] < 1 and weights[5, 0] == 0  # |0.1|^4: below the cut
    p = np.array([[1.0, 2.0, 3.0]])
    assert projected_points(p, 0)[0, :2].tolist() == [3.0, 2.0]  # x-facing: (z, y), rows stay y
    assert projected_points(p, 1)[0, :2].tolist() == [1.0, 3.0]
    assert projected_points(p, 2)[0, :2].tolist() == [1.0, 2.0]
    assert len({projected_points(p, a)[0, 2] for a in range(3)}) == 3  # each at its own depth


def test_unknown_projection_is_refused(waves, meshes, tmp_path):
    with pytest.raises(InvalidParameter, match="projection"):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny_uv.obj").read_bytes(), filename="bunny_uv.obj",
                  resolution=64, out_path=tmp_path / "x.glb", projection="cubic")


def test_triplanar_blends_by_the_files_own_normals_when_given():
    # An x-facing quad whose file normals say "facing z" (the artist's shading) reads the
    # z-facing projection, (x, y): one x, so one colour; by its face normal it shows stripes.
    tri_uv, tri_xyz = quad_facing(0)
    bake = dict(resolution=64, padding=2, scale=10.0, projection="triplanar")
    by_face, covered, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, **bake)
    by_file, _, _ = bake_texture(XStripes(), None, 0, tri_uv, tri_xyz, tri_normals=np.tile([0.0, 0.0, 2.0], (2, 3, 1)),
                                 **bake)
    assert np.ptp(by_face[covered]) > 200 and np.ptp(by_file[covered]) == 0


def test_triplanar_cube_bake_shows_the_pattern_on_every_face(meshes, tmp_path):
    # cube.obj has its own (per-face) normals; on all six faces the x stripes now vary.
    data = (meshes / "cube.obj").read_bytes()
    mesh = read_mesh(data, "cube.obj")
    assert mesh.normals is not None
    varying = {}
    for projection in ("solid", "triplanar"):
        result = bake_mesh(XStripes(), None, 0, mesh_bytes=data, filename="cube.obj", resolution=128, scale=6.0,
                           out_path=tmp_path / f"{projection}.glb", projection=projection)
        glb, image = glb_texture_and_mesh(result.path)
        inside = ndimage.binary_erosion(result.covered, iterations=3)
        spread = []  # of each face's texels, faces facing -x, +x, -y, +y, -z, +z
        for axis in range(3):
            for sign in (-1, 1):
                on = glb.face_normals[:, axis] * sign > 0.99
                spread.append(np.ptp(image[chart_mask(glb.visual.uv, glb.faces[on], 128) & inside][:, 0].astype(int)))
        varying[projection] = spread
    assert max(varying["solid"][:2]) <= 1 and min(varying["solid"][2:]) > 100  # facing x: one colour
    assert min(varying["triplanar"]) > 100
