"""read_image on good and broken inputs, encoder crops, writers."""
import io
import struct
import threading
import zlib

import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

from worker.colour import LUMA_709, even_lighting, linear_to_srgb, srgb_to_linear
from worker import decode, images
from worker.errors import InvalidImage, InvalidParameter, LimitExceeded
from worker.decode import sniff_format
from worker.encode import encode_image
from worker.images import png_bytes, read_image, thumbnail, write_image
from worker.photo import crop_starts, encoder_crops, resize_short_side, working_photo

MAX = 4096 * 4096
RNG = np.random.default_rng(5)
RGB8 = RNG.integers(0, 256, (40, 56, 3), dtype=np.uint8)


def pil_bytes(array, mode, fmt, **kw):
    buf = io.BytesIO()
    Image.fromarray(array, mode).save(buf, fmt, **kw)
    return buf.getvalue()


def oiio_bytes(array, ext, dtype, tmp_path):
    path = str(tmp_path / f"img.{ext}")
    spec = oiio.ImageSpec(array.shape[1], array.shape[0], array.shape[2], dtype)
    out = oiio.ImageOutput.create(path)
    assert out.open(path, spec) and out.write_image(array)
    out.close()
    return open(path, "rb").read()


def test_png_8bit_exact():
    img = read_image(pil_bytes(RGB8, "RGB", "PNG"), max_pixels=MAX)
    assert img.shape == (40, 56, 3) and img.dtype == np.float32
    assert np.array_equal((img * 255).round().astype(np.uint8), RGB8)


def test_16bit_png_and_tiff(tmp_path):
    rgb16 = RNG.integers(0, 65536, (32, 48, 3), dtype=np.uint16)
    for ext in ("png", "tif"):
        img = read_image(oiio_bytes(rgb16, ext, "uint16", tmp_path), max_pixels=MAX)
        assert np.allclose(img, rgb16 / 65535.0, atol=1e-6)


def test_exr_is_linear_and_becomes_srgb(tmp_path):
    linear = RNG.random((32, 32, 3), dtype=np.float32)
    linear[0, 0] = [np.nan, 5.0, -1.0]                      # junk an EXR can hold
    img = read_image(oiio_bytes(linear, "exr", "float", tmp_path), max_pixels=MAX)
    assert np.allclose(img[1:], linear_to_srgb(linear[1:]), atol=1e-6)
    assert img[0, 0].tolist() == [0.0, 1.0, 0.0]


def test_jpeg_webp_gray_rgba_cmyk():
    smooth = np.repeat(np.linspace(0, 255, 64, dtype=np.uint8)[None, :, None], 48, 0).repeat(3, 2)
    for fmt in ("JPEG", "WEBP"):
        img = read_image(pil_bytes(smooth, "RGB", fmt, quality=95), max_pixels=MAX)
        assert img.shape == (48, 64, 3) and np.abs(img * 255 - smooth).mean() < 3
    gray = read_image(pil_bytes(smooth[:, :, 0], "L", "PNG"), max_pixels=MAX)
    assert np.array_equal(gray[..., 0], gray[..., 2]) and np.allclose(gray[..., 1] * 255, smooth[..., 0])
    rgba = np.zeros((20, 20, 4), np.uint8)
    rgba[..., 0], rgba[:10, :, 3], rgba[10:, :, 3] = 255, 255, 0
    img = read_image(pil_bytes(rgba, "RGBA", "PNG"), max_pixels=MAX)
    assert np.allclose(img[0, 0], [1, 0, 0]) and np.allclose(img[15, 0], [0.5, 0.5, 0.5])  # mid grey
    cmyk = Image.new("CMYK", (24, 24), (0, 255, 255, 0))           # pure red in CMYK
    buf = io.BytesIO()
    cmyk.save(buf, "JPEG", quality=100)
    assert np.allclose(read_image(buf.getvalue(), max_pixels=MAX)[5, 5], [1, 0, 0], atol=0.02)


def test_animated_gif_first_frame():
    frames = [Image.new("RGB", (32, 32), c) for c in ((255, 0, 0), (0, 0, 255))]
    buf = io.BytesIO()
    frames[0].save(buf, "GIF", save_all=True, append_images=frames[1:], duration=100)
    assert np.allclose(read_image(buf.getvalue(), max_pixels=MAX)[0, 0], [1, 0, 0], atol=0.01)


def png_header_only(width, height):
    """A PNG that declares a huge size but carries almost no data (decompression bomb)."""
    ihdr = struct.pack(">2I5B", width, height, 8, 2, 0, 0, 0)
    chunk = lambda k, d: struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(k + d))  # noqa: E731
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 10)) + \
        chunk(b"IEND", b"")


