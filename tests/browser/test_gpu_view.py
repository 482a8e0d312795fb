"""The page's live GPU view (service/static/js/gpuview.js): the texture's own GLSL shader on
a WebGL2 canvas (SwiftShader here), checked against the tile of the same region: not
blank, and the same pixels as tile (native zoom, 0, 0) up to 8-bit rounding. The first
frame includes compiling the shader, about a minute on the software renderer."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from .helpers import ALL_TILES_LOADED, canvas_pixels, page_errors, spatial_std, texture_photo_png, tile_image_pixels, upload

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]
FRAME_TIMEOUT_MS = 600_000


def test_live_gpu_view_matches_the_tile(page, base_url: str, artifacts: Path) -> None:
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    upload(page, "brick", texture_photo_png())
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    native = page.evaluate("window.texspace.textureMap.nativeZoom")
    tile = tile_image_pixels(page, native, 0, 0)

    page.click("#gpu-panel summary")
    page.wait_for_function("document.getElementById('gpu-view').dataset.state === 'drawn'", timeout=FRAME_TIMEOUT_MS)
    first_ms = float(page.eval_on_selector("#gpu-view", "c => c.dataset.frameMs"))
    page.locator("#gpu-panel").screenshot(path=str(artifacts / "gpu-view.png"))
    live = canvas_pixels(page, "#gpu-view")
    assert spatial_std(live) > 5, "the live view is blank"
    diff = np.abs(live.astype(int) - tile[: live.shape[0], : live.shape[1]].astype(int))

    # A new seed redraws at once (no compile): the frame time is the renderer's.
    page.fill("#seed", "3")
    page.dispatch_event("#seed", "change")
    page.wait_for_function("document.getElementById('gpu-view').dataset.state === 'drawn'", timeout=FRAME_TIMEOUT_MS)
    reseeded = canvas_pixels(page, "#gpu-view")
    frame_ms = float(page.eval_on_selector("#gpu-view", "c => c.dataset.frameMs"))
    report = {"size": list(live.shape[:2]), "mean_abs_8bit": float(diff.mean()), "max_abs_8bit": int(diff.max()),
              "first_frame_ms_with_compile": first_ms, "frame_ms": frame_ms,
              "status": page.text_content("#gpu-status")}
    (artifacts / "gpu_view.json").write_text(json.dumps(report, indent=2) + "\n")
    assert diff.mean() < 1.0 and diff.max() <= 2, report
    assert np.abs(reseeded.astype(int) - live.astype(int)).mean() > 2, "a new seed changes the view"
    assert not page_errors(page)
