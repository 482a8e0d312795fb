"""Refinement by default, in the page: after an upload the page shows the fit job's
progress ("refining… NN%"), then reloads the map's tiles, now from the fitted sampler
(new URLs, new pixels). A real server with a real 3-second fit (the train extra)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from .helpers import (ALL_TILES_LOADED, TileLog, a_drawn_tile, page_errors, shoot, texture_photo_png, tile_image_pixels,
                      upload)

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]
FIT_TIMEOUT_MS = 180_000


def test_upload_shows_refinement_progress_then_fitted_tiles(page, refining_server: str, artifacts: Path) -> None:
    tiles = TileLog(page)
    page.goto(refining_server)
    page.wait_for_selector("#map.leaflet-container")
    # the brick (grain): its fit always draws new tiles; the gravel's 3-s fit, muted (detect_even),
    # may keep its start, which is now the served code, so its tiles need not change
    texture_id = upload(page, "brick", texture_photo_png("brick", (0.6, 0.7, 1.0)))
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)

    # the encoder's tiles at once, and the refinement's progress beside them
    page.wait_for_selector("#refinement:not([hidden])")
    assert page.text_content("#refinement").startswith(("refining… ", "queued for refinement ("))
    page.wait_for_function(
        "() => /^refining… \\d+%(, final in ~\\d+ (s|min))?$/.test(document.getElementById('refinement').textContent)",
        timeout=60_000)
    shoot(page, artifacts, "refine-1-refining")
    tile = a_drawn_tile(page)
    encoder_pixels = tile_image_pixels(page, *tile)
    assert all("v=" not in query for *_, query in tiles.keys(texture_id))

    # the job succeeds: the map reloads its tiles under new URLs, drawn by the fitted sampler
    page.wait_for_function("() => document.getElementById('refinement').dataset.state === 'succeeded'",
                           timeout=FIT_TIMEOUT_MS)
    page.wait_for_function("""() => {
      const tiles = [...document.querySelectorAll('#map img.leaflet-tile')];
      return tiles.length > 0 && tiles.every((t) => t.src.includes('v=fitted') && t.classList.contains('leaflet-tile-loaded'));
    }""", timeout=60_000)
    shoot(page, artifacts, "refine-2-refined")
    assert page.text_content("#refinement").startswith("refined")
    assert any("v=fitted" in query for *_, query in tiles.keys(texture_id))
    fitted_pixels = tile_image_pixels(page, *tile)
    assert np.abs(fitted_pixels.astype(int) - encoder_pixels.astype(int)).mean() > 1.0
    texture = page.evaluate("window.texspace.state.current")
    assert texture["sampler"] == "fitted" and texture["refinement"]["state"] == "succeeded"
    structure = texture["structure"]              # what the fit built in, said on the status line
    turned = f", straightened by {abs(structure['straightened']):.1f}°" if structure.get("straightened") else ""
    note = (f" (boards, grain along {structure['grain']}{turned})" if structure["lattice"] and structure["grain"] else
            " (follows the photo's repeat lattice)" if structure["lattice"] else
            f" (grain along {structure['grain']}{turned})" if structure["grain"] else "")
    if structure.get("detail_zoom"):  # (a 2-s detail stage: kept where it beat the fit)
        note += f"; the photo's own detail up to zoom {structure['detail_zoom']}"
    assert page.text_content("#refinement") == "refined: tiles from the fitted sampler" + note
    # opened again later, the texture still says what its tiles come from
    page.reload()
    page.wait_for_function("(text) => document.getElementById('refinement').textContent === text",
                           arg="tiles from the fitted sampler" + note, timeout=60_000)
    assert page_errors(page) == []


def test_a_queued_refinement_shows_its_place_and_estimate_not_zero_percent(page, refining_server: str) -> None:
    """Three uploads at once: the newest, on the map, waits behind the others; the page says
    how many fits go first and when refined tiles come, then follows it to the end."""
    for k in range(3):
        res = page.request.post(f"{refining_server.rstrip('/')}/v1/textures", multipart={"image": {
            "name": f"q{k}.png", "mimeType": "image/png", "buffer": texture_photo_png("gravel", (0.9, 0.8, 0.6))}})
        assert res.status == 201, res.text()
    newest = res.json()
    page.goto(refining_server)
    page.wait_for_selector(f'#texture-list button[data-id="{newest["id"]}"][aria-pressed="true"]')
    page.wait_for_selector("#refinement:not([hidden])")
    text = page.text_content("#refinement")
    queued = re.match(r"^queued for refinement \((\d+) ahead\), refined tiles in ~\d+ (s|min), final in ~\d+ (s|min)$",
                      text)
    assert queued and int(queued[1]) >= 1, text   # never "refining… 0%" while it waits
    assert "0%" not in text
    page.wait_for_function("() => document.getElementById('refinement').dataset.state === 'succeeded'",
                           timeout=FIT_TIMEOUT_MS)
    assert page_errors(page) == []
