"""The web page in headless Chromium against the real service: upload -> tiles on the map
-> pan and zoom fetch new tiles -> a seed change changes pixels -> a bake job -> the 3D
view renders the baked mesh. Screenshots of every step go to tests/artifacts/browser/.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .helpers import (
    ALL_TILES_LOADED,
    BAKE_TIMEOUT_MS,
    MAP_BACKGROUND,
    TILE_URL,
    TileLog,
    a_drawn_tile,
    canvas_pixels,
    map_pixels,
    page_errors,
    shoot,
    spatial_std,
    texture_photo_png,
    tile_image_pixels,
    upload,
    wait_for_new_tiles,
)

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]


def test_upload_browse_seed_and_bake(page, base_url: str, artifacts: Path) -> None:
    tiles = TileLog(page)
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")

    # 1. Upload through the file input (the drop zone's label) -> listed and shown.
    texture_id = upload(page, "brick", texture_photo_png(tint=(0.95, 0.7, 0.5)))
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    page.wait_for_function("() => document.getElementById('exemplar').naturalWidth > 0")
    shoot(page, artifacts, "1-uploaded")
    native = page.evaluate("window.texspace.textureMap.nativeZoom")
    first = wait_for_new_tiles(page, tiles, texture_id, set())  # response events may trail the loads
    assert {z for z, *_ in first} == {native}, "the map opens at the native zoom"
    # Centred on the world origin: tiles on both sides of it, negative indices included.
    assert any(x < 0 for _, x, _, _ in first) and any(x >= 0 for _, x, _, _ in first)
    assert all("seed=0" in q for *_, q in first)
    drawn = np.abs(map_pixels(page).astype(int) - MAP_BACKGROUND).max(axis=-1) > 2
    assert drawn.mean() > 0.95, "tiles cover the map"

    # 2. Pan by dragging: tiles that were not on screen are fetched.
    box = page.locator("#map").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx - 500, cy - 300, steps=12)
    page.mouse.up()
    panned = wait_for_new_tiles(page, tiles, texture_id, first)
    assert panned and {z for z, *_ in panned} == {native}
    assert max(x for _, x, _, _ in panned) > max(x for _, x, _, _ in first)
    shoot(page, artifacts, "2-panned")

    # 3. Zoom in with the +-button: tiles of the next zoom level are fetched.
    before_zoom = tiles.keys(texture_id)
    page.click(".leaflet-control-zoom-in")
    page.wait_for_function(f"() => window.texspace.textureMap.map.getZoom() === {native + 1}")
    zoomed = wait_for_new_tiles(page, tiles, texture_id, before_zoom)
    assert {z for z, *_ in zoomed} == {native + 1}
    shoot(page, artifacts, "3-zoomed")
    page.click("#native-zoom")
    page.wait_for_function(f"() => window.texspace.textureMap.map.getZoom() === {native}")
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)

    # 4. A new seed re-requests the tiles and changes the pixels.
    tile = a_drawn_tile(page)
    seed0 = tile_image_pixels(page, *tile)
    page.click("#seed-next")
    page.wait_for_function("""() => {
      const tiles = [...document.querySelectorAll('#map img.leaflet-tile')];
      return tiles.length > 0 && tiles.every((t) => t.src.includes('seed=1') && t.classList.contains('leaflet-tile-loaded'));
    }""", timeout=60_000)
    assert any("seed=1" in q for *_, q in tiles.keys(texture_id))
    seed1 = tile_image_pixels(page, *tile)
    assert seed0.shape == seed1.shape == (256, 256, 3)
    # Even an untrained model changes most pixels a little; a trained one, a lot.
    changed = np.abs(seed0.astype(int) - seed1.astype(int)).max(axis=-1) > 0
    assert changed.mean() > 0.2, f"tile {tile} with seed 1 looks like seed 0"
    shoot(page, artifacts, "4-seed1")

    # 4b. A slice of the solid: another plane at an offset re-requests every tile.
    page.select_option("#plane", "xz")
    page.fill("#offset", "0.5")
    page.wait_for_function("""() => {
      const tiles = [...document.querySelectorAll('#map img.leaflet-tile')];
      return tiles.length > 0 && tiles.every((t) => t.src.includes('plane=xz') && t.src.includes('offset=0.5')
                                              && t.classList.contains('leaflet-tile-loaded'));
    }""", timeout=60_000)
    assert page.text_content("#offset-value") == "0.50"
    shoot(page, artifacts, "4b-slice-xz")

    # 5. Bake onto the page's own sphere; follow the job live; the 3D view shows it.
    page.wait_for_selector("#viewer canvas")
    blank = canvas_pixels(page, "#viewer canvas")
    assert spatial_std(blank) < 1, "before a bake the 3D view is empty"
    page.select_option("#bake-resolution", "256")
    page.select_option("#bake-projection", "triplanar")
    with page.expect_request(lambda r: "/events" in r.url) as events:
        page.click("#bake-start")
    job_id = page.get_attribute("#jobs li[data-job-id]", "data-job-id")
    assert events.value.url.endswith(f"/v1/jobs/{job_id}/events"), "progress comes from server-sent events"
    page.wait_for_selector('#jobs li[data-state="succeeded"]', timeout=BAKE_TIMEOUT_MS)
    page.wait_for_selector("#viewer[data-loaded]", timeout=30_000)
    page.wait_for_timeout(300)  # one more animation frame after the load
    baked = canvas_pixels(page, "#viewer canvas")
    shoot(page, artifacts, "5-baked")
    assert spatial_std(baked) > 10, "the baked mesh is drawn"
    lit = np.abs(baked.astype(int) - blank.astype(int)).sum(axis=-1) > 30
    assert lit.mean() > 0.05, "the mesh covers a visible part of the view"
    assert page.locator('#jobs li[data-state="succeeded"] a[download]').count() >= 1
    assert page.request.get(f"{base_url}v1/jobs/{job_id}").json()["params"]["projection"] == "triplanar"

    # 6. A volume job: listed, followed to the end, downloadable.
    page.select_option("#volume-resolution", "32")
    page.click("#volume-start")
    page.wait_for_selector("#jobs li[data-job-id] >> nth=1")
    volume = page.locator("#jobs li").first
    volume.locator("xpath=self::li[@data-state='succeeded']").wait_for(timeout=BAKE_TIMEOUT_MS)
    href = volume.locator("a[download]").get_attribute("href")
    result = page.request.get(href)
    assert result.ok and len(result.body()) >= 32 ** 3 * 3 * 4, "npy of a 32^3 float32 RGB volume"
    shoot(page, artifacts, "6-volume")

    assert page.evaluate("window.texspace.textureMap.tilesFailed") == 0

    # 7. After a reload the recent jobs are listed again; the bake can be viewed in 3D.
    page.reload()
    page.wait_for_selector(f'#jobs li[data-job-id="{job_id}"][data-state="succeeded"]')
    assert page.locator("#jobs li").count() == 2
    page.click(f'#jobs li[data-job-id="{job_id}"] >> text=View in 3D')
    page.wait_for_selector("#viewer[data-loaded]", timeout=30_000)
    page.wait_for_timeout(300)
    assert spatial_std(canvas_pixels(page, "#viewer canvas")) > 10
    assert page.evaluate("window.texspace.textureMap.tilesFailed") == 0
    assert page_errors(page) == []


def test_interpolation_slider_and_strip(page, base_url: str, artifacts: Path) -> None:
    """Upload two (one dropped), pick A and B, move the slider: the blend is created and
    shown; the strip fills."""
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    a = upload(page, "gravel", texture_photo_png("gravel", (0.6, 0.7, 1.0)))
    b = upload(page, "grass", texture_photo_png("grass", (0.5, 1.0, 0.4)), drop=True)
    page.select_option("#interp-a", a)
    page.select_option("#interp-b", b)
    # (the strip makes its own blends at t = 0.25, 0.5, 0.75 meanwhile)
    def is_slider_blend(response) -> bool:
        return response.url.endswith("/v1/textures/interpolate") and '"t":0.3' in (response.request.post_data or "")

    with page.expect_response(is_slider_blend) as created:
        page.fill("#interp-t", "0.3")
    blend = created.value.json()
    assert created.value.status == 201 and blend["parents"] == {"a": a, "b": b, "t": 0.3}
    page.wait_for_function(f"() => document.body.dataset.texture === '{blend['id']}'")
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    assert page.eval_on_selector("#map img.leaflet-tile-loaded", "img => img.src").count(blend["id"]) == 1
    # Strip: t = 0, 0.25, 0.5, 0.75, 1, each a tile of its own texture.
    page.wait_for_function("""() => {
      const imgs = [...document.querySelectorAll('#strip img')];
      return imgs.length === 5 && imgs.every((img) => img.complete && img.naturalWidth > 0);
    }""", timeout=60_000)
    sources = page.eval_on_selector_all("#strip img", "imgs => imgs.map((img) => img.src)")
    assert a in sources[0] and b in sources[-1] and len({TILE_URL.search(u)["id"] for u in sources}) == 5
    shoot(page, artifacts, "7-interpolated")

    # The view lives in the URL hash: a reload (or a shared link) reopens it.
    page.click("#seed-next")
    page.click(".leaflet-control-zoom-out")
    page.wait_for_function("() => location.hash.includes('seed=1') && location.hash.includes('z=5')")
    view_before = page.evaluate("window.texspace.textureMap.view()")
    page.reload()
    page.wait_for_function(f"() => document.body.dataset.texture === '{blend['id']}'")
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    assert page.evaluate("window.texspace.textureMap.view()") == view_before
    assert page.input_value("#seed") == "1"
    # zoomed out, each tile is asked for again until the server answers with its exact
    # render (progressive zoom-out: a preview first), then shown from that answer
    page.wait_for_function("() => [...document.querySelectorAll('#map img.leaflet-tile')]"
                           ".every((t) => t._texspaceExact && t.complete && t.naturalWidth > 0)", timeout=90_000)
    sources = page.eval_on_selector_all("#map img.leaflet-tile", "i => i.map((t) => t.dataset.src || t.src)")
    assert sources and all("seed=1" in src and "/tiles/5/" in src for src in sources)
    assert page_errors(page) == []


def test_default_bake_mesh_is_a_closed_sphere(page, base_url: str, tmp_path: Path) -> None:
    """The OBJ the page uploads when no mesh is chosen is a watertight unit icosphere."""
    import trimesh

    page.goto(base_url)
    obj = page.evaluate("""async () => {
      const { sphereObjFile } = await import('./js/sphere.js');
      return await sphereObjFile().text();
    }""")
    (tmp_path / "sphere.obj").write_text(obj)
    mesh = trimesh.load(tmp_path / "sphere.obj", process=False)
    assert len(mesh.faces) == 1280 and mesh.is_watertight and mesh.is_winding_consistent
    assert np.allclose(np.linalg.norm(mesh.vertices, axis=1), 1.0, atol=1e-5)
    assert mesh.volume > 0.95 * 4 / 3 * np.pi * 0.97  # outward faces, close to the unit ball


def test_keyboard_reaches_upload_and_map(page, base_url: str) -> None:
    """Enter on the focused drop zone opens the file chooser; the map pans by keyboard."""
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    choosers = []
    # Registered before the key press: enabling file-chooser interception takes a round trip.
    page.on("filechooser", lambda chooser: choosers.append(chooser))
    page.focus("#drop-zone")
    page.keyboard.press("Enter")
    for _ in range(50):
        if choosers:
            break
        page.wait_for_timeout(100)
    assert len(choosers) == 1 and choosers[0].is_multiple()  # several photos upload one after another
    assert choosers[0].element.get_attribute("id") == "upload-file"
    assert page.get_attribute("#map", "tabindex") == "0", "the map takes keyboard focus"


def test_controls_are_labelled(page, base_url: str) -> None:
    """Every form control has an accessible name (label or aria-label)."""
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    unlabelled = page.evaluate("""() => [...document.querySelectorAll('input, select, button')]
        .filter((el) => !(el.labels && el.labels.length) && !el.getAttribute('aria-label')
                        && !el.textContent.trim() && !el.title)
        .map((el) => el.outerHTML.slice(0, 80))""")
    assert unlabelled == []
    assert page_errors(page) == []


def test_the_page_reads_the_servers_limits(page, base_url: str) -> None:
    """The fit budget, the planes and the sizes offered come from GET /v1/limits, not copies."""
    import httpx

    limits = httpx.get(f"{base_url.rstrip('/')}/v1/limits", timeout=30).json()
    page.goto(base_url)
    page.wait_for_function("() => document.querySelectorAll('#plane option').length > 0")
    offered = page.evaluate("""() => ({
        planes: [...document.querySelectorAll('#plane option')].map((o) => o.value),
        fit: Number(document.getElementById('fit-seconds').value),
        fitMax: Number(document.getElementById('fit-seconds').max),
        volumes: [...document.querySelectorAll('#volume-resolution option')].map((o) => Number(o.value)),
        bakes: [...document.querySelectorAll('#bake-resolution option')].map((o) => Number(o.value)),
    })""")
    assert offered["planes"] == limits["planes"]
    assert (offered["fit"], offered["fitMax"]) == (limits["fit_seconds"], limits["max_fit_seconds"])
    assert offered["volumes"] and max(offered["volumes"]) <= limits["max_volume_resolution"]
    assert offered["bakes"] and max(offered["bakes"]) <= limits["max_bake_resolution"]
    assert page_errors(page) == []
