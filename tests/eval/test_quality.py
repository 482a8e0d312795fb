"""eval/quality.py: the value-noise baseline (pure numpy; no model, no VGG run)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch", reason="eval/quality.py imports model/ (the train extra)")


@pytest.fixture(scope="module")
def quality():
    import eval.quality

    return eval.quality


def test_value_noise_is_deterministic_per_seed(quality):
    a = quality.value_noise(64, 48, 16.0, 3, seed=1)
    assert a.shape == (64, 48, 3)
    np.testing.assert_array_equal(a, quality.value_noise(64, 48, 16.0, 3, seed=1))
    assert np.abs(a - quality.value_noise(64, 48, 16.0, 3, seed=2)).mean() > 0.05


def test_value_noise_is_stationary(quality):
    """Quadrants of a window many octave-0 cells wide have the same mean and spread."""
    noise = quality.value_noise(256, 256, 16.0, 1, seed=3)[..., 0]
    quadrants = [noise[:128, :128], noise[:128, 128:], noise[128:, :128], noise[128:, 128:]]
    means, stds = np.array([q.mean() for q in quadrants]), np.array([q.std() for q in quadrants])
    assert np.ptp(means) < 0.5 * noise.std()
    assert stds.max() / stds.min() < 1.25


def test_colour_match_gives_the_photo_mean_and_std(quality):
    rng = np.random.default_rng(0)
    photo = (0.4 + 0.05 * rng.standard_normal((64, 64, 3)) * [1.0, 0.5, 2.0]).astype(np.float32)
    for channels in (3, 1):
        matched = quality.colour_match(quality.value_noise(128, 128, 32.0, channels, seed=4), photo)
        assert matched.shape == (128, 128, 3) and matched.dtype == np.float32
        np.testing.assert_allclose(matched.reshape(-1, 3).mean(0), photo.reshape(-1, 3).mean(0), atol=1e-4)
        np.testing.assert_allclose(matched.reshape(-1, 3).std(0), photo.reshape(-1, 3).std(0), rtol=1e-3)
    # luminance-only: one noise drives all three channels (perfectly correlated)
    assert np.corrcoef(matched.reshape(-1, 3), rowvar=False).min() > 0.999


def test_baseline_tiles_sit_at_the_tile_positions(quality):
    photo = np.full((32, 32, 3), 0.5, np.float32)
    photo[::2] = 0.3
    tiles = quality.baseline_tiles(photo, 256.0, "lum")
    assert tiles.shape == (len(quality.SEEDS) * len(quality.POSITIONS), quality.TILE, quality.TILE, 3)
    # tiles (0, 0) and (1, 0) of one seed are neighbours on one field: they join without a seam
    seam = np.abs(tiles[0][:, -1] - tiles[1][:, 0]).mean()
    assert seam < 2 * np.abs(np.diff(tiles[0], axis=1)).mean()


def quality_row(oblique_over_axis: float, pattern_2d: bool = False) -> dict:
    """One photo's figures as measure_photo gives them, all within target but the ratio."""
    colour = {"de76": 0.1, "de2000": 0.1, "std_ratio": [1.0, 1.0, 1.0]}
    return {"colour": {"pooled": colour, "worst_tile": colour}, "style": {"win": True, "ours": 0.1},
            "diversity_min": 0.1, "style_oblique": oblique_over_axis, "style_axis": 1.0,
            "oblique_over_axis": oblique_over_axis, "pattern_2d": pattern_2d}


def test_the_oblique_targets_leave_out_2d_pattern_fits_and_report_them(quality):
    summary = quality.summarise([quality_row(1.0), quality_row(1.4), quality_row(4.0, pattern_2d=True)])
    assert summary["max_oblique_over_axis"] == 4.0                     # still reported, whole
    assert summary["oblique_over_axis"] == 1.2 and summary["pass"]["oblique_over_axis"]  # pooled over the solids
    assert summary["max_oblique_over_axis_solid"] == 1.4 and summary["oblique_over_axis_pattern_2d"] == [4.0]
    assert summary["pass"]["oblique_over_axis_worst_photo"]
    assert "lattice and stripe fits 4.00" in quality.to_markdown(
        {"models": {"m": {"summary": summary, "photos": {}, "model_dir": "d", "version": "v", "step": 1}}})
    # a solid that is not a 2D pattern is held to it
    solids = quality.summarise([quality_row(1.0), quality_row(1.6), quality_row(2.2)])
    assert not solids["pass"]["oblique_over_axis_worst_photo"] and not solids["pass"]["oblique_over_axis"]


