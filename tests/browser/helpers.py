"""Helpers for the browser tests: test images, pixels of the map / tiles / 3D canvas,
a log of the tiles the page fetched, uploads by file input or drop."""
from __future__ import annotations

import base64
import io
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image

from service import spawn
from service.spawn import free_port

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
SERVER_START_TIMEOUT_S = 60

TILE_URL = re.compile(r"/v1/textures/(?P<id>[0-9a-f-]+)/tiles/(?P<z>-?\d+)/(?P<x>-?\d+)/(?P<y>-?\d+)\.png\?(?P<query>.*)$")
BAKE_TIMEOUT_MS = 240_000
ALL_TILES_LOADED = """() => {
  const tiles = [...document.querySelectorAll('#map img.leaflet-tile')];
  return tiles.length > 0 && tiles.every((t) => t.classList.contains('leaflet-tile-loaded'));
}"""


def texture_photo_png(name: str = "brick", tint: tuple[float, float, float] = (1.0, 0.75, 0.55)) -> bytes:
    """A real photo (scikit-image's bundled brick / gravel / grass, CC0), tinted to RGB."""
    from skimage import data

    gray = getattr(data, name)().astype(np.float32) / 255.0            # (512, 512)
    rgb = gray[..., None] * np.asarray(tint, np.float32)                # (512, 512, 3)
    buffer = io.BytesIO()
    Image.fromarray((rgb * 255).astype(np.uint8)).save(buffer, "PNG")
    return buffer.getvalue()


MAP_BACKGROUND = (136, 136, 136)  # .map in app.css: what shows where no tile is drawn


def map_pixels(page) -> np.ndarray:
    """(h, w, 3) uint8 screenshot of the map without Leaflet's controls."""
    png = page.locator("#map").screenshot(style=".leaflet-control-container { display: none; }")
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def a_drawn_tile(page) -> tuple[int, int, int]:
    """(z, x, y) of one tile the map shows now."""
    src = page.eval_on_selector("#map img.leaflet-tile-loaded", "img => img.src")
    match = TILE_URL.search(src)
    return int(match["z"]), int(match["x"]), int(match["y"])


def tile_image_pixels(page, z: int, x: int, y: int) -> np.ndarray:
    """(size, size, 3) uint8 pixels of the map's <img> for tile (z, x, y), as decoded by the page."""
    data_url = page.evaluate("""(suffix) => {
      const img = [...document.querySelectorAll('#map img.leaflet-tile-loaded')]
        .find((t) => new URL(t.src).pathname.endsWith(suffix));
      const canvas = document.createElement('canvas');
      [canvas.width, canvas.height] = [img.naturalWidth, img.naturalHeight];
      canvas.getContext('2d').drawImage(img, 0, 0);
      return canvas.toDataURL('image/png');
    }""", f"/tiles/{z}/{x}/{y}.png")
    png = base64.b64decode(data_url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def canvas_pixels(page, selector: str) -> np.ndarray:
    """(h, w, 3) uint8 read back from a WebGL canvas (needs preserveDrawingBuffer)."""
    data_url = page.eval_on_selector(selector, "c => c.toDataURL('image/png')")
    png = base64.b64decode(data_url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def spatial_std(pixels: np.ndarray) -> float:
    """Largest per-channel standard deviation over the pixels of a (h, w, 3) image."""
    return float(pixels.reshape(-1, 3).astype(np.float64).std(axis=0).max())


class TileLog:
    """Every tile the page fetched successfully: (texture id, z, x, y, query) in order."""

    def __init__(self, page):
        self.tiles: list[tuple[int, int, int, str]] = []
        page.on("response", self._on_response)

    def _on_response(self, response) -> None:
        match = TILE_URL.search(response.url)
        if match and response.status in (200, 304):
            self.tiles.append((match["id"], int(match["z"]), int(match["x"]), int(match["y"]), match["query"]))

    def keys(self, texture_id: str) -> set[tuple[int, int, int, str]]:
        """Distinct (z, x, y, query) fetched for one texture."""
        return {tile[1:] for tile in self.tiles if tile[0] == texture_id}


def wait_for_new_tiles(page, tiles: TileLog, texture_id: str, seen: set, timeout_s: float = 60) -> set:
    """Wait until the page has fetched tiles not in ``seen`` and all drawn tiles are loaded."""
    deadline = time.monotonic() + timeout_s
    while not tiles.keys(texture_id) - seen:
        assert time.monotonic() < deadline, "no new tiles were fetched"
        page.wait_for_timeout(100)  # lets playwright deliver response events
    page.wait_for_function(ALL_TILES_LOADED, timeout=timeout_s * 1000)
    return tiles.keys(texture_id) - seen


def page_errors(page) -> list[str]:
    """The page's uncaught exceptions and console errors, less the 503s a busy server answers
    cold tiles with (back-pressure, TEXSPACE_TILE_QUEUE_*): the page asks for those again
    (retry=n), so a tile still missing fails the test where it waits for tiles instead."""
    return [e for e in page.js_errors if "status of 503" not in e]


def shoot(page, artifacts: Path, name: str) -> None:
    page.screenshot(path=str(artifacts / f"{name}.png"), full_page=True)


DROP = """([name, b64]) => {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const transfer = new DataTransfer();
  transfer.items.add(new File([bytes], name, { type: 'image/png' }));
  const zone = document.getElementById('drop-zone');
  for (const type of ['dragenter', 'dragover', 'drop']) {
    zone.dispatchEvent(new DragEvent(type, { dataTransfer: transfer, bubbles: true, cancelable: true }));
  }
}"""


def upload(page, name: str, png: bytes, *, drop: bool = False) -> str:
    """Upload through the file input or by dropping the file on the drop zone;
    returns the new texture's id once it is on the map."""
    with page.expect_response(lambda r: r.url.endswith("/v1/textures") and r.request.method == "POST") as done:
        if drop:
            page.evaluate(DROP, [f"{name}.png", base64.b64encode(png).decode()])
        else:
            page.set_input_files("#upload-file", files=[{"name": f"{name}.png", "mimeType": "image/png", "buffer": png}])
    assert done.value.status == 201, done.value.text()
    texture_id = done.value.json()["id"]
    page.wait_for_selector(f'#texture-list button[data-id="{texture_id}"][aria-pressed="true"]')
    return texture_id


@contextmanager
def serve(data_dir: Path, log: Path, env: dict[str, str]) -> Iterator[str]:
    """``texspace serve`` on a free loopback port; yields its URL (the page's), stops it afterwards."""
    port = free_port()
    log.write_bytes(b"")  # this run's log only
    process = spawn.spawn(["serve", "--host", "127.0.0.1", "--port", str(port)], env, log)
    url = f"http://127.0.0.1:{port}/"
    try:
        spawn.wait_ready(url.rstrip("/"), [process], SERVER_START_TIMEOUT_S, path="/", name="texspace serve",
                         output=lambda: log.read_text(errors="replace"))
        yield url
    finally:
        spawn.stop([process])
