"""Derived maps (height, normal) and mipmapped GPU textures (DDS, KTX2) as functions."""
import io

import numpy as np
import pytest
from PIL import Image

from tests.worker.gpu_readers import assert_block_compressed_close, read_dds_levels, read_ktx2
from worker.colour import linear_to_srgb8
from worker.derived_maps import (AO_RADII, ROUGHNESS_RANGE, ambient_occlusion, decode_normals8, derived_map_files,
                                 derived_maps, height_map, luminance, normal_map, read_height_range,
                                 roughness_map)
from worker.errors import InvalidParameter
from worker.gpu_textures import dds_bytes, ktx2_bytes, mip_chain, mip_sizes


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(7)
    return rng.random((37, 64, 3)).astype(np.float32)       # odd height: fractional mip weights


def test_height_is_the_linear_luminance_stretched_over_its_range(image):
    y = 0.2126 * image[..., 0] + 0.7152 * image[..., 1] + 0.0722 * image[..., 2]
    assert np.allclose(luminance(image), y, atol=1e-6)
    dim = 0.2 + 0.1 * image                                  # luminance 0.2..0.3: 10% of the range
    h, (low, high) = height_map(dim)
    assert h.shape == (37, 64) and h.dtype == np.float32 and (h.min(), h.max()) == (0.0, 1.0)
    assert (low, high) == pytest.approx((luminance(dim).min(), luminance(dim).max()))
    assert np.allclose(low + h * (high - low), luminance(dim), atol=1e-6)
    assert np.array_equal(height_map(np.ones((2, 2, 3)))[0], np.zeros((2, 2)))     # flat: all 0
    # a bake's atlas: the range of the covered texels only, the black background clipped to 0
    mask = np.zeros((37, 64), bool)
    mask[5:30, 10:50] = True
    atlas = np.where(mask[..., None], dim, 0.0)
    h, (low, _) = height_map(atlas, mask)
    assert low == pytest.approx(luminance(dim)[mask].min()) and h[~mask].max() == 0 and h[mask].max() == 1


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
    h = luminance(image)
    wrapped = normal_map(h, wrap=True)
    shifted = normal_map(np.roll(h, (5, 9), axis=(0, 1)), wrap=True)
    assert np.allclose(np.roll(wrapped, (5, 9), axis=(0, 1)), shifted, atol=1e-6)   # no border
    clamped = normal_map(h)
    assert np.allclose(clamped[1:-1, 1:-1], wrapped[1:-1, 1:-1], atol=1e-6)


def test_map_files_read_back(image):
    dim = 0.1 + 0.2 * image
    files = derived_map_files(dim, ("height", "normal"), strength=2.0)
    height = Image.open(io.BytesIO(files["height.png"]))
    normal = Image.open(io.BytesIO(files["normal.png"]))
    assert height.size == normal.size == (64, 37) and normal.mode == "RGB"
    codes = np.asarray(height)
    assert (codes.min(), codes.max()) == (0, 65535)                      # the full 16-bit range
    low, high = read_height_range(files["height.png"])                   # stated in the file (tEXt)
    assert (float(height.info["texspace:height_min"]), float(height.info["texspace:height_max"])) == (low, high)
    assert np.abs(low + codes / 65535 * (high - low) - luminance(dim)).max() <= (high - low) / 65535
    n = decode_normals8(np.asarray(normal))
    assert np.abs(np.linalg.norm(n, axis=-1) - 1).max() < 0.02          # unit length up to 8-bit codes
    assert np.abs(n - normal_map(height_map(dim)[0], 2.0)).max() <= 1 / 127.5 + 1e-6
    assert set(derived_map_files(image, ("normal",))) == {"normal.png"} and derived_map_files(image, ()) == {}
    assert set(derived_map_files(image, ("ao", "roughness"), stem="oak")) == {"oak_ao.png", "oak_roughness.png"}
    with pytest.raises(InvalidParameter):
        derived_map_files(image, ("gloss",))
    with pytest.raises(InvalidParameter):
        normal_map(np.zeros((4, 4)), strength=0)


def test_default_normals_are_not_flat_on_a_dim_low_contrast_texture():
    """A photo of concrete spans 27% of the luminance range; stretched, its normal map at the
    default strength tilts as much as a full-contrast one (mean |xy| 0.14 on the real photo)."""
    rng = np.random.default_rng(3)
    field = np.cumsum(np.cumsum(rng.standard_normal((128, 128)), axis=0), axis=1)   # smooth relief
    field = (field - field.min()) / np.ptp(field)
    grey = np.repeat((0.24 + 0.27 * field)[..., None], 3, axis=2).astype(np.float32)
    tilt = np.hypot(*derived_maps(grey, ("normal",)).arrays["normal"][..., :2].transpose(2, 0, 1)).mean()
    full = np.repeat(field[..., None], 3, axis=2).astype(np.float32)
    full_tilt = np.hypot(*derived_maps(full, ("normal",)).arrays["normal"][..., :2].transpose(2, 0, 1)).mean()
    assert tilt == pytest.approx(full_tilt, rel=1e-3)


def test_roughness_reads_fine_detail():
    rng = np.random.default_rng(5)
    flat = np.full((64, 64, 3), 0.4, np.float32)
    busy = np.clip(0.4 + 0.3 * rng.standard_normal((64, 64, 1)), 0, 1).repeat(3, axis=2).astype(np.float32)
    smooth, rough = roughness_map(flat), roughness_map(busy)
    assert smooth.dtype == np.float32 and smooth.shape == (64, 64)
    assert np.allclose(smooth, ROUGHNESS_RANGE[0]) and np.median(rough) == pytest.approx(ROUGHNESS_RANGE[1])
    assert ((rough >= ROUGHNESS_RANGE[0]) & (rough <= ROUGHNESS_RANGE[1])).all()
    # not stretched per image: a faint texture stays smoother than a busy one
    faint = (0.4 + 0.05 * (busy - 0.4)).astype(np.float32)
    assert ROUGHNESS_RANGE[0] < np.median(roughness_map(faint)) < np.median(rough) - 0.2
    assert np.allclose(roughness_map(busy, wrap=True), np.roll(roughness_map(np.roll(busy, 7, axis=1), wrap=True),
                                                               -7, axis=1), atol=1e-5)


def test_ambient_occlusion_darkens_hollows_only():
    h = np.ones((96, 96), np.float32)
    h[40:56, 40:56] = 0.0                                   # a square pit
    ao = ambient_occlusion(h)
    assert ao.dtype == np.float32 and 0 <= ao.min() and ao.max() <= 1
    assert ao[48, 48] < 0.9 and ao[10, 10] == pytest.approx(1.0)          # its floor is shadowed, the plain not
    assert ao[40, 40] < 0.2 and ao[40, 40] < ao[40, 48] < ao[48, 48]      # most in its corners, then by its walls
    pillar = ambient_occlusion(1 - h)
    assert pillar[48, 48] == pytest.approx(1.0) and pillar[48, 38] < 0.95   # its top is open, its foot not
    assert np.allclose(ambient_occlusion(np.full((8, 8), 0.5)), 1.0)
    assert len(AO_RADII) >= 4


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