def floor_row(ratio: float, by_example: float, value_noise: float, floor: float = 0.01) -> dict:
    """quality_row with the style-over-floor figures measure_photo adds."""
    row = quality_row(1.0)
    row["style"].update(baseline=0.2, baseline_kind="lum")  # what the per-photo tables read
    row["diversity"] = 0.1
    row["style_floor"] = {"floor": floor, "corner_errors": [floor] * 4, "error": ratio * floor, "ratio": ratio,
                          "by_example_error": by_example * floor, "by_example_ratio": by_example,
                          "value_noise_error": value_noise * floor, "value_noise_ratio": value_noise,
                          "value_noise_kind": "lum", "off_grid_error": 0.8 * floor, "off_grid_ratio": 0.8}
    return row


def test_the_summary_gives_median_ratios_over_the_floor(quality):
    rows = [floor_row(3.0, 2.0, 40.0), floor_row(1.5, 4.0, 10.0), floor_row(9.0, 1.2, 20.0)]
    summary = quality.summarise(rows)
    assert summary["median_floor_ratio"] == 3.0
    assert summary["median_floor_ratio_by_example"] == 2.0
    assert summary["median_floor_ratio_value_noise"] == 20.0
    assert summary["floor_ratio_below_by_example"] == [1, 3]
    # a photo without a floor (ratio None) is left out of the median, not counted as 0
    rows[2]["style_floor"]["ratio"] = None
    assert quality.summarise(rows)["median_floor_ratio"] == 2.25
    # reports from before the floor was measured have no floor figures
    assert quality.summarise([quality_row(1.0)])["median_floor_ratio"] is None


def test_the_markdown_has_a_floor_table_with_medians_and_an_empty_fit_column(quality):
    rows = {"bricks": floor_row(3.0, 2.0, 40.0), "gravel": floor_row(1.5, 4.0, 10.0)}
    entry = {"summary": quality.summarise(list(rows.values())), "photos": rows, "model_dir": "d",
             "version": "v", "step": 1}
    markdown = quality.to_markdown({"models": {"shipped": entry}})
    assert ("| photo | floor | shipped / floor | fit / floor | by-example / floor | value noise / floor (kind) "
            "| photo off grid / floor |") in markdown
    assert "| bricks | 0.0100 | 3.00 |  | 2.00 | 40.00 (lum) | 0.80 |" in markdown
    assert "| **median** | | **2.25** |  | **3.00** | **25.00** | **0.80** |" in markdown
    # a report from before the off-grid figure: its cells and median stay empty
    for row in rows.values():
        del row["style_floor"]["off_grid_ratio"]
    entry["summary"] = quality.summarise(list(rows.values()))
    assert "| **median** | | **2.25** |  | **3.00** | **25.00** |  |" in quality.to_markdown({"models": {"shipped": entry}})
    assert "no --fits given" in markdown
    fit = dict(entry, step="fit", photos={"bricks": floor_row(0.5, 2.0, 40.0)})
    fit["summary"] = quality.summarise(list(fit["photos"].values()))
    markdown = quality.to_markdown({"models": {"shipped": entry, "shipped-fit": fit}})
    assert "| bricks | 0.0100 | 3.00 | 0.50 | 2.00 | 40.00 (lum) |" in markdown
    assert "| gravel | 0.0100 | 1.50 |  | 4.00 | 10.00 (lum) |" in markdown
    assert "no --fits given" not in markdown


def test_one_photo_per_family_from_the_corpus_index(quality, tmp_path):
    """--families N: N families of the split beside index.json, one photo each (the first by
    name), the same choice every time; a train photo never comes from the val folder."""
    import json

    entries = [{"family": f"fam{i % 5}", "path": f"val/p{i:02d}.png"} for i in range(20)]
    entries.append({"family": "fam0", "path": "train/a00.png"})
    (tmp_path / "index.json").write_text(json.dumps({"exemplars": entries}))
    chosen = quality.one_per_family(tmp_path / "val", 3)
    assert len(chosen) == 3 and chosen == quality.one_per_family(tmp_path / "val", 3)
    families = {int(p.stem[1:]) % 5 for p in chosen}
    assert len(families) == 3  # three different families
    assert all(p.parent == tmp_path / "val" and int(p.stem[1:]) < 5 for p in chosen)  # each family's first
    assert set(quality.one_per_family(tmp_path / "val", 5)) == {tmp_path / "val" / f"p{i:02d}.png" for i in range(5)}
    with pytest.raises(ValueError, match="5 families"):
        quality.one_per_family(tmp_path / "val", 6)


