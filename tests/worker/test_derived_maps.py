"""Derived maps (height, normal) and mipmapped GPU textures (DDS, KTX2) as functions."""
import io

import numpy as np
import pytest
from PIL import Image

from tests.worker.gpu_readers import assert_block_compressed_close, read_dds_levels, read_ktx2
from worker.colour import linear_to_srgb8
from worker.derived_maps import (decode_normals8, derived_map_files, height_map, normal_map)
from worker.errors import InvalidParameter
from worker.gpu_textures import dds_bytes, ktx2_bytes, mip_chain, mip_sizes


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(7)
    return rng.random((37, 64, 3)).astype(np.float32)       # odd height: fractional mip weights


def test_height_is_the_linear_luminance(image):
    h = height_map(image)
    assert h.shape == (37, 64) and h.dtype == np.float32
    assert np.allclose(h, 0.2126 * image[..., 0] + 0.7152 * image[..., 1] + 0.0722 * image[..., 2], atol=1e-6)
    assert height_map(np.ones((2, 2, 3)))[0, 0] == pytest.approx(1.0)


def test_normals_are_unit_and_follow_the_opengl_convention():
    rows, cols = np.mgrid[0:16, 0:16].astype(np.float32)
    # height rising to the right: the surface faces left (-x); rising upwards (towards row 0):
    # it faces down (-y, OpenGL +Y is up)
    right = normal_map(cols / 16, strength=1.0)
    up = normal_map((15 - rows) / 16, strength=1.0)
    assert np.allclose(np.linalg.norm(right, axis=-1), 1, atol=1e-6) and (right[..., 2] > 0).all()
    assert (right[..., 0] < 0).all() and np.allclose(right[..., 1], 0)
    assert (up[..., 1] < 0).all() and np.allclose(up[..., 0], 0)
    slope = 1 / 16
    assert np.allclose(right[5, 5], np.array([-slope, 0, 1]) / np.hypot(slope, 1), atol=1e-6)
    flat = normal_map(np.full((4, 5), 0.3))
    assert np.allclose(flat, [0, 0, 1])


def test_wrapped_normals_tile(image):
    h = height_map(image)
    wrapped = normal_map(h, wrap=True)
    shifted = normal_map(np.roll(h, (5, 9), axis=(0, 1)), wrap=True)
    assert np.allclose(np.roll(wrapped, (5, 9), axis=(0, 1)), shifted, atol=1e-6)   # no border
    clamped = normal_map(h)
    assert np.allclose(clamped[1:-1, 1:-1], wrapped[1:-1, 1:-1], atol=1e-6)


def test_map_files_read_back(image):
    files = derived_map_files(image, ("height", "normal"), strength=2.0)
    height = Image.open(io.BytesIO(files["height.png"]))
    normal = Image.open(io.BytesIO(files["normal.png"]))
    assert height.size == normal.size == (64, 37) and normal.mode == "RGB"
    h16 = np.asarray(height, dtype=np.float64) / 65535
    assert np.abs(h16 - height_map(image)).max() <= 0.5 / 65535 + 1e-7
    n = decode_normals8(np.asarray(normal))
    assert np.abs(np.linalg.norm(n, axis=-1) - 1).max() < 0.02          # unit length up to 8-bit codes
    assert np.abs(n - normal_map(height_map(image), 2.0)).max() <= 1 / 127.5 + 1e-6
    assert set(derived_map_files(image, ("normal",))) == {"normal.png"} and derived_map_files(image, ()) == {}
    with pytest.raises(InvalidParameter):
        derived_map_files(image, ("roughness",))
    with pytest.raises(InvalidParameter):
        normal_map(np.zeros((4, 4)), strength=0)


