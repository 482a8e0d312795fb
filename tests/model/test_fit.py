"""Single-exemplar fitting writes a sampler with the shipped contract, and it learns."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from model.export import export_model  # noqa: E402
from model.fit import detect_grain, fit_exemplar  # noqa: E402
from model.evaluate import load_candidates  # noqa: E402
from model.networks import ModelConfig, TextureSpace  # noqa: E402


def test_fit_writes_a_contract_sampler_and_its_code(tmp_path, skimage_textures, vgg):
    torch.manual_seed(0)
    export_model(TextureSpace(ModelConfig()), tmp_path / "space")
    image = tmp_path / "gravel.png"
    Image.fromarray((skimage_textures["gravel"] * 255).astype(np.uint8)).save(image)
    seen = []
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=tmp_path / "space" / "space.pt",
                          minutes=0.05, patch=32, progress=seen.append, grain="auto")
    assert result["steps"] >= 1 and seen and 0 < seen[-1] <= 1
    assert result["grain"] is None  # gravel: detected as isotropic
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


def _streaks(size: int = 256, angle_degrees: float = 0.0) -> np.ndarray:
    """Wood-like streaks: bands of many widths whose brightness changes across image x
    (so they run up-down at angle 0), turned by ``angle_degrees``, with a little noise."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    across = x * np.cos(np.radians(angle_degrees)) + y * np.sin(np.radians(angle_degrees))
    value = sum(np.sin(across * f + rng.uniform(0, 6.3)) / f ** 0.5 for f in rng.uniform(0.03, 0.8, 12))
    value = 0.5 + 0.1 * value + 0.01 * rng.standard_normal((size, size))
    return np.repeat(np.clip(value, 0, 1)[..., None], 3, axis=2)


def test_detect_grain_finds_axis_aligned_streaks_only(skimage_textures):
    assert detect_grain(_streaks()) == "y"                     # bands across x: the grain runs up-down
    assert detect_grain(_streaks().transpose(1, 0, 2)) == "x"
    assert detect_grain(_streaks(angle_degrees=45)) is None    # a fit can stretch along x or y only
    assert detect_grain(np.full((64, 64, 3), 0.5)) is None     # flat: no gradients at all
    for name in ("grass", "gravel"):                           # isotropic photos
        assert detect_grain(skimage_textures[name]) is None, name
