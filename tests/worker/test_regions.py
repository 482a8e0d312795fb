"""Regions: one big image equal to the tiles' pixels; zipped pyramid equal to tile bytes."""
import json
import os
import zipfile

import numpy as np
import OpenImageIO as oiio
import pytest

from tests.worker.gpu_readers import assert_block_compressed_close, read_dds_levels, read_ktx2
from worker.colour import linear_to_srgb, linear_to_srgb8
from worker.derived_maps import decode_normals8, height_map, normal_map, read_height_range
from worker.gpu_textures import mip_chain
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.images import write_image
from worker.regions import RegionLimits, render_region
from worker.runtime import SamplerSession
from worker.tiles import NATIVE_ZOOM, render_tile, render_window

N = NATIVE_ZOOM
RECT = dict(z=N - 1, x0=-70, y0=33, width=150, height=70)     # not tile aligned, crosses x = 0


@pytest.fixture(scope="module")
def expected(runtime, code):
    return render_window(runtime, code, 9, RECT["z"], RECT["x0"], RECT["y0"], RECT["width"],
                         RECT["height"], pixels_per_unit=runtime.pixels_per_unit, supersample=2)


def read(path):
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, 3, "float")
    inp.close()
    return spec, pixels


def test_region_pixels_are_the_tiles_pixels(runtime, code, expected):
    # tile (N-1, -1, 0) covers columns [-64, 0) and rows [0, 64); the region starts at (-70, 33)
    tile = render_tile(runtime, code, 9, N - 1, -1, 0, 64)
    assert np.array_equal(expected[:31, 6:70], tile[33:, :])


@pytest.mark.parametrize("fmt, tolerance", [("png", 0), ("tiff", 1e-4), ("exr", 1e-3)])
def test_single_image_formats(runtime, code, expected, tmp_path, fmt, tolerance):
    seen = []
    out = render_region(runtime, code, 9, fmt=fmt, out_path=tmp_path / f"r.{fmt}",
                        progress=seen.append, **RECT)
    spec, pixels = read(out)
    assert (spec.width, spec.height) == (150, 70) and seen[-1] == 1.0
    if fmt == "png":
        assert np.array_equal(np.round(pixels * 255).astype(np.uint8), linear_to_srgb8(expected))
    elif fmt == "tiff":
        assert spec.tile_width == 0 and np.abs(pixels - linear_to_srgb(expected)).max() < tolerance   # strips
    else:
        assert np.abs(pixels - expected).max() < tolerance
    assert os.listdir(tmp_path) == [f"r.{fmt}"]


@pytest.mark.parametrize("fmt", ["dds", "ktx2"])
def test_gpu_formats_carry_the_mip_chain(runtime, code, expected, tmp_path, fmt):
    out = render_region(runtime, code, 9, fmt=fmt, out_path=tmp_path / f"r.{fmt}", **RECT)
    levels = read_dds_levels(out) if fmt == "dds" else read_ktx2(out.read_bytes())[1]
    sizes = [(70, 150), (35, 75), (17, 37), (8, 18), (4, 9), (2, 4), (1, 2), (1, 1)]
    assert [lv.shape[:2] for lv in levels] == sizes
    for got, want in zip(levels, mip_chain(expected)):
        # BC1 / the KTX2 blocks: near, not equal. The KTX2 ones err more on a busy texture (the
        # 7dc44253 space's brick: level means 4.9-6.9, worst 70 codes; BC1 4.0, 28)
        mean, worst = (6, 64) if fmt == "dds" else (8, 80)
        assert_block_compressed_close(got[..., :3], linear_to_srgb8(want), mean=mean, worst=worst)
    assert os.listdir(tmp_path) == [f"r.{fmt}"]


