"""Volumes: every format read back equals the npy result; memory O(slab); progress/cancel."""
import json
import os
import shutil
import struct
import subprocess
import tracemalloc
import zipfile
from pathlib import Path

import nrrd
import numpy as np
import OpenImageIO as oiio
import pytest

from tests.worker.vdb_reader import read_vdb
from worker.colour import LUMA_709, linear_to_srgb8
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.volume_writers import flipbook_grid
from worker.volumes import render_volume, slab_points, voxel_centres

N = 12                                   # flipbook grid 4 x 3
BOUNDS = ((-1.0, 0.0, 2.0), (1.0, 0.5, 3.0))


@pytest.fixture(scope="module")
def reference(runtime, code, tmp_path_factory):
    path = render_volume(runtime, code, 4, resolution=N, bounds=BOUNDS, fmt="npy",
                         out_path=tmp_path_factory.mktemp("vol") / "ref.npy", slab=5)
    return np.load(path)


def read_pages(path):
    inp = oiio.ImageInput.open(str(path))
    pages = []
    while inp.seek_subimage(len(pages), 0):
        pages.append(inp.read_image(len(pages), 0, 0, 3, "float"))
    inp.close()
    return np.stack(pages)


# Debian's python3-openvdb (the OpenVDB 10 library) under the system Python: the project's
# environment cannot import it (built for numpy 1.x), so it runs as a child process.
SYSTEM_PYTHON = "/usr/bin/python3"
READ_VDB = """
import json, sys, numpy as np, pyopenvdb as vdb
grids, file_meta = vdb.readAll(sys.argv[1])
out = {"grids": [], "file_meta": file_meta}
for g in grids:
    lo, hi = g.evalActiveVoxelBoundingBox()
    shape = tuple(h + 1 for h in hi) + ((3,) if type(g).__name__ == "Vec3SGrid" else ())
    a = np.zeros(shape, np.float32)
    g.copyToArray(a, ijk=(0, 0, 0))
    np.save(sys.argv[2] + "-" + g.name + ".npy", a)
    out["grids"].append({"name": g.name, "type": type(g).__name__, "active": g.activeVoxelCount(),
                         "bbox": [lo, hi], "first": g.transform.indexToWorld((0, 0, 0)),
                         "voxel_size": g.transform.voxelSize(),
                         "meta": {k: g[k] for k in g.metadata.keys()}})
json.dump(out, open(sys.argv[3], "w"))
"""


def read_vdb_with_openvdb(path: Path, tmp: Path):
    """({grid name: array [x][y][z](c)}, info) as OpenVDB itself reads the file; skips without it."""
    if not (shutil.which(SYSTEM_PYTHON) and subprocess.run(
            [SYSTEM_PYTHON, "-c", "import pyopenvdb"], capture_output=True).returncode == 0):
        pytest.skip("Debian's python3-openvdb is not installed (apt-get install python3-openvdb)")
    subprocess.run([SYSTEM_PYTHON, "-c", READ_VDB, str(path), str(tmp / "vdb"), str(tmp / "vdb.json")],
                   check=True, timeout=120)
    info = json.loads((tmp / "vdb.json").read_text())
    return {g["name"]: np.load(tmp / f"vdb-{g['name']}.npy") for g in info["grids"]}, info


def check_vdb(path: Path, reference: np.ndarray, bounds, tmp: Path) -> None:
    """The file read back by our own minimal reader, then by OpenVDB itself (if installed):
    ``Cd`` is the colour, ``density`` its linear luminance."""
    n = reference.shape[0]
    lo, hi = np.asarray(bounds, float)
    size = (hi - lo) / n
    xyz = reference.transpose(2, 1, 0, 3)                               # voxel (i, j, k) = [z=k, y=j, x=i]
    luminance = xyz @ LUMA_709
    grids = read_vdb(path.read_bytes())
    assert list(grids) == ["Cd", "density"]
    (colour, dense), (fog, density) = grids["Cd"], grids["density"]
    assert (colour["version"], colour["type"], colour["active"]) == (224, "Tree_vec3s_5_4_3", n ** 3)
    assert (fog["type"], fog["active"], fog["meta"]["class"]) == ("Tree_float_5_4_3", n ** 3, "fog volume")
    assert np.array_equal(dense, xyz) and np.allclose(density[..., 0], luminance, atol=1e-6)
    for info in (colour, fog):
        assert np.allclose(info["translation"], lo + size / 2) and np.allclose(info["scale"], size)
    data, info = read_vdb_with_openvdb(path, tmp)
    assert [(g["name"], g["type"], g["active"]) for g in info["grids"]] == [
        ("Cd", "Vec3SGrid", n ** 3), ("density", "FloatGrid", n ** 3)]
    assert np.array_equal(data["Cd"], xyz) and np.allclose(data["density"], luminance, atol=1e-6)
    for g in info["grids"]:
        assert g["bbox"] == [[0, 0, 0], [n - 1] * 3]
        assert np.allclose(g["first"], lo + size / 2) and np.allclose(g["voxel_size"], size)
        assert np.allclose(g["meta"]["texspace_bounds_min"], lo) and np.allclose(g["meta"]["texspace_bounds_max"], hi)
    assert info["grids"][0]["meta"]["texspace_colour"] == "linear" and info["file_meta"] == {"creator": "texspace"}


