"""Evaluation CLI on small random-init checkpoints and two real photos."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

from model import evaluate as ev  # noqa: E402
from model.networks import ModelConfig, TextureSpace  # noqa: E402

SETTINGS = ev.EvalSettings(patch=32, seeds=2, planes=1, code_crops=2)


def save_checkpoint(path: Path, variant: str, dims: int = 3, **extra) -> Path:
    torch.manual_seed(len(variant))
    cfg = ModelConfig(variant=variant, dims=dims, exemplar_short_side=64)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"config": cfg.to_dict(), "model": TextureSpace(cfg).state_dict(), "step": 3, "mode": "space", **extra}, path)
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory, skimage_textures):
    root = tmp_path_factory.mktemp("eval")
    exemplars = root / "exemplars"
    exemplars.mkdir()
    for name in ("brick", "gravel"):
        Image.fromarray((skimage_textures[name] * 255).astype(np.uint8)).save(exemplars / f"{name}.png")
    checkpoints = [
        save_checkpoint(root / "runs" / "ours" / "checkpoint.pt", "ours"),
        save_checkpoint(root / "runs" / "mlp" / "checkpoint.pt", "mlp"),
        save_checkpoint(root / "runs" / "flat" / "checkpoint.pt", "oursNoT", dims=2),
        save_checkpoint(root / "runs" / "fit" / "checkpoint.pt", "perlin", mode="single", data=["gravel"],
                        code=torch.zeros(1, 8)),
    ]
    return root, sorted(exemplars.iterdir()), checkpoints


def test_domain_planes():
    origins, axes = ev.domain_planes("2d", 4, seed=0)
    assert torch.all(origins[:, 2] == 0)
    assert torch.equal(axes[:, 0], torch.tensor([[1.0, 0, 0]] * 4, dtype=torch.float64))
    assert torch.equal(axes[:, 1], torch.tensor([[0, 1.0, 0]] * 4, dtype=torch.float64))
    _, oblique = ev.domain_planes("3d_oblique", 4, seed=0)
    assert torch.allclose(oblique.norm(dim=-1), torch.ones(4, 2, dtype=torch.float64))
    assert torch.all((oblique.abs() > 1e-3).sum(dim=-1) >= 2)  # not axis-aligned
    _, axis = ev.domain_planes("3d_axis", 3, seed=0)
    assert {tuple(a.abs().sum(dim=0).tolist()) for a in axis} == {(1, 1, 0), (1, 0, 1), (0, 1, 1)}


def test_success_uses_the_worst_style_error_per_exemplar_and_domain():
    rows = [
        {"exemplar": "a", "domain": "2d", "variant": "x", "style_error": 1.0, "diversity": 2.0},
        {"exemplar": "a", "domain": "2d", "variant": "y", "style_error": 4.0, "diversity": 3.0},
        {"exemplar": "b", "domain": "2d", "variant": "x", "style_error": 5.0, "diversity": 1.0},
    ]
    ev.add_success(rows)
    assert [r["success"] for r in rows] == [6.0, 0.0, 0.0]


def test_checks_count_fit_wins_per_domain_and_compare_slices():
    row = lambda e, v, d, s, div=1.0: {"exemplar": e, "variant": v, "domain": d, "style_error": s, "diversity": div}
    rows = [row("a", "ours", "3d_axis", 1.0), row("a", "ours", "3d_oblique", 3.0, div=0.5),
            row("b", "ours", "3d_axis", 3.0), row("b", "ours", "3d_oblique", 3.0),
            row("a", "ours-fit", "3d_axis", 0.5), row("b", "ours-fit", "3d_axis", 4.0, div=0.0)]
    result = ev.checks(rows)
    assert result["ours"] == {"min_diversity": 0.5, "oblique_over_axis": 1.5}
    assert result["ours-fit"]["fit_better"] == {"3d_axis": [1, 2]}
    assert result["ours-fit"]["min_diversity"] == 0.0


def test_fits_share_one_label_across_exemplars(tmp_path):
    paths = [save_checkpoint(tmp_path / name / "fit.pt", "ours", mode="single", data=[name], code=torch.zeros(1, 8))
             for name in ("brick", "gravel")]
    paths.append(save_checkpoint(tmp_path / "again" / "fit.pt", "ours", mode="single", data=["brick"],
                                 code=torch.zeros(1, 8)))
    labels = [c.label for c in ev.load_candidates(paths)]
    assert labels == ["ours-fit:brick/fit", "ours-fit", "ours-fit:again/fit"]


@pytest.mark.slow
def test_evaluate_rows_metrics_and_determinism(setup):
    _, exemplars, checkpoints = setup
    candidates = ev.load_candidates(checkpoints)
    assert [c.label for c in candidates] == ["ours", "mlp", "oursNoT", "perlin-fit"]
    report, images = ev.evaluate(candidates, exemplars, SETTINGS)
    rows = {(r["exemplar"], r["variant"], r["domain"]): r for r in report["results"]}
    # space models on every exemplar; the planar one in 2D only; the fit on its own exemplar
    assert {k for k in rows if k[1] == "ours"} == {(e, "ours", d) for e in ("brick", "gravel") for d in ev.DOMAINS}
    assert {k for k in rows if k[1] == "oursNoT"} == {("brick", "oursNoT", "2d"), ("gravel", "oursNoT", "2d")}
    assert {k for k in rows if k[1] == "perlin-fit"} == {("gravel", "perlin-fit", d) for d in ev.DOMAINS}
    for row in rows.values():
        assert np.isfinite(row["style_error"]) and row["style_error"] > 0
        assert row["success"] >= 0
    # position-only MLP ignores the seed: zero diversity; noise models vary with the seed
    assert all(rows[(e, "mlp", d)]["diversity"] == 0 for e in ("brick", "gravel") for d in ev.DOMAINS)
    assert all(rows[(e, "ours", d)]["diversity"] > 0 for e in ("brick", "gravel") for d in ev.DOMAINS)
    assert images[("gravel", "ours", "3d_oblique")].shape == (2, 32, 32, 3)
    assert images[("brick", None, None)].shape == (32, 32, 3)
    again, _ = ev.evaluate(candidates[:1], exemplars[:1], SETTINGS)
    first = [r for r in report["results"] if r["variant"] == "ours" and r["exemplar"] == "brick"]
    assert [r["style_error"] for r in again["results"]] == [r["style_error"] for r in first]
    assert [r["diversity"] for r in again["results"]] == [r["diversity"] for r in first]
    # another plane seed draws other planes and crops: how the spread of the metrics is measured
    moved, _ = ev.evaluate(candidates[:1], exemplars[:1], replace(SETTINGS, plane_seed=1))
    assert [r["style_error"] for r in moved["results"]] != [r["style_error"] for r in first]
    assert moved["settings"]["plane_seed"] == 1


@pytest.mark.slow
def test_cli_writes_json_markdown_and_grids(setup, tmp_path):
    root, exemplars, _ = setup
    runs = tmp_path / "runs"
    shutil.copytree(root / "runs" / "ours", runs / "ours")
    shutil.copytree(root / "runs" / "fit", runs / "fit")
    out = tmp_path / "eval"
    code = ev.main(["--checkpoint-dir", str(runs), "--exemplars", str(exemplars[0].parent), "--out", str(out),
                    "--patch", "32", "--seeds", "2", "--planes", "1", "--plane-seed", "3"])
    assert code == 0
    report = json.loads((out / "results.json").read_text())
    assert report["settings"]["plane_seed"] == 3
    assert {c["label"] for c in report["checkpoints"]} == {"ours", "perlin-fit"}
    assert report["summary"]["3d_oblique"]["ours"]["n"] == 2
    markdown = (out / "results.md").read_text()
    assert "| ours |" in markdown and "## 3d_axis" in markdown and "| brick | " in markdown
    assert "## Checks" in markdown and set(report["checks"]) == {"ours", "perlin-fit"}
    for domain in ev.GRID_DOMAINS:
        with Image.open(out / f"grid_{domain}.png") as grid:
            assert grid.size == ((1 + 2 * 2) * 34, 14 + 2 * 34)
    with pytest.raises(SystemExit):
        ev.main(["--checkpoint-dir", str(runs), "--seeds", "1"])
    # --group: every checkpoint under a folder is one named column
    code = ev.main(["--group", f"setting-a={root / 'runs' / 'fit'}", "--group", f"setting-b={runs / 'ours'}",
                    "--exemplars", str(exemplars[0].parent), "--out", str(tmp_path / "grouped"),
                    "--patch", "32", "--seeds", "2", "--planes", "1"])
    grouped = json.loads((tmp_path / "grouped" / "results.json").read_text())
    assert [c["label"] for c in grouped["checkpoints"]] == ["setting-a", "setting-b"]
    with pytest.raises(SystemExit):
        ev.main(["--group", str(runs)])
