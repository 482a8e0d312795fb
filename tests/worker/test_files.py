"""atomic_output: the result appears whole under its name, or not at all."""
import os
import stat

import pytest

from worker.files import atomic_output


def test_success_renames_into_place(tmp_path):
    target = tmp_path / "sub" / "result.npy"  # the folder does not exist yet
    with atomic_output(target, suffix=".npy") as tmp:
        assert os.path.dirname(tmp) == str(target.parent)  # same folder: the rename is atomic
        assert tmp.endswith(".npy") and tmp != str(target)
        assert not target.exists()  # nothing under the final name while writing
        with open(tmp, "wb") as f:
            f.write(b"payload")
    assert target.read_bytes() == b"payload"
    assert stat.S_IMODE(target.stat().st_mode) == 0o644
    assert os.listdir(target.parent) == ["result.npy"]  # no temporary file left


def test_success_overwrites_an_existing_file(tmp_path):
    target = tmp_path / "result.bin"
    target.write_bytes(b"old")
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as f:
            f.write(b"new")
    assert target.read_bytes() == b"new"
    assert os.listdir(tmp_path) == ["result.bin"]


@pytest.mark.parametrize("error", [ValueError("broken writer"), KeyboardInterrupt()])
def test_exception_leaves_no_file_and_no_temp(tmp_path, error):
    target = tmp_path / "result.png"
    with pytest.raises(type(error)):
        with atomic_output(target, suffix=".png") as tmp:
            with open(tmp, "wb") as f:
                f.write(b"half a file")
            raise error
    assert not target.exists()
    assert os.listdir(tmp_path) == []


def test_exception_keeps_the_previous_result(tmp_path):
    target = tmp_path / "result.zip"
    target.write_bytes(b"previous run")
    with pytest.raises(RuntimeError):
        with atomic_output(target, suffix=".zip"):
            raise RuntimeError("canceled")
    assert target.read_bytes() == b"previous run"
    assert os.listdir(tmp_path) == ["result.zip"]


def test_temp_removed_by_the_block_is_not_an_error(tmp_path):
    target = tmp_path / "result.raw"
    with pytest.raises(OSError):
        with atomic_output(target) as tmp:
            os.unlink(tmp)
            raise OSError("writer cleaned up after itself")
    assert os.listdir(tmp_path) == []


def test_every_format_offered_has_an_extension_and_a_media_type():
    """Every format an output offers (worker.files.OFFERED) is in the one table
    (worker.files.FORMATS), and each writer takes what the registry says it offers: a format
    added to one but not the other would fail only when a job names it."""
    from worker import decode
    from worker.bake import BAKE_FORMATS
    from worker.files import FORMATS, OCTET_STREAM, OFFERED, media_type_of_extension
    from worker.gpu_textures import GPU_FORMATS
    from worker.regions import REGION_FORMATS
    from worker.shader import LANGUAGES
    from worker.tiles import TILE_FORMATS
    from worker.volume_writers import VOLUME_FORMATS, WRITERS

    assert (TILE_FORMATS, VOLUME_FORMATS, REGION_FORMATS, BAKE_FORMATS, GPU_FORMATS, LANGUAGES) == tuple(
        OFFERED[output] for output in ("tile", "volume", "region", "bake", "gpu_texture", "shader"))
    assert set(WRITERS) == set(VOLUME_FORMATS) and set(GPU_FORMATS) <= set(REGION_FORMATS)
    offered = {fmt for formats in OFFERED.values() for fmt in formats} | {"zip", "onnx"}
    assert offered <= set(FORMATS), f"not in worker.files.FORMATS: {sorted(offered - set(FORMATS))}"
    for fmt in offered:
        assert FORMATS[fmt].extension.startswith(".") and "/" in FORMATS[fmt].media_type, fmt
    # every image an upload may be (what decode sniffs) is stored with its own media type
    assert all(media_type_of_extension(ext) != OCTET_STREAM for _, _, ext in decode._MAGIC)


def _image_writes(kind: str, fmt: str, sampler, path) -> bytes:
    import numpy as np

    from worker.images import write_image
    from worker.regions import render_region
    from worker.volumes import render_volume

    code = np.zeros(8, np.float32)
    if kind == "image":
        rgb = np.random.default_rng(1).random((24, 40, 3)).astype(np.float32)
        path.write_bytes(write_image(rgb, fmt))
    elif kind == "region":
        render_region(sampler, code, 3, z=6, x0=-5, y0=7, width=40, height=24, fmt=fmt, out_path=path)
    else:
        render_volume(sampler, code, 3, resolution=6, fmt=fmt, out_path=path)
    return path.read_bytes()


@pytest.mark.parametrize("kind", ["image", "region", "volume"])
@pytest.mark.parametrize("fmt", ["exr", "tiff"])
def test_images_carry_a_fixed_time_so_the_same_request_gives_the_same_bytes(waves, tmp_path, kind, fmt):
    # OpenImageIO stamps EXR parts (capDate) and TIFF pages with the time of writing unless
    # told otherwise: two runs of one request then differed in those bytes alone.
    import OpenImageIO as oiio

    from worker.files import IMAGE_DATETIME

    first = _image_writes(kind, fmt, waves, tmp_path / f"a.{fmt}")
    assert _image_writes(kind, fmt, waves, tmp_path / f"b.{fmt}") == first
    reader = oiio.ImageInput.open(str(tmp_path / f"a.{fmt}"))
    stamps = set()
    subimage = 0
    while reader.seek_subimage(subimage, 0):
        stamps.add(reader.spec().get_string_attribute("DateTime"))
        subimage += 1
    reader.close()
    assert stamps == {IMAGE_DATETIME} and IMAGE_DATETIME == "2020:01:01 00:00:00"
