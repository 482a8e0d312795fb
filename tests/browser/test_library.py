"""The page's library and jobs, as a user works with them: search by name, jobs labelled
by their texture, delete (with its jobs), a fit started from the page with its progress,
and the whole page usable at a phone's width."""
from __future__ import annotations

import json
import os
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.browser.helpers import serve
from .helpers import page_errors, shoot, texture_photo_png, upload

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]
FIT_TIMEOUT_MS = 240_000


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory, artifacts: Path) -> Iterator[str]:
    """A server of this module's own: its textures and jobs (deleted ones, fits) stay out of
    the page tests' server, whose job list they count."""
    data_dir = tmp_path_factory.mktemp("texspace-library-data")
    env = {**os.environ, "TEXSPACE_DATA_DIR": str(data_dir), "TEXSPACE_AUTO_FIT": "false"}
    with serve(data_dir, artifacts / "server-library.log", env) as url:
        yield url


def listed_names(page) -> list[str]:
    return page.locator("#texture-list button.pick .meta > span").all_inner_texts()


def test_search_label_and_delete(page, base_url: str, artifacts: Path) -> None:
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    page.fill("#upload-name", "library brick")
    brick = upload(page, "brick", texture_photo_png())
    page.fill("#upload-name", "library gravel")
    page.check("#upload-even-lighting")                   # the page sends the lighting asked for
    gravel = upload(page, "gravel", texture_photo_png("gravel", (0.6, 0.7, 1.0)))
    lighting = {t: json.load(urllib.request.urlopen(f"{base_url}v1/textures/{t}", timeout=30))["lighting"]
                for t in (brick, gravel)}
    assert lighting == {brick: "as-is", gravel: "even"}

    # search: by name, any case; no match says so
    page.fill("#texture-search", "GRAV")
    assert listed_names(page) == ["library gravel"]
    page.fill("#texture-search", "no such texture")
    assert listed_names(page) == [] and page.is_visible("#no-match")
    page.fill("#texture-search", "library")
    assert set(listed_names(page)) >= {"library brick", "library gravel"}
    assert not page.is_visible("#no-match")

    # a job is labelled by its texture's name
    page.click(f'#texture-list button.pick[data-id="{brick}"]')
    page.select_option("#volume-resolution", "32")
    page.click("#volume-start")
    job = page.locator(f'#jobs li[data-texture-id="{brick}"]').first
    job.wait_for()
    assert job.locator("strong").inner_text() == "volume 32^3 (npy) · library brick"
    page.wait_for_selector(f'#jobs li[data-texture-id="{brick}"][data-state="succeeded"]', timeout=120_000)
    shoot(page, artifacts, "library-1-search-and-job")

    # delete the texture on the map: asked first, then gone with its jobs; the next one is shown
    page.once("dialog", lambda dialog: dialog.accept())
    page.click(f'#texture-list button.delete[aria-label="Delete library brick"]')
    page.wait_for_selector(f'#texture-list button.pick[data-id="{brick}"]', state="detached")
    assert page.locator(f'#jobs li[data-texture-id="{brick}"]').count() == 0
    page.wait_for_function(f"() => window.texspace.state.current?.id === '{gravel}'")
    assert "Deleted library brick" in page.text_content("#status")
    with pytest.raises(urllib.error.HTTPError) as gone:
        urllib.request.urlopen(f"{base_url}v1/textures/{brick}", timeout=10)
    assert gone.value.code == 404

    # a dismissed question deletes nothing
    page.once("dialog", lambda dialog: dialog.dismiss())
    page.click('#texture-list button.delete[aria-label="Delete library gravel"]')
    page.wait_for_timeout(300)
    assert page.locator(f'#texture-list button.pick[data-id="{gravel}"]').count() == 1
    shoot(page, artifacts, "library-2-deleted")
    assert page_errors(page) == []


def test_fit_button_shows_progress_then_the_fitted_texture(page, base_url: str, artifacts: Path) -> None:
    pytest.importorskip("torch", reason="fitting needs the train extra")
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    page.fill("#upload-name", "fit source")
    source = upload(page, "grass", texture_photo_png("grass", (0.7, 1.0, 0.6)))
    page.fill("#fit-seconds", "2")
    page.click("#fit-start")
    assert page.is_disabled("#fit-start")
    page.wait_for_function("() => /^fit of fit source: /.test(document.getElementById('fit-state').textContent)")
    assert page.is_visible("#fit-progress")
    job = page.locator(f'#jobs li[data-texture-id="{source}"]').first
    job.wait_for()
    assert job.locator("strong").inner_text() == "fit 2 s · fit source"
    shoot(page, artifacts, "fit-1-running")
    page.wait_for_function("() => document.getElementById('fit-state').textContent.startsWith('fitted: ')",
                           timeout=FIT_TIMEOUT_MS)
    current = page.evaluate("window.texspace.state.current")
    assert current["id"] != source and current["sampler"] == "fitted"
    assert page.locator(f'#texture-list button.pick[data-id="{current["id"]}"][aria-pressed="true"]').count() == 1
    page.wait_for_function(f"() => document.body.dataset.texture === '{current['id']}'")
    assert not page.is_disabled("#fit-start")
    shoot(page, artifacts, "fit-2-fitted")
    assert page_errors(page) == []


def test_usable_at_a_phone_width(page, base_url: str, artifacts: Path) -> None:
    page.set_viewport_size({"width": 375, "height": 812})
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    upload(page, "phone", texture_photo_png("brick", (0.9, 0.9, 0.9)))
    page.wait_for_selector("#map img.leaflet-tile")
    overflow = page.evaluate("() => document.documentElement.scrollWidth - window.innerWidth")
    assert overflow <= 0, f"the page is {overflow} px wider than the screen"
    for selector in ("#drop-zone", "#texture-search", "#map", "#seed-next", "#fit-start", "#bake-start",
                     "#volume-start", "#texture-list button.delete"):
        box = page.locator(selector).first.bounding_box()
        assert box and box["x"] >= 0 and box["x"] + box["width"] <= 375 + 0.5, (selector, box)
    map_box = page.locator("#map").bounding_box()
    assert map_box["width"] >= 300 and map_box["height"] >= 250
    page.locator("#volume-start").scroll_into_view_if_needed()
    shoot(page, artifacts, "phone-375")
    assert page_errors(page) == []


def test_a_tile_the_busy_server_refused_is_asked_for_again(page, base_url: str) -> None:
    """Back-pressure answers a cold tile 503 + Retry-After; the map asks again (retry=1)."""
    refused: list[str] = []

    def busy_once(route) -> None:  # noqa: ANN001
        # every first attempt is refused (not only the first request: the page may first
        # show a texture an earlier test left in the library, whose tiles it then drops)
        if "retry=" in route.request.url:
            route.continue_()
            return
        refused.append(route.request.url)
        route.fulfill(status=503, headers={"Retry-After": "1"}, content_type="application/problem+json",
                      body='{"type": "urn:texspace:problem:busy", "title": "busy", "status": 503}')

    page.route("**/v1/textures/*/tiles/**", busy_once)
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    upload(page, "retried", texture_photo_png("brick", (0.83, 0.41, 0.67)))  # a photo no other test uploads: no cached tiles
    page.wait_for_function("""() => [...document.querySelectorAll('#map img.leaflet-tile-loaded')]
      .some((t) => t.src.includes('retry=1') && t.naturalWidth > 0)""", timeout=30_000)
    assert refused and all("retry=" not in url for url in refused)
    assert page_errors(page) == []
