"""BC7 DDS textures (worker/gpu_textures.py, ``compression="bc7"``): the DX10 header's fields
and every mip level decoded by ``texture2ddecoder``, a decoder that shares no code with the
encoder (etcpak's bc7enc), then compared with the exact mip chain."""
from __future__ import annotations

import numpy as np
import pytest

from tests.worker.gpu_readers import read_bc7_dds, read_dds_levels
from worker.colour import linear_to_srgb8
from worker.errors import InvalidParameter
from worker.gpu_textures import (DXGI_FORMAT_BC7_UNORM, DXGI_FORMAT_BC7_UNORM_SRGB, check_gpu_options, dds_bytes,
                                 gpu_texture_bytes, mip_chain, mip_sizes)
from worker.regions import render_region

W, H = 64, 37                       # odd height: every level below is padded to whole blocks


def gradient_with_noise(seed: int = 0) -> np.ndarray:
    """A smooth colour gradient with fine noise, (H, W, 3) linear 0..1: what a texture is
    like to a block encoder (slow change plus grain)."""
    rows, cols = np.mgrid[0:H, 0:W] / np.array([H - 1, W - 1])[:, None, None]
    smooth = np.stack([0.1 + 0.7 * cols, 0.15 + 0.6 * rows, 0.4 + 0.3 * np.sin(5 * cols + 3 * rows)], axis=-1)
    noise = np.random.default_rng(seed).normal(0.0, 0.01, smooth.shape)
    return np.clip(smooth + noise, 0.0, 1.0).astype(np.float32)


def test_bc7_dds_header_and_every_level_decode_close(tmp_path):
    image = gradient_with_noise()
    header, levels = read_bc7_dds(dds_bytes(image, "bc7"))
    assert (header["width"], header["height"], header["mips"]) == (W, H, len(mip_sizes(W, H))) == (64, 37, 7)
    assert header["dxgi_format"] == DXGI_FORMAT_BC7_UNORM_SRGB == 99         # colour: sRGB
    assert (header["dimension"], header["misc"], header["array_size"], header["alpha_mode"]) == (3, 0, 1, 3)
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(W, H)
    bc1_path = tmp_path / "bc1.dds"
    bc1_path.write_bytes(dds_bytes(image, "bc1"))
    bc1_levels = read_dds_levels(bc1_path)
    for k, (got, bc1, want) in enumerate(zip(levels, bc1_levels, mip_chain(image))):
        want = linear_to_srgb8(want[..., :3]).astype(np.int16)
        error = np.abs(got[..., :3] - want).mean()
        assert (got[..., 3] == 255).all(), k                                  # opaque: alpha exactly 255
        # the two large levels within 3 codes; a level of a few texels holds the whole
        # image's colour range in one block, more than its two colour lines can (BC1's one
        # line does worse): there BC7 is only no worse than BC1 (measured: 1.55, 2.03,
        # 3.70, 9.0, 14.5 codes, then 0; BC1 2.34, 3.58, 6.73, 14.6, 20.1, 1.67, 0.67)
        assert error < 3 if k < 2 else error <= np.abs(bc1[..., :3] - want).mean(), (k, error)


def test_bc7_is_closer_than_bc1():
    """The point of BC7: a smaller error than BC1's on the same image (here 1.57 codes
    against 2.41; on 256 x 256 photo crops 1.0-1.3 against 2.6-2.8)."""
    import texture2ddecoder

    image = gradient_with_noise(1)[:32]                                       # 64 x 32: whole blocks, no padding
    want = linear_to_srgb8(image).astype(np.int16)
    bc1 = dds_bytes(image, "bc1")
    decoded = np.frombuffer(texture2ddecoder.decode_bc1(bc1[128:128 + 8 * 16 * 8], 64, 32), np.uint8)
    bc1_error = np.abs(decoded.reshape(32, 64, 4)[..., [2, 1, 0]] - want).mean()
    bc7_error = np.abs(read_bc7_dds(dds_bytes(image, "bc7"))[1][0][..., :3] - want).mean()
    assert bc7_error < 0.7 * bc1_error, (bc7_error, bc1_error)


def test_bc7_of_data_is_unorm_and_stores_the_values():
    """A data map (normals, roughness) is stored as it is, not sRGB-encoded, and says so."""
    image = gradient_with_noise(2)
    header, levels = read_bc7_dds(dds_bytes(image, "bc7", srgb=False))
    assert header["dxgi_format"] == DXGI_FORMAT_BC7_UNORM == 98
    want = np.rint(image * 255)
    assert np.abs(levels[0][..., :3] - want).mean() < 3


def test_bc7_with_alpha_keeps_it_straight():
    rows, cols = np.mgrid[0:16, 0:16]
    image = np.concatenate([np.full((16, 16, 3), 0.2), (cols / 15)[..., None]], axis=-1).astype(np.float32)
    header, levels = read_bc7_dds(dds_bytes(image, "bc7"))
    assert header["alpha_mode"] == 1                                          # DDS_ALPHA_MODE_STRAIGHT
    assert np.abs(levels[0][..., 3].astype(int) - np.rint(cols / 15 * 255)).max() <= 4
    assert np.abs(levels[0][..., :3].astype(int) - linear_to_srgb8(image[..., :3])).max() <= 4


def test_openimageio_reads_the_bc7_dds_as_texture2ddecoder_does(tmp_path):
    """OpenImageIO 3 (the project's binding; not Debian 12's iinfo 2.4) reads the DX10 BC7
    file, every level, to the same pixels as the independent decoder."""
    import OpenImageIO as oiio

    path = tmp_path / "t.dds"
    path.write_bytes(dds_bytes(gradient_with_noise(), "bc7"))
    spec = oiio.ImageInput.open(str(path))
    assert spec.spec().getattribute("compression") == "BC7"
    assert "srgb" in spec.spec().getattribute("oiio:ColorSpace").lower()
    spec.close()
    ours = read_bc7_dds(path.read_bytes())[1]
    theirs = read_dds_levels(path)
    assert len(theirs) == len(ours) and all(np.array_equal(a, b) for a, b in zip(theirs, ours))


def test_bc7_is_refused_without_a_dds():
    check_gpu_options("dds", "bc7")
    for fmt, compression in ((None, "bc7"), ("ktx2", "bc7"), ("dds", "bc5"), ("dds", "BC7")):
        with pytest.raises(InvalidParameter):
            check_gpu_options(fmt, compression)
    with pytest.raises(InvalidParameter):
        gpu_texture_bytes(gradient_with_noise(), "ktx2", "bc7")


def test_region_as_bc7_dds(waves, tmp_path):
    out = render_region(waves, np.zeros(8, np.float32), 0, z=6, x0=-20, y0=13, width=72, height=40, fmt="dds",
                        dds_compression="bc7", out_path=tmp_path / "r.dds")
    header, levels = read_bc7_dds(out.read_bytes())
    assert (header["width"], header["height"], header["dxgi_format"]) == (72, 40, 99)
    assert [lv.shape[:2][::-1] for lv in levels] == mip_sizes(72, 40)
    calls = len(waves.calls)
    with pytest.raises(InvalidParameter):           # refused before anything renders
        render_region(waves, np.zeros(8, np.float32), 0, z=6, x0=0, y0=0, width=8, height=8, fmt="png",
                      dds_compression="bc7", out_path=tmp_path / "r.png")
    assert len(waves.calls) == calls and not (tmp_path / "r.png").exists()
