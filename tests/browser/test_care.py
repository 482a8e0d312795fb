"""The page's care for people: several photos uploaded one after another with a line each,
a long texture name that does not widen a phone's page, and "View in 3D" on a GLB bake
that came back as a zip (with its height map)."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

from .helpers import BAKE_TIMEOUT_MS, canvas_pixels, page_errors, shoot, spatial_std, texture_photo_png

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.slow]
MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"
LONG_NAME = "Weathered reclaimed oak floorboards with nail holes and saw marks, north barn, second floor"


def test_batch_upload_and_a_long_name_on_a_phone(page, base_url: str, artifacts: Path) -> None:
    page.set_viewport_size({"width": 390, "height": 844})
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    photos = [{"name": f"{LONG_NAME} {i}.png", "mimeType": "image/png",
               "buffer": texture_photo_png(tint=(0.9, 0.6 + 0.1 * i, 0.5))} for i in range(2)]
    photos.insert(1, {"name": "notes.txt", "mimeType": "text/plain", "buffer": b"not a photo"})
    page.set_input_files("#upload-file", files=photos)
    page.wait_for_function("""() => [...document.querySelectorAll('#upload-queue li')]
        .every((li) => li.dataset.state === 'done' || li.dataset.state === 'failed')""", timeout=120_000)
    states = page.eval_on_selector_all("#upload-queue li", "items => items.map((li) => li.dataset.state)")
    assert states == ["done", "failed", "done"]
    assert "Uploaded 2 of 3; 1 failed." in page.text_content("#status")
    listed = page.eval_on_selector_all("#texture-list .meta span", "spans => spans.map((s) => s.textContent)")
    assert sum(LONG_NAME in name for name in listed) >= 2
    # the interpolation selects hold the long names; nothing makes the page wider than the phone
    page.wait_for_function(f"() => document.getElementById('interp-a').textContent.includes({LONG_NAME!r})")
    shoot(page, artifacts, "care-390px")
    # (665-788 px before: the selects were as wide as their longest option)
    widths = page.evaluate("""() => ({page: document.documentElement.scrollWidth,
        selects: Math.max(...[...document.querySelectorAll('select')].map((el) => el.getBoundingClientRect().right)),
        queue: document.getElementById('upload-queue').getBoundingClientRect().right})""")
    assert widths["page"] <= 390 and widths["selects"] <= 390 and widths["queue"] <= 390, widths
    assert page_errors(page) == []
    forget_textures(page, base_url, lambda texture: LONG_NAME in texture["name"])


def forget_textures(page, base_url: str, which) -> None:  # noqa: ANN001
    """Delete the textures a test made (their jobs go with them): the server is shared by the
    session's browser tests, and the page's tests count the jobs it lists."""
    api = page.request
    for texture in api.get(f"{base_url}v1/textures?limit=100").json()["items"]:
        if which(texture):
            assert api.delete(f"{base_url}v1/textures/{texture['id']}").status == 204


def test_view_in_3d_reads_a_zipped_glb_bake(page, base_url: str) -> None:
    api = page.request
    created = api.post(f"{base_url}v1/textures", multipart={
        "image": {"name": "brick.png", "mimeType": "image/png", "buffer": texture_photo_png()}})
    assert created.status == 201, created.text()
    texture = created.json()
    bake = api.post(f"{base_url}v1/textures/{texture['id']}/bakes", multipart={
        "mesh": {"name": "cube.obj", "mimeType": "text/plain", "buffer": (MESHES / "cube.obj").read_bytes()},
        "resolution": "64", "maps": "height"})
    assert bake.status == 202, bake.text()
    job_id = bake.json()["id"]
    deadline = time.monotonic() + BAKE_TIMEOUT_MS / 1000
    while (job := api.get(f"{base_url}v1/jobs/{job_id}").json())["state"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, job
        time.sleep(0.5)
    assert job["state"] == "succeeded" and job["result"]["media_type"] == "application/zip", job
    page.goto(base_url)
    page.wait_for_selector(f'#jobs li[data-job-id="{job_id}"][data-state="succeeded"]')
    page.click(f'#jobs li[data-job-id="{job_id}"] >> text=View in 3D')
    page.wait_for_selector("#viewer[data-loaded]", timeout=30_000)
    page.wait_for_timeout(300)
    assert spatial_std(canvas_pixels(page, "#viewer canvas")) > 10, "the cube from the zip is drawn"
    assert "Bake loaded" in page.text_content("#status")
    assert page_errors(page) == []
    forget_textures(page, base_url, lambda other: other["id"] == texture["id"])


def test_a_photo_uploaded_with_its_width_bakes_at_real_size(page, base_url: str) -> None:
    """The upload's "Photo width in metres" reaches the texture; a bake with "Mesh unit:
    metres" is made at real size and says its texels per metre."""
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    page.fill("#upload-width-m", "0.8")
    page.set_input_files("#upload-file", files=[{"name": "real-size.png", "mimeType": "image/png",
                                                 "buffer": texture_photo_png()}])
    page.wait_for_selector('#upload-queue li[data-state="done"]', timeout=60_000)
    api = page.request
    texture = next(t for t in api.get(f"{base_url}v1/textures?limit=100").json()["items"] if t["name"] == "real-size")
    assert texture["width_m"] == 0.8
    page.select_option("#bake-resolution", "256")
    page.select_option("#bake-unit", "1")
    page.click("#bake-start")
    page.wait_for_selector('#jobs li[data-state="succeeded"]', timeout=BAKE_TIMEOUT_MS)
    job_id = page.get_attribute('#jobs li[data-state="succeeded"]', "data-job-id")
    job = api.get(f"{base_url}v1/jobs/{job_id}").json()
    assert job["params"]["unit_m"] == 1.0 and job["result"]["texels_per_metre"] > 0, job
    assert page_errors(page) == []
    forget_textures(page, base_url, lambda other: other["id"] == texture["id"])
