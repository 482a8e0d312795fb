"""The page's image export: "Tileable" is checked by default and makes a region job with
``tileable: true``, whose PNG repeats without a seam."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from .helpers import ALL_TILES_LOADED, page_errors, shoot, texture_photo_png, upload

pytestmark = [pytest.mark.browser, pytest.mark.e2e]
JOB_TIMEOUT_MS = 120_000


def test_export_a_tileable_image(page, base_url: str, artifacts: Path) -> None:
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    upload(page, "brick", texture_photo_png())
    page.wait_for_function(ALL_TILES_LOADED, timeout=60_000)
    assert page.is_checked("#region-tileable")
    page.select_option("#region-size", "512")
    page.select_option("#region-format", "png")
    with page.expect_response(lambda r: r.url.endswith("/regions") and r.request.method == "POST") as submitted:
        page.click("#region-start")
    job = submitted.value.json()
    assert submitted.value.status == 202 and job["params"]["tileable"] is True
    assert (job["params"]["width"], job["params"]["height"], job["params"]["z"]) == (512, 512, 6)
    item = page.locator(f'#jobs li[data-job-id="{job["id"]}"]')
    item.locator("xpath=self::li[@data-state='succeeded']").wait_for(timeout=JOB_TIMEOUT_MS)
    assert "tileable 512x512 (png)" in item.text_content()
    result = page.request.get(item.locator("a[download]").get_attribute("href"))
    image = np.asarray(Image.open(io.BytesIO(result.body())), dtype=np.float32)
    assert image.shape == (512, 512, 3)
    interior = np.abs(np.diff(image, axis=1)).mean()
    assert np.abs(image[:, 0] - image[:, -1]).mean() < 2 * interior, "no seam where copies meet"
    shoot(page, artifacts, "tileable-export")
    assert page_errors(page) == []


def test_export_a_bc7_dds_from_the_page(page, base_url: str) -> None:
    """The format list offers DDS twice; "dds (BC7)" asks for BC7 blocks (``dds_compression``)
    and the download is a DX10 DDS of the asked size in DXGI_FORMAT_BC7_UNORM_SRGB."""
    page.goto(base_url)
    page.wait_for_selector("#map.leaflet-container")
    upload(page, "brick", texture_photo_png())
    labels = page.eval_on_selector_all("#region-format option", "options => options.map(o => o.textContent)")
    assert "dds (BC1)" in labels and "dds (BC7)" in labels
    page.select_option("#region-size", "512")
    page.select_option("#region-format", "dds:bc7")
    with page.expect_response(lambda r: r.url.endswith("/regions") and r.request.method == "POST") as submitted:
        page.click("#region-start")
    job = submitted.value.json()
    assert submitted.value.status == 202
    assert (job["params"]["format"], job["params"]["dds_compression"]) == ("dds", "bc7")
    item = page.locator(f'#jobs li[data-job-id="{job["id"]}"]')
    item.locator("xpath=self::li[@data-state='succeeded']").wait_for(timeout=JOB_TIMEOUT_MS)
    body = page.request.get(item.locator("a[download]").get_attribute("href")).body()
    header = np.frombuffer(body[:148], dtype="<u4")
    assert body[:4] == b"DDS " and body[84:88] == b"DX10"
    assert (header[3], header[4]) == (512, 512)  # height, width
    assert header[32] == 99  # DXGI_FORMAT_BC7_UNORM_SRGB
    assert page_errors(page) == []