def test_reference_is_the_sampler_on_voxel_centres(runtime, code, reference):
    assert reference.shape == (N, N, N, 3) and reference.dtype == np.float32
    xs, ys, zs = (voxel_centres(BOUNDS[0][a], BOUNDS[1][a], N) for a in range(3))
    k, j, i = 7, 3, 10                                       # [z, y, x]
    direct = runtime.sample(np.array([[xs[i], ys[j], zs[k]]]), code, 4)[0]
    assert np.allclose(reference[k, j, i], direct, atol=1e-6)
    assert voxel_centres(0, 1, 4).tolist() == [0.125, 0.375, 0.625, 0.875]
    assert slab_points((xs, ys, zs), 2, 3)[0].tolist() == [xs[0], ys[0], zs[2]]


@pytest.mark.parametrize("fmt", ["exr", "tiff", "raw", "nrrd", "dds", "flipbook", "vdb"])
def test_every_format_reads_back_equal_to_npy(runtime, code, reference, tmp_path, fmt):
    out = render_volume(runtime, code, 4, resolution=N, bounds=BOUNDS, fmt=fmt,
                        out_path=tmp_path / f"v.{fmt}", slab=5)
    assert out.is_file() and os.listdir(tmp_path) == [f"v.{fmt}"]      # no temp (or spool) file left
    if fmt in ("exr", "tiff"):
        assert np.array_equal(read_pages(out), reference)
        if fmt == "exr":    # Blender's multilayer names: one layer per slice, its pass Combined
            inp = oiio.ImageInput.open(str(out))
            assert inp.seek_subimage(3, 0) and inp.spec().channelnames == tuple(f"slice_0003.Combined.{c}" for c in "RGB")
            inp.close()
    elif fmt == "vdb":
        check_vdb(out, reference, BOUNDS, tmp_path)
    elif fmt == "raw":
        with zipfile.ZipFile(out) as z:
            meta = json.loads(z.read("volume.json"))
            data = np.frombuffer(z.read("volume.raw"), "<f4").reshape(meta["shape"])
        assert meta["axes"] == ["z", "y", "x", "channel"] and np.array_equal(data, reference)
    elif fmt == "nrrd":
        data, header = nrrd.read(str(out), index_order="C")
        assert np.array_equal(data, reference)
        assert np.allclose(header["space origin"], [-1 + 1 / N, 0.25 / N, 2 + 0.5 / N])
    elif fmt == "dds":
        raw = out.read_bytes()
        magic, size, flags, height, width, pitch, depth = struct.unpack_from("<4s6I", raw)
        assert (magic, size, height, width, depth, pitch) == (b"DDS ", 124, N, N, N, 4 * N)
        assert flags & 0x800000 and struct.unpack_from("<I", raw, 112)[0] & 0x200000  # DEPTH, caps2 VOLUME
        # legacy pixel format: DDPF_RGB | DDPF_ALPHAPIXELS, 32 bits A8R8G8B8, bytes B G R A
        assert struct.unpack_from("<2I4s5I", raw, 76) == (32, 0x41, bytes(4), 32, 0xFF0000, 0xFF00, 0xFF, 0xFF000000)
        texels = np.frombuffer(raw, np.uint8, offset=128).reshape(N, N, N, 4)
        assert np.array_equal(texels[..., 2::-1], linear_to_srgb8(reference)) and (texels[..., 3] == 255).all()
        # OpenImageIO recognises it as an RGBA volume (its reader returns slice 0 only).
        spec = oiio.ImageInput.open(str(out)).spec()
        assert (spec.width, spec.height, spec.depth, spec.nchannels) == (N, N, N, 4)
    else:
        cols, rows = flipbook_grid(N)
        inp = oiio.ImageInput.open(str(out))
        sheet = inp.read_image(0, 0, 0, 3, "uint8").reshape(rows * N, cols * N, 3)
        slices = sheet.reshape(rows, N, cols, N, 3).transpose(0, 2, 1, 3, 4).reshape(N, N, N, 3)
        assert np.array_equal(slices, linear_to_srgb8(reference))        # slice 0 top-left, row-major


def test_exr_and_tiff_pages_carry_bounds_and_voxel_size(runtime, code, tmp_path):
    bounds = ((-1.25, 0.0, 2.0), (1.0, 0.5, 3.5))
    for fmt in ("exr", "tiff"):
        out = render_volume(runtime, code, 4, resolution=6, bounds=bounds, fmt=fmt, out_path=tmp_path / f"v.{fmt}")
        inp = oiio.ImageInput.open(str(out))
        k = 0
        while inp.seek_subimage(k, 0):
            spec = inp.spec()
            text = spec.get_string_attribute("texspace:volume" if fmt == "exr" else "ImageDescription")
            meta = json.loads(text)
            assert meta["bounds_min"] == [-1.25, 0.0, 2.0] and meta["bounds_max"] == [1.0, 0.5, 3.5]
            assert np.allclose(meta["voxel_size"], [2.25 / 6, 0.5 / 6, 1.5 / 6]) and meta["resolution"] == [6] * 3
            assert meta["slice"] == k and np.isclose(meta["slice_z"], 2.0 + (k + 0.5) * 0.25)
            if fmt == "exr":   # plain OpenEXR attributes, what a compositor or DCC importer reads
                assert np.allclose(spec.getattribute("boundsMin"), bounds[0])
                assert np.allclose(spec.getattribute("boundsMax"), bounds[1])
                assert np.allclose(spec.getattribute("voxelSize"), meta["voxel_size"])
                assert spec.getattribute("sliceIndex") == k and np.isclose(spec.getattribute("sliceZ"), meta["slice_z"])
            k += 1
        inp.close()
        assert k == 6


