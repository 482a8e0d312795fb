"""/docs renders offline: every request the page makes that leaves the server is refused,
and Swagger UI (bundled under /vendor/swagger-ui-dist) still draws the operations."""
from __future__ import annotations

import io
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from PIL import Image

from .helpers import spatial_std

pytestmark = [pytest.mark.browser, pytest.mark.e2e]


def test_docs_render_offline(page, base_url: str, artifacts: Path) -> None:
    server = urlsplit(base_url).netloc
    outside: list[str] = []

    def offline(route) -> None:  # noqa: ANN001
        if urlsplit(route.request.url).netloc == server or route.request.url.startswith("data:"):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort("internetdisconnected")

    page.route("**/*", offline)
    page.goto(base_url + "docs")
    page.wait_for_selector(".swagger-ui .opblock-summary", timeout=30_000)
    operations = page.locator(".swagger-ui .opblock").count()
    assert operations >= 15, operations
    assert "texspace" in page.locator(".swagger-ui .info .title").inner_text()
    page.locator(".opblock-summary", has_text="/v1/textures/{texture_id}/tiles").first.click()
    page.wait_for_selector(".swagger-ui .opblock.is-open .parameters")
    png = page.screenshot(path=str(artifacts / "docs-offline.png"), full_page=False)
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    assert spatial_std(pixels) > 20, "the docs page is blank"
    assert not outside, f"/docs asked outside the server for {outside}"
    assert not page.js_errors, page.js_errors
    yaml_text = page.request.get(base_url + "openapi.yaml").text()
    assert yaml_text.startswith("openapi: 3.1")