def test_limits_checked_from_the_header():
    with pytest.raises(LimitExceeded, match="100000x100000"):     # OIIO's own guard
        read_image(png_header_only(100_000, 100_000), max_pixels=MAX)
    with pytest.raises(LimitExceeded, match="1144 MB image from a 68 byte file"):
        read_image(png_header_only(20_000, 20_000), max_pixels=MAX)
    with pytest.raises(LimitExceeded, match="56x40 = 2240 pixels"):  # ours, from the header
        read_image(pil_bytes(RGB8, "RGB", "PNG"), max_pixels=40 * 56 - 1)
    with pytest.raises(InvalidImage, match="at least"):
        read_image(pil_bytes(RGB8[:8], "RGB", "PNG"), max_pixels=MAX)


@pytest.mark.parametrize("data, message", [
    (b"", "empty"),
    (b"hello world, not an image", "unrecognised"),
    (b"\x89PNG\r\n\x1a\n" + b"garbage" * 20, "png"),
    (b"\xff\xd8\xff\xe0" + b"\x00" * 50, "jpg"),
])
def test_broken_inputs(data, message):
    with pytest.raises(InvalidImage, match=message):
        read_image(data, max_pixels=MAX)


def test_truncated_png_and_jpeg():
    noise = RNG.integers(0, 256, (128, 128, 3), dtype=np.uint8)
    for fmt in ("PNG", "JPEG"):
        data = pil_bytes(noise, "RGB", fmt)
        with pytest.raises(InvalidImage):
            read_image(data[: len(data) // 2], max_pixels=MAX)


def test_sniff_ignores_names():
    assert sniff_format(pil_bytes(RGB8, "RGB", "WEBP")) == "webp"
    assert sniff_format(pil_bytes(RGB8, "RGB", "TIFF")) == "tif"


def test_encoder_crops_grid_and_range(brick):
    crops = encoder_crops(brick, short_side=256, size=128, grid=3, dihedral=False)
    assert crops.shape == (9, 3, 128, 128) and crops.dtype == np.float32
    assert crops.min() >= -1 and crops.max() <= 1
    # brick is 512x512 -> resized to 256x256; crop (0, 0) is the top-left corner, crop 8 the
    # bottom-right one
    from worker.photo import resize_short_side
    work = resize_short_side(brick, 256) * 2 - 1
    assert np.allclose(crops[0], work[:128, :128].transpose(2, 0, 1))
    assert np.allclose(crops[8], work[128:, 128:].transpose(2, 0, 1))
    wide = np.zeros((100, 700, 3), np.float32)                     # upscaled to 128 x 896
    assert encoder_crops(wide, short_side=64, size=128, grid=3, dihedral=False).shape == (3, 3, 128, 128)


def test_crop_starts_are_flush_even_and_distinct():
    """The one grid rule the encoder's crops and the quality report's windows share."""
    assert crop_starts(256, 128, 3).tolist() == [0, 64, 128]
    assert crop_starts(300, 128, 3).tolist() == [0, 86, 172]   # the last flush with the border
    assert crop_starts(128, 128, 3).tolist() == [0]             # room for one position only
    assert crop_starts(130, 128, 5).tolist() == [0, 1, 2]       # duplicates dropped


def test_encoder_crops_come_in_eight_orientations(brick):
    """The grid's crops first, then each quarter turn, then the four mirrored: a crop of the
    photo turned by 90 degrees is among them, so is the mirror image."""
    plain = encoder_crops(brick, short_side=256, size=128, grid=3, dihedral=False)
    crops = encoder_crops(brick, short_side=256, size=128, grid=3)
    assert crops.shape == (72, 3, 128, 128)
    np.testing.assert_array_equal(crops[:9], plain)
    np.testing.assert_array_equal(crops[9:18], np.rot90(plain, 1, axes=(2, 3)))
    np.testing.assert_array_equal(crops[36:45], plain[..., ::-1])
    assert len({c.tobytes() for c in crops[:, :, :, :]}) == 72  # the brick has no symmetry: 72 different crops


def test_a_turned_or_mirrored_photo_gets_the_same_code(runtime, brick):
    """The upload's code is the mean over the crops' eight orientations: a photo turned by a
    quarter or mirrored is the same material and gets the same code; without the orientations
    the brick's code moves."""
    code = encode_image(runtime, brick)
    for changed in (np.rot90(brick), brick[:, ::-1], np.rot90(brick, 3)[::-1]):
        np.testing.assert_allclose(encode_image(runtime, np.ascontiguousarray(changed)), code, atol=1e-5)
    plain = encoder_crops(np.ascontiguousarray(np.rot90(brick)), short_side=runtime.short_side,
                          size=runtime.input_size, dihedral=False)
    assert np.abs(runtime.encode(plain).mean(0) - code).max() > 1e-3


def test_encode_image(runtime, brick):
    z = encode_image(runtime, brick)
    assert z.shape == (8,) and z.dtype == np.float32 and np.isfinite(z).all()
    assert np.array_equal(z, encode_image(runtime, brick))


@pytest.mark.parametrize("fmt", ["png", "webp", "jpeg", "exr", "tiff"])
def test_writers_are_deterministic_and_read_back(fmt):
    linear = srgb_to_linear(np.repeat(np.linspace(0, 1, 96, dtype=np.float32)[None, :, None], 64, 0)
                            .repeat(3, 2))
    data = write_image(linear, fmt)
    assert data == write_image(linear, fmt)
    back = read_image(data, max_pixels=MAX)                      # sRGB-encoded again
    tolerance = {"png": 0.5 / 255, "tiff": 1e-4, "exr": 2e-3, "webp": 6 / 255, "jpeg": 6 / 255}[fmt]
    assert np.abs(back - linear_to_srgb(linear)).mean() <= tolerance


def test_writer_rejects_bad_input():
    with pytest.raises(InvalidParameter):
        write_image(np.zeros((4, 4, 3), np.float32), "bmp")
    with pytest.raises(InvalidParameter):
        write_image(np.zeros((4, 4), np.float32), "png")


def test_thumbnail(brick):
    img = read_image(thumbnail(brick, max_side=100, fmt="png"), max_pixels=MAX)
    assert img.shape == (100, 100, 3)
    assert abs(img.mean() - brick.mean()) < 0.02


def test_long_thin_images_are_refused_from_the_header():
    """16 x 1,000,000 (under the pixel limit) used to be upscaled to 256 x 16,000,000."""
    with pytest.raises(InvalidImage, match="at most 16 times"):
        read_image(pil_bytes(np.zeros((16_000, 16), np.uint8), "L", "PNG"), max_pixels=MAX)
    assert read_image(pil_bytes(np.zeros((256, 16), np.uint8), "L", "PNG"), max_pixels=MAX).shape == (256, 16, 3)


def test_banded_decode_matches_a_whole_decode(monkeypatch):
    rgba = RNG.integers(0, 256, (61, 37, 4), dtype=np.uint8)
    whole = read_image(pil_bytes(rgba, "RGBA", "PNG"), max_pixels=MAX)
    monkeypatch.setattr(decode, "DECODE_BAND_PIXELS", 37 * 5)      # 13 bands, the last short
    assert np.array_equal(read_image(pil_bytes(rgba, "RGBA", "PNG"), max_pixels=MAX), whole)


def test_large_images_are_box_reduced_before_resizing(monkeypatch):
    smooth = np.linspace(0, 1, 1031 * 2063 * 3, dtype=np.float32).reshape(1031, 2063, 3)
    direct = resize_short_side(smooth, 256)
    monkeypatch.setattr("worker.photo.RESIZE_DIRECT_PIXELS", 1000)
    reduced = resize_short_side(smooth, 256)
    assert reduced.shape == direct.shape == (256, 512, 3)
    assert np.abs(reduced - direct).max() < 0.01
    with pytest.raises(LimitExceeded, match="limit"):
        resize_short_side(np.zeros((16, 4096, 3), np.float32), 4096)


def test_decode_budget_holds_pixels_while_the_image_lives():
    data = pil_bytes(RGB8, "RGB", "PNG")
    images.set_decode_budget(RGB8.shape[0] * RGB8.shape[1])
    try:
        first = read_image(data, max_pixels=MAX)
        assert images._budget.used == first.shape[0] * first.shape[1]
        done = threading.Event()
        threading.Thread(target=lambda: (read_image(data, max_pixels=MAX), done.set()), daemon=True).start()
        assert not done.wait(0.3)          # waits for room
        del first
        assert done.wait(5)
        assert images._budget.used == 0
    finally:
        images.set_decode_budget(None)


def test_png_bytes_round_trip():
    rng = np.random.default_rng(2)
    for shape in ((1, 1, 3), (1, 9, 3), (37, 16, 3), (64, 64, 3)):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        if shape[0] > 8:
            image[: shape[0] // 2] = 200                           # runs, as in a baked atlas
        decoded = Image.open(io.BytesIO(png_bytes(image)))
        assert decoded.mode == "RGB" and np.array_equal(np.asarray(decoded), image)
    big = rng.integers(0, 256, (600, 512, 3), dtype=np.uint8)       # deflated in parts, joined as one stream
    big[100:300] = 7
    for parts in (1, 2, 3):
        encoded = png_bytes(big, parts)
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(encoded))), big)
        assert zlib.decompress(encoded[41:-16]) == zlib.decompress(png_bytes(big, 1)[41:-16])