def test_vdb_partial_leaves_and_several_nodes(waves, tmp_path):
    """N = 130: two 4-level nodes per axis and partial leaves past the edge (all read back)."""
    n, bounds = 130, ((0.0, -2.0, 1.0), (13.0, 2.0, 1.5))
    ref = render_volume(waves, np.zeros(8, np.float32), 3, resolution=n, bounds=bounds, fmt="npy",
                        out_path=tmp_path / "w.npy", slab=40)
    out = render_volume(waves, np.zeros(8, np.float32), 3, resolution=n, bounds=bounds, fmt="vdb",
                        out_path=tmp_path / "w.vdb", slab=40)
    check_vdb(out, np.load(ref), bounds, tmp_path)


def test_flipbook_grid():
    assert flipbook_grid(128) == (16, 8) and flipbook_grid(64) == (8, 8)
    assert flipbook_grid(12) == (4, 3) and flipbook_grid(7) == (7, 1)


@pytest.mark.parametrize("fmt", ["npy", "raw", "flipbook"])
def test_memory_is_bounded_by_the_slab(waves, tmp_path, fmt):
    n = 128
    full = n ** 3 * 3 * 4                                     # 25 MB as float32
    tracemalloc.start()
    try:
        render_volume(waves, np.zeros(8, np.float32), 0, resolution=n, fmt=fmt,
                      out_path=tmp_path / "big", slab=4)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert max(waves.calls) == 4 * n * n
    # positions (24 B/point) + colours (12 B/point) + the sampler's chunk temporaries
    # (+ one 8-bit grid row for the flipbook): O(slab), far below the full volume.
    slab_bytes = 4 * n * n * 12
    assert peak < 8 * slab_bytes + (n ** 3 * 3 // 8 if fmt == "flipbook" else 0), \
        f"peak {peak / 1e6:.1f} MB vs full {full / 1e6:.1f} MB"
    assert peak < full / 4


def test_npy_of_the_big_volume_is_right(waves, tmp_path):
    path = render_volume(waves, np.zeros(8, np.float32), 2, resolution=64, fmt="npy",
                         out_path=tmp_path / "w.npy", slab=7)
    vol = np.load(path, mmap_mode="r")
    c = voxel_centres(0, 1, 64)
    assert np.array_equal(vol[63, 5, 9], waves.sample(np.array([[c[9], c[5], c[63]]]), None, 2)[0])


def test_progress_and_cancel(runtime, code, tmp_path):
    seen = []
    render_volume(runtime, code, 1, resolution=8, fmt="npy", out_path=tmp_path / "a.npy",
                  slab=3, progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) == 3
    seen.clear()
    render_volume(runtime, code, 1, resolution=8, fmt="vdb", out_path=tmp_path / "a.vdb", slab=4,
                  progress=seen.append)
    assert seen == [0.45, 0.9, 1.0]                           # the encode after the last slab
    os.unlink(tmp_path / "a.vdb")
    calls = []
    with pytest.raises(Canceled):
        render_volume(runtime, code, 1, resolution=8, fmt="flipbook", out_path=tmp_path / "b.png", slab=2,
                      should_cancel=lambda: calls.append(1) or len(calls) > 1)
    assert sorted(os.listdir(tmp_path)) == ["a.npy"]          # nothing half-written left behind
    calls.clear()
    with pytest.raises(Canceled):
        render_volume(runtime, code, 1, resolution=8, fmt="vdb", out_path=tmp_path / "c.vdb", slab=2,
                      should_cancel=lambda: calls.append(1) or len(calls) > 1)
    assert sorted(os.listdir(tmp_path)) == ["a.npy"]          # neither the VDB nor its spool


def test_limits_and_bad_parameters(runtime, code, tmp_path):
    with pytest.raises(LimitExceeded):
        render_volume(runtime, code, 0, resolution=300, fmt="npy", out_path=tmp_path / "x",
                      max_voxels=256 ** 3)
    with pytest.raises(InvalidParameter):
        render_volume(runtime, code, 0, resolution=8, fmt="openvdb", out_path=tmp_path / "x")
    with pytest.raises(InvalidParameter):
        render_volume(runtime, code, 0, resolution=8, bounds=((0, 0, 0), (1, 0, 1)), fmt="npy",
                      out_path=tmp_path / "x")
    assert os.listdir(tmp_path) == []
