"""The large corpus (model/corpus.py): filter, dedupe, families, split, licences, sources.

No network: the image tests synthesise their arrays; the index test skips unless
``python -m model.corpus fetch`` has been run.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from model import corpus
from model.corpus import (
    DEFAULT_CORPUS_DIR,
    MIN_VAL_FAMILIES,
    SOURCES,
    dep5_stanzas,
    family_of,
    is_candidate,
    licence_of,
    near_duplicates,
    photo_rejections,
    split_of,
)

ROOT = Path(__file__).resolve().parents[2]


def photo_like(size: int = 256, seed: int = 0) -> np.ndarray:
    """(size, size, 3) uint8 noise with some large-scale structure: passes the filter."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((size // 16, size // 16, 3))
    base = np.kron(coarse, np.ones((16, 16, 1)))
    return np.clip((0.6 * base + 0.4 * rng.random((size, size, 3))) * 255, 0, 255).astype(np.uint8)


def test_filter_keeps_a_photo_like_image():
    assert photo_rejections(photo_like()) == ()


def test_filter_rejects_a_flat_image():
    flat = np.full((256, 256, 3), 120, dtype=np.uint8)
    flat += np.random.default_rng(1).integers(0, 3, flat.shape, dtype=np.uint8)  # sensor-like noise
    assert "near_uniform" in photo_rejections(flat)


def test_filter_rejects_an_alpha_cut_sprite():
    rgb = photo_like()
    yy, xx = np.mgrid[:256, :256]
    alpha = np.where((yy - 128) ** 2 + (xx - 128) ** 2 < 90 ** 2, 255, 0).astype(np.uint8)  # a disc cut out
    assert "alpha_cutout" in photo_rejections(rgb, alpha)
    assert "alpha_cutout" not in photo_rejections(rgb, np.full((256, 256), 255, np.uint8))


def test_filter_rejects_a_normal_map():
    # tangent-space normals of a bumpy height field, encoded as (n + 1) / 2
    height = photo_like().mean(axis=2) / 255.0
    dy, dx = np.gradient(height * 4)
    normals = np.stack([-dx, -dy, np.ones_like(dx)], axis=2)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    encoded = np.round((normals + 1) / 2 * 255).astype(np.uint8)
    assert "normal_map" in photo_rejections(encoded)


def test_filter_rejects_small_strips_and_posterised_art():
    assert "too_small" in photo_rejections(photo_like(96))
    assert "strip" in photo_rejections(photo_like(256)[:100], full_size=(128, 512))
    cartoon = np.zeros((256, 256, 3), np.uint8)
    cartoon[:, :128] = (200, 40, 40)
    cartoon[128:, 128:] = (40, 200, 40)
    assert "posterised" in photo_rejections(cartoon)


def test_near_duplicates_catch_repeats_up_to_rotation_not_new_patterns():
    thumbs = np.stack([photo_like(16, seed) for seed in range(4)]).astype(np.float32) / 255
    batch = np.concatenate([thumbs, thumbs[1:2, ::-1].transpose(0, 2, 1, 3), np.clip(thumbs[2:3] + 0.01, 0, 1)])
    assert near_duplicates(batch).tolist() == [False, False, False, False, True, True]


def test_families_group_variants_and_ignore_the_source():
    source = {s.name: s for s in SOURCES}
    assert family_of(source["openarena"], "textures/gothic_block/blocks15_c.jpg") == "gothic_block"
    assert family_of(source["nexuiz"], "textures/e7/e7walldesign01b.jpg") == family_of(
        source["openarena"], "textures/e7/e7dimfloor.jpg") == "e7"
    assert family_of(source["ufoai"], "textures/tex_buildings/concrete024.png") == "tex_buildings/concrete"
    zero_ad = source["0ad"]
    terrain = "art/textures/terrain/types/"
    assert family_of(zero_ad, terrain + "alpine_arctic/grass_dirt_01.png.cached.dds") == "alpine_arctic/grass"
    assert family_of(zero_ad, terrain + "temp_grass_long.dds.cached.dds") == "temp/grass"
    assert family_of(zero_ad, terrain + "sahara/sand_01_wet.png.cached.dds") == family_of(
        zero_ad, terrain + "sahara/sand_02.png.cached.dds")


