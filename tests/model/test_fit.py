"""Single-exemplar fitting writes a sampler with the shipped contract, and it learns."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from model.export import export_model  # noqa: E402
from model.fit import fit_exemplar  # noqa: E402
from model.evaluate import load_candidates  # noqa: E402
from model.networks import ModelConfig, TextureSpace  # noqa: E402


def test_fit_writes_a_contract_sampler_and_its_code(tmp_path, skimage_textures, vgg):
    torch.manual_seed(0)
    export_model(TextureSpace(ModelConfig()), tmp_path / "space")
    image = tmp_path / "gravel.png"
    Image.fromarray((skimage_textures["gravel"] * 255).astype(np.uint8)).save(image)
    seen = []
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=tmp_path / "space" / "space.pt",
                          minutes=0.05, patch=32, progress=seen.append)
    assert result["steps"] >= 1 and seen and 0 < seen[-1] <= 1
    code = json.loads((tmp_path / "fit" / "code.json").read_text())["code"]
    assert len(code) == 8
    session = ort.InferenceSession(str(tmp_path / "fit" / "sampler.onnx"), providers=["CPUExecutionProvider"])
    from model.colour import identity_colour  # the fitted sampler has the colour stage too

    rgb = session.run(None, {"points": np.random.default_rng(0).random((100, 3)), "colour": identity_colour()[None].numpy(),
                             "z": np.asarray([code], np.float32), "seed": np.asarray(1, np.int64)})[0]
    assert rgb.shape == (100, 3) and np.isfinite(rgb).all()
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert manifest["kind"] == "fitted" and manifest["code"] == code
    # the slim checkpoint beside it is what model.evaluate compares with the space's code
    (fit,) = load_candidates([tmp_path / "fit" / "fit.pt"])
    assert fit.label == "ours-fit" and fit.fitted_to == "gravel" and fit.code.reshape(-1).tolist() == code