def test_png_bytes_writes_16_bit_grey_and_refuses_what_png_cannot_hold():
    rng = np.random.default_rng(3)
    height = rng.integers(0, 65536, (33, 20), dtype=np.uint16)
    height[:5] = 0x1234                                             # two different bytes per sample
    decoded = Image.open(io.BytesIO(png_bytes(height)))
    assert decoded.mode.startswith("I") and np.array_equal(np.asarray(decoded).astype(np.uint16), height)
    grey8 = rng.integers(0, 256, (7, 5), dtype=np.uint8)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png_bytes(grey8)))), grey8)
    for bad in (np.zeros((4, 4, 4), np.uint8), np.zeros((4, 4), np.float32), np.zeros(4, np.uint8)):
        with pytest.raises(InvalidParameter):
            png_bytes(bad)


def _shaded_texture(size=(192, 256), strength=0.6):
    """A grainy texture (linear light) and the same under a light falling off across it and
    a vignette (about 2.6x between its brightest and darkest corners)."""
    from scipy import ndimage

    rng = np.random.default_rng(4)
    detail = ndimage.gaussian_filter(rng.standard_normal(size + (3,)), (2, 2, 0))
    clean = np.clip(0.25 * np.exp(2.0 * detail), 0, 1)
    y, x = np.mgrid[0:size[0], 0:size[1]] / max(size)
    shade = (1 - strength * (x - 0.3)) * (1 - strength * ((x - 0.5) ** 2 + (y - 0.6) ** 2))
    return clean, clean * shade[..., None]