@pytest.mark.parametrize("fmt", ["png", "exr", "ktx2"])
def test_derived_maps_come_in_a_zip_with_the_colour(runtime, code, expected, tmp_path, fmt):
    out = render_region(runtime, code, 9, fmt=fmt, out_path=tmp_path / "r.zip", maps=("height", "normal"),
                        normal_strength=3.0, **RECT)
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == sorted([f"r_basecolor.{fmt}", "r_height.png", "r_normal.png"])
        z.extractall(tmp_path / "x")
    if fmt == "png":
        assert np.array_equal(np.round(read(tmp_path / "x/r_basecolor.png")[1] * 255).astype(np.uint8),
                              linear_to_srgb8(expected))
    elif fmt == "exr":
        assert np.abs(read(tmp_path / "x/r_basecolor.exr")[1] - expected).max() < 1e-3
    spec, height = read(tmp_path / "x/r_height.png")
    assert (spec.width, spec.height, spec.nchannels, str(spec.format)) == (150, 70, 1, "uint16")
    stretched, height_range = height_map(expected)
    assert np.abs(height[..., 0] - stretched).max() <= 1 / 65535
    assert read_height_range((tmp_path / "x/r_height.png").read_bytes()) == pytest.approx(height_range)
    normals = decode_normals8(np.round(read(tmp_path / "x/r_normal.png")[1] * 255))
    assert normals.shape == (70, 150, 3) and np.abs(np.linalg.norm(normals, axis=-1) - 1).max() < 0.02
    assert np.abs(normals - normal_map(stretched, 3.0)).max() <= 1 / 127.5 + 1e-6
    assert sorted(os.listdir(tmp_path)) == ["r.zip", "x"]


def test_pyramid(runtime, code, tmp_path):
    out = render_region(runtime, code, 9, z=N, x0=-64, y0=0, width=128, height=64, size=64,
                        min_zoom=N - 1, fmt="pyramid", out_path=tmp_path / "p.zip")
    with zipfile.ZipFile(out) as z:
        names = sorted(z.namelist())
        meta = json.loads(z.read("tilejson.json"))
        tile = z.read(f"{N}/-1/0.png")
        parent = z.read(f"{N - 1}/-1/0.png")
    assert names == sorted([f"{N}/-1/0.png", f"{N}/0/0.png", f"{N - 1}/-1/0.png", f"{N - 1}/0/0.png",
                            "tilejson.json"])
    assert meta["minzoom"] == N - 1 and meta["maxzoom"] == N and meta["tiles"] == ["{z}/{x}/{y}.png"]
    # the same bytes the tile endpoint serves
    assert tile == write_image(render_tile(runtime, code, 9, N, -1, 0, 64), "png")
    assert parent == write_image(render_tile(runtime, code, 9, N - 1, -1, 0, 64), "png")


def test_limits_cancel_and_parameters(runtime, code, tmp_path):
    with pytest.raises(LimitExceeded):
        render_region(runtime, code, 0, fmt="png", out_path=tmp_path / "a.png",
                      limits=RegionLimits(max_pixels=100), **RECT)
    with pytest.raises(LimitExceeded):
        render_region(runtime, code, 0, z=N, x0=0, y0=0, width=4096, height=4096, fmt="pyramid",
                      out_path=tmp_path / "a.zip", limits=RegionLimits(max_tiles=10))
    with pytest.raises(Canceled):
        render_region(runtime, code, 0, fmt="tiff", out_path=tmp_path / "a.tif",
                      should_cancel=lambda: True, **RECT)
    with pytest.raises(InvalidParameter):
        render_region(runtime, code, 0, fmt="jpeg2000", out_path=tmp_path / "a.jp2", **RECT)
    with pytest.raises(LimitExceeded):
        render_region(runtime, code, 0, fmt="ktx2", out_path=tmp_path / "a.ktx2",
                      limits=RegionLimits(max_whole_pixels=100), **RECT)
    with pytest.raises(LimitExceeded):
        render_region(runtime, code, 0, fmt="png", maps=("normal",), out_path=tmp_path / "a.zip",
                      limits=RegionLimits(max_whole_pixels=100), **RECT)
    with pytest.raises(InvalidParameter):
        render_region(runtime, code, 0, fmt="pyramid", maps=("height",), out_path=tmp_path / "a.zip", **RECT)
    with pytest.raises(InvalidParameter):
        render_region(runtime, code, 0, fmt="png", maps=("gloss",), out_path=tmp_path / "a.zip", **RECT)
    with pytest.raises(InvalidParameter, match="pixels_per_unit"):   # a bare fitted sampler
        render_region(SamplerSession(runtime.sampler.path), code, 0, fmt="png",
                      out_path=tmp_path / "a.png", **RECT)
    assert os.listdir(tmp_path) == []
