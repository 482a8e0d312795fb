"""eval/space_reach.py: a code-only fit learns the code and leaves the space as it was."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

MODEL_DIR = Path(__file__).resolve().parents[2] / "model" / "weights"


@pytest.mark.slow
def test_a_code_only_fit_moves_the_code_only_and_is_scored_through_the_space(tmp_path) -> None:
    import skimage.data

    from eval.quality import texture_code
    from eval.space_reach import code_fit, measure, summarise, to_markdown
    from worker.images import read_image
    from worker.runtime import ModelRuntime

    photo = tmp_path / "gravel.png"
    Image.fromarray(skimage.data.gravel()).convert("RGB").resize((256, 256)).save(photo)  # scikit-image: CC0
    model = ModelRuntime(MODEL_DIR)
    encoder_code = texture_code(model, read_image(photo.read_bytes(), max_pixels=1 << 26))[:model.code_size]

    fitted = code_fit(photo, MODEL_DIR / "space.pt", steps=2)  # raises if a weight of the space moved
    assert fitted["steps"] == 2 and len(fitted["code"]) == model.code_size
    # the code learned: Adam moves each number by about the rate, 2.5e-4 and 5e-4 at the first warm-up steps
    assert np.abs(np.asarray(fitted["code"]) - encoder_code).max() > 2e-4

    row = measure(model, photo, fitted["code"]) | {"steps": fitted["steps"]}
    assert all(np.isfinite(row[key]) and row[key] > 0 for key in ("uploaded", "encoder", "code_only"))
    # the encoder's own code, scored as a code-only one, is the encoder's figure: the codes compared alike
    assert measure(model, photo, encoder_code.tolist())["code_only"] == pytest.approx(row["encoder"], rel=1e-3)
    text = to_markdown([row], summarise([row]), {"date": "today", "machine": "here", "version": "v",
                                                 "exemplars": "val", "steps": 2})
    assert "| gravel |" in text and "| **median** |" in text
