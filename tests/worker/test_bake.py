"""UV bakes: atlas choice, coverage, gutter, colours through the saved file, bad meshes."""
import os
import zipfile

import time

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy import ndimage
from skimage.draw import polygon

from worker.bake import BakeLimits, bake_mesh, load_mesh
from worker.colour import linear_to_srgb8
from worker.errors import AtlasFailed, Canceled, InvalidMesh, LimitExceeded
from worker.raster import uv_to_texel

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
    # Gutter: every texel within the padding copies its nearest covered texel (never black).
    dist, (ri, ci) = ndimage.distance_transform_edt(~result.covered, return_indices=True)
    near = (dist <= 4) & ~result.covered
    assert near.sum() > 0 and (image[near] == image[ri[near], ci[near]]).all()
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
    assert sorted(os.listdir(folder)) == ["model.mtl", "model.obj", "texture.exr", "texture.png"]
    assert "Kd 1 1 1" in (folder / "model.mtl").read_text()
    mesh = trimesh.load(str(folder / "model.obj"), process=False, force="mesh")
    assert len(mesh.faces) == 12 and mesh.visual.uv.shape == (len(mesh.vertices), 2)
    assert Image.open(folder / "texture.png").size == (64, 64)


def test_other_mesh_types(waves, meshes, tmp_path):
    bunny = trimesh.load(str(meshes / "bunny.obj"), process=False, force="mesh")
    for ext in ("ply", "stl", "glb"):
        result = bake_mesh(waves, None, 0, mesh_bytes=bunny.export(file_type=ext),
                           filename=f"bunny.{ext}", resolution=64, out_path=tmp_path / f"{ext}.glb")
        assert result.faces == 902 and result.covered.sum() > 0


BAD_MESHES = [
    ("nan.obj", b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "NaN"),
    ("range.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n", "out of (bounds|range)"),
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


def test_mesh_limits(meshes):
    with pytest.raises(LimitExceeded, match="902 faces"):
        load_mesh((meshes / "bunny.obj").read_bytes(), "bunny.obj", BakeLimits(max_faces=900))


@pytest.mark.parametrize("hook", ["segfault", "abort"])
def test_atlas_crash_is_contained(waves, meshes, tmp_path, hook):
    data = (meshes / "bunny.obj").read_bytes()
    with pytest.raises(AtlasFailed, match="signal"):
        bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                  out_path=tmp_path / "x.glb", atlas_crash_for_test=hook)
    assert not (tmp_path / "x.glb").exists()
    # this process is alive and the next bake works
    assert bake_mesh(waves, None, 0, mesh_bytes=data, filename="bunny.obj", resolution=64,
                     out_path=tmp_path / "y.glb").path.is_file()


def test_atlas_timeout(waves, meshes, tmp_path):
    with pytest.raises(AtlasFailed, match="longer than"):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny.obj").read_bytes(), filename="bunny.obj",
                  resolution=64, out_path=tmp_path / "x.glb", atlas_crash_for_test="hang",
                  limits=BakeLimits(atlas_timeout=2))


def test_cancel(waves, meshes, tmp_path):
    with pytest.raises(Canceled):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny_uv.obj").read_bytes(),
                  filename="bunny_uv.obj", resolution=64, out_path=tmp_path / "x.glb",
                  should_cancel=lambda: True)
    assert os.listdir(tmp_path) == []


def test_cancel_ends_the_atlas_child(waves, meshes, tmp_path):
    """A cancel while xatlas runs kills its child within a poll, not at the atlas timeout."""
    started = time.monotonic()
    with pytest.raises(Canceled, match="atlas"):
        bake_mesh(waves, None, 0, mesh_bytes=(meshes / "bunny.obj").read_bytes(), filename="bunny.obj",
                  resolution=64, out_path=tmp_path / "x.glb", atlas_crash_for_test="hang",
                  should_cancel=lambda: time.monotonic() - started > 1.0)
    assert time.monotonic() - started < 10