def test_split_is_deterministic_keeps_families_disjoint_and_holds_out_enough():
    families = sorted({f"set{k % 37}/material{k}" for k in range(400)})
    splits = {family: split_of(family) for family in families}
    assert splits == {family: split_of(family) for family in reversed(families)}  # order-independent
    val = [f for f, s in splits.items() if s == "val"]
    assert len(val) >= MIN_VAL_FAMILIES
    assert 0.15 < len(val) / len(families) < 0.35


def test_dep5_licences_take_the_last_matching_stanza():
    text = ("Files: *\nCopyright: team\nLicense: GPL-2+\n\n"
            "Files:\n base/textures/a/one.png\n base/textures/b/*\nCopyright: x\nLicense: CC-BY-3.0\n\n"
            "License: GPL-2+\n text\n")
    stanzas = dep5_stanzas(text)
    assert stanzas == [(("*",), "GPL-2+", "team"), (("base/textures/a/one.png", "base/textures/b/*"), "CC-BY-3.0", "x")]
    assert licence_of("base/textures/a/one.png", stanzas, ("?", "?")) == ("CC-BY-3.0", "x")
    assert licence_of("base/textures/b/two.jpg", stanzas, ("?", "?")) == ("CC-BY-3.0", "x")
    assert licence_of("base/textures/a/two.png", stanzas, ("?", "?")) == ("GPL-2+", "team")
    assert licence_of("other.png", [], ("CC0-1.0", "someone")) == ("CC0-1.0", "someone")


def test_candidates_skip_maps_decor_and_props():
    quake = next(s for s in SOURCES if s.name == "openarena")
    assert is_candidate(quake, "textures/gothic_block/blocks15.jpg")
    assert is_candidate(quake, "textures/e7/e7walldesign01b.jpg")  # "design" is not a "sign"
    for member in ("textures/gothic_block/blocks15_norm.tga", "textures/base_light/ceil1_30.jpg",
                   "textures/gothic_trim/border2.jpg", "textures/skies/stars.jpg",
                   "textures/evil4_metals/mtlpanel.jpg"):
        assert not is_candidate(quake, member), member


def test_sources_are_pinned_and_permissive():
    for source in SOURCES:
        assert len(source.sha256) == 64 and source.version
        assert source.default_licence in corpus.LICENCES


def test_no_source_mentions_robosuite():
    # robosuite's textures are reserved for independent evaluation
    for path in (ROOT / "model" / "corpus.py", ROOT / "model" / "data.py"):
        code = "\n".join(line for line in path.read_text().splitlines() if not line.lstrip().startswith("#"))
        assert "robosuite" not in code.lower()
    for source in SOURCES:
        assert "robosuite" not in repr(source).lower()


@pytest.mark.skipif(not (ROOT / DEFAULT_CORPUS_DIR / "index.json").exists(), reason="large corpus not fetched")
def test_fetched_corpus_index_is_consistent():
    folder = ROOT / DEFAULT_CORPUS_DIR
    index = json.loads((folder / "index.json").read_text())
    entries = index["exemplars"]
    assert len(entries) >= 300
    families = {split: {e["family"] for e in entries if e["split"] == split} for split in ("train", "val")}
    assert not families["train"] & families["val"]
    assert len(families["val"]) >= MIN_VAL_FAMILIES
    for entry in entries:
        assert entry["licence"] in corpus.LICENCES
        assert entry["split"] == split_of(entry["family"])
        assert "robosuite" not in entry["source_package"].lower()
        assert (folder / entry["path"]).exists()
