"""Progressive zoom-out (the default): a cold zoomed-out tile is answered at once
with a preview at a native tile's cost, and the exact (supersampled) tile, rendered behind
it, replaces it: revalidating the preview gives 304 until then, the exact tile after."""
from __future__ import annotations

import threading
import time

import pytest

from service import tiles as service_tiles
from worker.tiles import NATIVE_ZOOM

from tests.service.helpers import tile_url

N = NATIVE_ZOOM
SIZE = {"size": 64}


def reference(client, services, texture: dict, url: str, mode: str) -> tuple[str, bytes]:
    """ETag and bytes of ``url`` when the server renders zoomed-out tiles in ``mode``."""
    was = services.settings.tile_zoom_out
    services.settings.tile_zoom_out = mode
    try:
        res = client.get(url, params=SIZE)
    finally:
        services.settings.tile_zoom_out = was
    assert res.status_code == 200 and "x-texspace-tile" not in res.headers
    return res.headers["etag"], res.content


def wait_for_exact(etag: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while service_tiles.EXACT.pending(etag):
        assert time.monotonic() < deadline, "the exact tile never rendered"
        time.sleep(0.05)


def test_preview_first_then_the_exact_tile(client, services, texture) -> None:
    assert services.settings.tile_zoom_out == "progressive"  # the default
    url = tile_url(texture, N - 2, 3, -2)
    first = client.get(url, params=SIZE)
    assert first.status_code == 200
    assert first.headers["x-texspace-tile"] == "preview"
    assert first.headers["cache-control"] == service_tiles.PREVIEW_CACHE_CONTROL  # revalidated, not kept
    exact_etag = service_tiles.tile_etag(_texture(services, texture), z=N - 2, x=3, y=-2, seed=0, plane="xy",
                                         offset=0.0, fmt="png", zoom_out="supersample", **SIZE)
    wait_for_exact(exact_etag)
    # the preview is exactly the bounded render, the final tile exactly the supersampled one
    bounded_etag, bounded = reference(client, services, texture, url, "bounded")
    assert (first.headers["etag"], first.content) == (bounded_etag, bounded)
    again = client.get(url, params=SIZE, headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 200 and "x-texspace-tile" not in again.headers
    assert again.headers["etag"] == exact_etag
    assert again.headers["cache-control"] == service_tiles.CACHE_CONTROL
    assert (exact_etag, again.content) == reference(client, services, texture, url, "supersample")
    assert again.content != first.content
    # from now on the URL is final: same bytes, 304 on its ETag
    assert client.get(url, params=SIZE).content == again.content
    assert client.get(url, params=SIZE, headers={"If-None-Match": exact_etag}).status_code == 304


def _texture(services, texture: dict):  # noqa: ANN202
    from service.routes.textures import load_texture

    return load_texture(services, texture["id"])


def test_revalidating_a_preview_is_304_until_the_exact_tile_is_ready(client, services, texture, monkeypatch) -> None:
    queued = []
    monkeypatch.setattr(service_tiles.EXACT, "submit", lambda *args: queued.append(args[2]))  # never renders
    url = tile_url(texture, N - 1, -7, 4)
    first = client.get(url, params=SIZE)
    assert first.headers["x-texspace-tile"] == "preview"
    again = client.get(url, params=SIZE, headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 304
    assert again.headers["etag"] == first.headers["etag"] and again.headers["x-texspace-tile"] == "preview"
    assert len(queued) == 2 and len(set(queued)) == 1 and queued[0] != first.headers["etag"]  # the exact one


def test_native_tiles_and_tiles_built_from_children_have_no_preview(client, services, texture, monkeypatch) -> None:
    monkeypatch.setattr(service_tiles.EXACT, "submit", lambda *args: pytest.fail("nothing to render behind"))
    for i in (0, 1):
        for j in (0, 1):
            res = client.get(tile_url(texture, N, 10 + i, 20 + j), params=SIZE)
            assert res.status_code == 200 and "x-texspace-tile" not in res.headers
    parent = client.get(tile_url(texture, N - 1, 5, 10), params=SIZE)  # its 4 children are cached
    assert parent.status_code == 200 and "x-texspace-tile" not in parent.headers
    assert parent.headers["cache-control"] == service_tiles.CACHE_CONTROL


def test_exact_renders_go_newest_first_and_drop_the_oldest(monkeypatch) -> None:
    rendered: list[str] = []
    gate = threading.Event()

    class Cache:
        def get(self, etag):  # noqa: ANN001, ANN202
            return None

        def put(self, etag, data):  # noqa: ANN001, ANN202
            rendered.append(etag)

    class FakeServices:
        tile_cache = Cache()

    def render(services, texture, **key):  # noqa: ANN001, ANN003, ANN202
        gate.wait(10)  # the first render holds the thread while the rest queue up
        return b"tile"

    monkeypatch.setattr(service_tiles, "render_tile_bytes", render)
    monkeypatch.setattr(service_tiles, "MAX_PENDING_EXACT", 3)
    exact = service_tiles.ExactRenders()
    exact.submit(FakeServices(), None, "first", {})
    deadline = time.monotonic() + 5
    while "first" in exact._waiting:  # taken by the thread, blocked in render
        assert time.monotonic() < deadline
        time.sleep(0.01)
    for name in ("a", "b", "c", "d", "e"):  # only the 3 newest stay
        exact.submit(FakeServices(), None, name, {})
    exact.submit(FakeServices(), None, "e", {})  # already waiting: not twice
    assert exact.pending("first") and not exact.pending("a") and not exact.pending("b")
    gate.set()
    while any(exact.pending(name) for name in ("first", "c", "d", "e")):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert rendered == ["first", "e", "d", "c"]