def test_carry_keeps_a_model_measured_before_and_refuses_other_photos(quality, tmp_path):
    """--carry: the GPU fits' rows stay as measured when the encoder's column is re-measured;
    a missing label or rows of photos not measured now stop the run with the reason."""
    import json

    fit = {"model_dir": "runs/fits-gpu", "version": "per photo", "step": "fit",
           "photos": {"bricks": floor_row(0.5, 2.0, 40.0)}}
    (tmp_path / "results.json").write_text(json.dumps({"models": {"shipped": {}, "shipped-fit": fit}}))
    carried = quality.carried_models(tmp_path / "results.json", ["shipped-fit"], ["bricks", "gravel"])
    assert carried == {"shipped-fit": fit | {"carried": True}}
    assert quality.carried_models(tmp_path / "nothing.json", [], ["bricks"]) == {}
    with pytest.raises(SystemExit, match="holds no large-fit"):
        quality.carried_models(tmp_path / "results.json", ["large-fit"], ["bricks"])
    with pytest.raises(SystemExit, match="other photos \\(bricks\\)"):
        quality.carried_models(tmp_path / "results.json", ["shipped-fit"], ["gravel"])
    with pytest.raises(SystemExit, match="no earlier results"):
        quality.carried_models(tmp_path / "nothing.json", ["shipped-fit"], ["bricks"])


def test_the_photos_own_crops_say_how_uneven_its_colour_is(quality):
    """A photo dark on the left and light on the right has windows far from its mean; an
    even one does not; std ratios are crop over photo, the one furthest from 1 per channel."""
    rng = np.random.default_rng(0)
    even = (0.5 + 0.05 * rng.standard_normal((256, 256, 3))).clip(0, 1).astype(np.float32)
    halves = even.copy()
    halves[:, :128] -= 0.2
    flat, uneven = quality.own_crop_colour(even), quality.own_crop_colour(halves)
    assert flat["de76"] < 1.0 < 10.0 < uneven["de76"]
    assert all(0.9 < r < 1.1 for r in flat["std_ratio"]) and uneven["std_ratio"][0] < 0.7  # L: one tone a crop
    assert flat["windows"] == 9  # 128-px windows at 64-px steps: 3 x 3 on 256 px
    tall = quality.own_crop_colour(np.concatenate([even, halves]))  # 512 x 256: 7 x 3, ends flush
    assert tall["windows"] == 21 and tall["de76"] > 10.0


def test_the_worst_tile_shows_its_photos_own_crops_and_carried_rows_get_them(quality):
    tile = floor_row(1.0, 1.0, 10.0)
    tile["colour"]["worst_tile"] = {"de76": 6.0, "de2000": 4.0, "std_ratio": [1.0, 1.0, 1.0]}
    measured = dict(tile, colour=dict(tile["colour"], photo_crops={"de76": 6.5, "std_ratio": [0.8, 1.2, 1.0]}))
    now = {"shipped": {"photos": {"evil": measured}, "summary": quality.summarise([measured]), "model_dir": "w",
                       "version": "v", "step": 1}}
    carried = quality.with_photo_figures({"fit": {"photos": {"evil": tile}, "model_dir": "d", "version": "v",
                                                  "step": "fit"}}, now)
    summary = carried["fit"]["summary"]
    assert summary["max_de76_worst_tile_photo_crops"] == 6.5 and not summary["pass"]["de76_worst_tile"]
    markdown = quality.to_markdown({"models": now | carried})
    assert "| 6.00 **x** (its photo's crops 6.50) |" in markdown
    assert "| evil | 0.10 | 0.10 | 6.00 | 6.50 | 1.00/1.00/1.00 | 1.00/1.00/1.00 | 0.80/1.20/1.00 |" in markdown
    # a report from before the figure: empty cells, no note
    old = quality.summarise([floor_row(1.0, 1.0, 10.0)])
    assert old["max_de76_worst_tile_photo_crops"] is None and "photo's crops" not in quality.own_crops(old)