def test_mip_chain_sizes_and_linear_light_averages(image):
    assert mip_sizes(64, 37) == [(64, 37), (32, 18), (16, 9), (8, 4), (4, 2), (2, 1), (1, 1)]
    assert len(mip_sizes(2048, 2048)) == 12 and mip_sizes(1, 1) == [(1, 1)]
    levels = mip_chain(image)
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(64, 37)
    for lv in levels:       # exact area averages keep the mean (in linear light)
        assert np.allclose(lv.mean(axis=(0, 1)), image.mean(axis=(0, 1)), atol=1e-5)
    even = image[:36]
    assert np.allclose(mip_chain(even)[1][3, 4], even[6:8, 8:10].mean(axis=(0, 1)), atol=1e-6)
    # a black / white checkerboard becomes linear 0.5 (sRGB code 188), not sRGB code 128
    board = np.indices((8, 8)).sum(axis=0) % 2
    grey = mip_chain(np.repeat(board[..., None], 3, axis=2).astype(np.float32))[1]
    assert np.allclose(grey, 0.5) and linear_to_srgb8(grey)[0, 0, 0] == 188


def two_colour_ramp() -> np.ndarray:
    """(37, 64, 3) linear: a ramp between two colours, so each 4 x 4 block's colours lie
    near a line, as BC1 needs (odd height: fractional mip weights)."""
    rows, cols = np.mgrid[0:37, 0:64]
    t = ((cols / 63 + rows / 36) / 2)[..., None]
    return (np.array([0.05, 0.1, 0.4]) * (1 - t) + np.array([0.8, 0.5, 0.1]) * t).astype(np.float32)


def test_dds_is_bc1_with_every_level(tmp_path):
    image = two_colour_ramp()
    path = tmp_path / "t.dds"
    path.write_bytes(dds_bytes(image))
    levels = read_dds_levels(path)
    assert [lv.shape for lv in levels] == [(h, w, 4) for w, h in mip_sizes(64, 37)]
    for got, want in zip(levels, mip_chain(image)):
        assert_block_compressed_close(got[..., :3], linear_to_srgb8(want), mean=5, worst=24)
        assert (got[..., 3] == 255).all()
    raw = path.read_bytes()
    assert raw[84:88] == b"DXT1" and int.from_bytes(raw[28:32], "little") == 7     # FourCC, mip count
    # 8 bytes per 4 x 4 block, every level padded to whole blocks (1 x 1 -> one block)
    blocks = sum(-(-w // 4) * -(-h // 4) for w, h in mip_sizes(64, 37))
    assert len(raw) == 128 + 8 * blocks


def test_dds_with_alpha_is_bc3(tmp_path):
    rows, cols = np.mgrid[0:16, 0:16]
    alpha = (cols / 15)[..., None]
    image = np.concatenate([np.full((16, 16, 3), 0.2), alpha], axis=-1).astype(np.float32)
    path = tmp_path / "a.dds"
    path.write_bytes(dds_bytes(image))
    assert path.read_bytes()[84:88] == b"DXT5"
    top = read_dds_levels(path)[0]
    assert np.abs(top[..., 3].astype(int) - np.rint(alpha[..., 0] * 255)).max() <= 4   # BC3: 8 alpha steps a block
    assert np.abs(top[..., :3].astype(int) - linear_to_srgb8(image[..., :3])).max() <= 4


def test_ktx2_is_uastc_with_zstd_and_every_level(image):
    header, levels = read_ktx2(ktx2_bytes(image))
    assert (header["vk_format"], header["type_size"], header["width"], header["height"]) == (0, 1, 64, 37)
    assert (header["depth"], header["layers"], header["faces"], header["levels"]) == (0, 0, 1, 7)
    assert header["supercompression"] == 2                                        # Zstandard
    dfd = header["dfd"]
    assert (dfd["model"], dfd["primaries"], dfd["transfer"], dfd["block"]) == (166, 1, 2, (4, 4))   # UASTC, sRGB
    assert header["kv"]["KTXwriter"].startswith(b"Basis Universal")
    assert [lv.shape for lv in levels] == [(h, w, 4) for w, h in mip_sizes(64, 37)]
    assert all((lv[..., 3] == 255).all() for lv in levels)
    # pixels on smooth colour (white noise, the worst case, is off by 20 codes on average)
    smooth = two_colour_ramp()
    for got, want in zip(read_ktx2(ktx2_bytes(smooth))[1], mip_chain(smooth)):
        assert_block_compressed_close(got[..., :3], linear_to_srgb8(want), mean=3, worst=8)