def _block_luminance(linear, blocks=4):
    """Mean luminance of a blocks x blocks grid of the image: how its light varies across it."""
    h, w = linear.shape[0] // blocks * blocks, linear.shape[1] // blocks * blocks
    lum = linear[:h, :w] @ LUMA_709
    return lum.reshape(blocks, h // blocks, blocks, w // blocks).mean(axis=(1, 3))


def test_even_lighting_divides_out_a_smooth_shading_and_keeps_the_detail():
    clean, shaded = _shaded_texture()
    evened = srgb_to_linear(even_lighting(linear_to_srgb(shaded)))
    assert evened.shape == shaded.shape and evened.dtype == np.float32
    spread = lambda lum: lum.max() / lum.min()  # noqa: E731
    assert spread(_block_luminance(shaded)) > 1.8                        # the light across the photo
    assert spread(_block_luminance(evened)) < 1.15 * spread(_block_luminance(clean))
    # what is left is the texture itself, times one brightness: its grains are all still there
    ratio = np.log(np.maximum(evened, 1e-3) / np.maximum(clean, 1e-3)).mean(axis=-1)
    assert ratio.std() < 0.05
    # an evenly lit photo is left nearly as it is
    kept = srgb_to_linear(even_lighting(linear_to_srgb(clean)))
    assert np.abs(kept - clean).mean() < 0.01


def test_working_photo_evens_only_when_asked():
    _, shaded = _shaded_texture((300, 400))
    photo = linear_to_srgb(shaded)
    as_is = working_photo(photo, 96)
    assert as_is.shape == (96, 128, 3) and np.array_equal(as_is, resize_short_side(photo, 96))
    evened = working_photo(photo, 96, "even")
    assert np.array_equal(evened, even_lighting(as_is))
    with pytest.raises(InvalidParameter, match="lighting must be one of as-is, even"):
        working_photo(photo, 96, "flat")


def test_a_decoders_message_names_no_server_path(tmp_path) -> None:
    """A truncated EXR's problem said 'EXR Error (/tmp/texspace-img-.../upload.exr)': the
    temporary folder is cut out of what the client reads."""
    path = str(tmp_path / "real.exr")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(32, 32, 3, oiio.HALF))
    out.write_image(np.random.default_rng(0).random((32, 32, 3)).astype(np.float32))
    out.close()
    with pytest.raises(InvalidImage) as error:
        read_image((tmp_path / "real.exr").read_bytes()[:200], max_pixels=1 << 20)
    assert "upload.exr" in str(error.value) and "texspace-img-" not in str(error.value)
