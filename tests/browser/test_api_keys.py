"""The web page against a server with API keys on (TEXSPACE_API_KEYS_ENABLED=true, as in
compose.yaml): without a key the page says it needs one; with a key entered, every /v1
request carries X-API-Key (never in a URL), tiles are fetched with it and drawn from blob:
URLs, job progress streams through a fetch-read event stream, the result downloads, the
bake shows in the 3D view, and after a reload the stored key is used again.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from .helpers import (
    ALL_TILES_LOADED,
    BAKE_TIMEOUT_MS,
    MAP_BACKGROUND,
    canvas_pixels,
    map_pixels,
    page_errors,
    shoot,
    spatial_std,
    texture_photo_png,
    upload,
)

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]

PROTECTED = re.compile(r"/v1/(textures|jobs)")
JOB_GET = re.compile(r"/v1/jobs/[0-9a-f-]+$")
WRONG_KEY = "tsk_not-a-key"
TILE_SRC = re.compile(r"/v1/textures/[0-9a-f-]+/tiles/\d+/-?\d+/-?\d+\.png\?")


def test_page_with_api_keys(page, keyed_server: tuple[str, str], artifacts: Path) -> None:
    url, key = keyed_server
    requests: list[tuple[str, str | None]] = []  # (url, X-API-Key sent) of every request
    page.on("request", lambda r: requests.append((r.url, r.headers.get("x-api-key"))))

    # 1. No key: the 401s of the first calls make the page ask for one, visibly.
    page.goto(url)
    page.wait_for_selector("#api-key-section", state="visible")
    page.wait_for_function("() => document.getElementById('status').textContent.includes('needs an API key')")
    assert "error" in page.get_attribute("#status", "class")
    assert page.locator("#texture-list li").count() == 0
    shoot(page, artifacts, "keys-1-no-key")

    # 2. A wrong key is refused with a message of its own.
    page.fill("#api-key", WRONG_KEY)
    page.click("#api-key-save")
    page.wait_for_function("() => document.getElementById('status').textContent.includes('refused')")

    # 3. The real key: upload, tiles, exemplar.
    page.fill("#api-key", key)
    keyed_from = len(requests)
    with page.expect_response(lambda r: r.url.endswith("/v1/textures?limit=50") and r.status == 200):
        page.click("#api-key-save")
    texture_id = upload(page, "brick", texture_photo_png())
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    page.wait_for_function("() => document.getElementById('exemplar').naturalWidth > 0")
    tiles = page.eval_on_selector_all("#map img.leaflet-tile", "ts => ts.map((t) => [t.src, t.dataset.src])")
    assert tiles and all(src.startswith("blob:") and TILE_SRC.search(api) for src, api in tiles)
    assert all(texture_id in api for _, api in tiles)
    assert page.get_attribute("#exemplar", "src").startswith("blob:")
    drawn = np.abs(map_pixels(page).astype(int) - MAP_BACKGROUND).max(axis=-1) > 2
    assert drawn.mean() > 0.95, "tiles cover the map"
    assert spatial_std(map_pixels(page)) > 1, "the tiles are a texture, not a flat fill"
    shoot(page, artifacts, "keys-2-tiles")

    # 4. A bake: progress from the event stream (read with fetch: no polling), then the 3D view.
    page.wait_for_selector("#viewer canvas")
    page.select_option("#bake-resolution", "256")
    with page.expect_response(lambda r: "/events" in r.url) as events:
        page.click("#bake-start")
    assert events.value.status == 200 and events.value.request.headers.get("x-api-key") == key
    job_id = page.get_attribute("#jobs li[data-job-id]", "data-job-id")
    assert events.value.url.endswith(f"/v1/jobs/{job_id}/events")
    page.wait_for_selector(f'#jobs li[data-job-id="{job_id}"][data-state="succeeded"]', timeout=BAKE_TIMEOUT_MS)
    assert page.eval_on_selector(f'#jobs li[data-job-id="{job_id}"] progress', "p => p.value") == 1
    assert not [u for u, _ in requests if JOB_GET.search(u)], "progress came from the stream, not polling"
    page.wait_for_selector("#viewer[data-loaded]", timeout=30_000)
    page.wait_for_timeout(300)
    assert spatial_std(canvas_pixels(page, "#viewer canvas")) > 10, "the baked mesh is drawn"
    shoot(page, artifacts, "keys-3-baked")

    # 5. A volume: the download link fetches the result with the key.
    page.select_option("#volume-resolution", "32")
    page.click("#volume-start")
    page.wait_for_selector("#jobs li[data-job-id] >> nth=1")
    volume = page.locator("#jobs li").first
    volume.locator("xpath=self::li[@data-state='succeeded']").wait_for(timeout=BAKE_TIMEOUT_MS)
    with page.expect_download() as download:
        volume.locator("a[download]").click()
    assert download.value.suggested_filename.endswith(".npy")
    assert Path(download.value.path()).stat().st_size >= 32 ** 3 * 3 * 4

    # 6. Reload: the stored key is used again, without asking.
    page.reload()
    page.wait_for_function(f"() => document.body.dataset.texture === '{texture_id}'")
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    page.wait_for_selector(f'#jobs li[data-job-id="{job_id}"][data-state="succeeded"]')
    assert "needs an API key" not in page.text_content("#status")
    assert page.evaluate("window.texspace.textureMap.tilesFailed") == 0

    # (a late request of step 2 may still carry the wrong key; none goes without one)
    protected = [sent for u, sent in requests[keyed_from:] if PROTECTED.search(u)]
    assert protected.count(key) > 20 and set(protected) <= {key, WRONG_KEY}, \
        "once entered, the key goes with every request for textures, tiles and jobs"
    assert not [u for u, _ in requests if key in u], "the key never goes into a URL"
    # Only the 401s of steps 1-2 may show as console errors.
    assert [e for e in page_errors(page) if "401" not in e] == []
