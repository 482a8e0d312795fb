"""eval/detail.py: a fit's tiles at the photo's own scale, with and without its detail sampler."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

MODEL_DIR = Path(__file__).resolve().parents[2] / "model" / "weights"


@pytest.fixture(scope="module")
def fit_dirs(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A 512-px photo and two fit folders: the shipped sampler as the fit, one with a detail
    sampler (the space grown by one octave, its columns drawn) and one whose stage was not kept."""
    from model.detail import grow_octaves
    from model.export import export_sampler
    from model.networks import load_checkpoint

    root = tmp_path_factory.mktemp("detail-eval")
    rng = np.random.default_rng(0)
    photo = root / "speckle.png"
    Image.fromarray((rng.random((512, 512, 3)) * 255).astype(np.uint8)).save(photo)
    model, _ = load_checkpoint(MODEL_DIR / "space.pt")
    grown = grow_octaves(model, 1)
    with torch.no_grad():
        columns = grown.field.decoder.from_noise.weight
        columns[:, model.cfg.n_octaves * 3:] = 3 * torch.randn(columns.shape[0], 3)
    folders = []
    for name, kept in (("kept", True), ("dropped", False)):
        folder = root / name
        folder.mkdir()
        shutil.copy(MODEL_DIR / "sampler.onnx", folder / "sampler.onnx")
        (folder / "code.json").write_text(json.dumps({"code": [0.0] * 8}))
        stage = {"factor": 2, "steps": 10, "start": 1.0, "score": 0.5 if kept else 1.5, "kept": kept}
        if kept:
            export_sampler(grown.field, folder / "sampler_detail.onnx")
            stage["sampler"] = "sampler_detail.onnx"
        (folder / "manifest.json").write_text(json.dumps({"detail": stage}))
        folders.append(folder)
    return photo, *folders


def test_the_photo_is_measured_at_its_own_scale_with_and_without_the_stage(fit_dirs) -> None:
    from eval.detail import measure, to_markdown
    from worker.runtime import ModelRuntime

    photo, kept, dropped = fit_dirs
    model = ModelRuntime(MODEL_DIR)
    with_stage, without = measure(model, photo, kept), measure(model, photo, dropped)
    assert with_stage["factor"] == 2 and with_stage["zoom"] == 7 and with_stage["size"] == [512, 512]
    # the same fit: the working-size and magnified figures agree; the detail sampler draws other pixels
    assert with_stage["working"] == pytest.approx(without["working"])
    assert with_stage["native_fit"] == pytest.approx(without["native_fit"])
    assert with_stage["native_detail"] != pytest.approx(with_stage["native_fit"], rel=1e-3)
    assert without["native_detail"] == without["native_fit"]  # not kept: the texture serves the fit
    for key in ("working", "native_fit", "native_detail", "native_by_example"):
        assert np.isfinite(with_stage[key]) and with_stage[key] > 0
    table = to_markdown([with_stage, without], {"date": "today", "fit_seconds": 70, "detail_seconds": 20,
                                                "machine": "here"})
    assert "| speckle.png | 512x512 | 2 | 10 |" in table and "(not kept)" in table and "| **median** |" in table
