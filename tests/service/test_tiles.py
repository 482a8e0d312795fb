"""Tile endpoint: image sizes, caching headers, ETag/304, LRU, parameter validation."""
from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from worker.tiles import MAX_ZOOM, NATIVE_ZOOM

from tests.service.helpers import tile_url


def test_png_tile_decodes_with_right_size(client, texture) -> None:
    res = client.get(tile_url(texture, NATIVE_ZOOM, -3, 2), params={"size": 64, "seed": 7})
    assert res.status_code == 200 and res.headers["content-type"] == "image/png"
    image = Image.open(io.BytesIO(res.content))
    assert image.size == (64, 64) and image.mode == "RGB"
    assert res.headers["cache-control"] == "public, max-age=31536000, immutable"
    assert res.headers["etag"].startswith('"') and not res.headers["etag"].startswith("W/")


def test_same_url_same_bytes_and_304(client, texture, services) -> None:
    url = tile_url(texture, NATIVE_ZOOM, 0, 0)
    first = client.get(url, params={"size": 64})
    services.tile_cache._items.clear()  # force a second render: bytes must still match
    second = client.get(url, params={"size": 64})
    assert first.content == second.content and first.headers["etag"] == second.headers["etag"]
    not_modified = client.get(url, params={"size": 64}, headers={"If-None-Match": first.headers["etag"]})
    assert not_modified.status_code == 304 and not_modified.content == b""
    assert not_modified.headers["etag"] == first.headers["etag"]
    other = client.get(url, params={"size": 64}, headers={"If-None-Match": '"something-else"'})
    assert other.status_code == 200


def test_etag_depends_on_every_parameter(client, texture) -> None:
    base = {"size": 64, "seed": 0}
    tags = {client.get(tile_url(texture, NATIVE_ZOOM, 0, 0), params=base).headers["etag"],
            client.get(tile_url(texture, NATIVE_ZOOM, 1, 0), params=base).headers["etag"],
            client.get(tile_url(texture, NATIVE_ZOOM, 0, 0), params={**base, "seed": 1}).headers["etag"],
            client.get(tile_url(texture, NATIVE_ZOOM, 0, 0), params={**base, "plane": "xz"}).headers["etag"],
            client.get(tile_url(texture, NATIVE_ZOOM + 1, 0, 0), params=base).headers["etag"],
            client.get(tile_url(texture, NATIVE_ZOOM, 0, 0, "webp"), params=base).headers["etag"]}
    assert len(tags) == 6


def test_lru_hits_are_counted(client, texture) -> None:
    url = tile_url(texture, NATIVE_ZOOM, 5, 5)
    for _ in range(3):
        assert client.get(url, params={"size": 64}).status_code == 200
    metrics = client.get("/metrics").text
    assert "texspace_tile_cache_hits_total 2.0" in metrics
    assert "texspace_tile_cache_misses_total 1.0" in metrics


def test_seed_changes_pixels_and_neighbours_differ(client, texture) -> None:
    def pixels(**params) -> np.ndarray:
        x = params.pop("x", 0)
        res = client.get(tile_url(texture, NATIVE_ZOOM, x, 0), params={"size": 64, **params})
        return np.asarray(Image.open(io.BytesIO(res.content)), np.int16)

    assert not np.array_equal(pixels(seed=0), pixels(seed=1))
    assert not np.array_equal(pixels(x=0), pixels(x=1))


def test_exr_and_webp(client, texture) -> None:
    exr = client.get(tile_url(texture, NATIVE_ZOOM, 0, 0, "exr"), params={"size": 64})
    assert exr.status_code == 200 and exr.content[:4] == b"v/1\x01"
    webp = client.get(tile_url(texture, NATIVE_ZOOM, 0, 0, "webp"), params={"size": 64})
    assert Image.open(io.BytesIO(webp.content)).size == (64, 64)


@pytest.mark.parametrize("path,params", [
    ("{b}/tiles/6/0/0.gif", {}),
    ("{b}/tiles/{big}/0/0.png", {}),
    ("{b}/tiles/6/0/0.png", {"size": 8}),
    ("{b}/tiles/6/0/0.png", {"seed": -1}),
    ("{b}/tiles/6/0/0.png", {"plane": "ab"}),
    ("{b}/tiles/6/x/0.png", {}),
    ("{b}/tiles/6/99999999999999999/0.png", {}),
])
def test_bad_tile_requests_are_422(client, texture, path, params) -> None:
    url = path.format(b=f"/v1/textures/{texture['id']}", big=MAX_ZOOM + 1)
    res = client.get(url, params=params)
    assert res.status_code == 422, res.text
    assert res.headers["content-type"] == "application/problem+json"


def test_unknown_texture_404(client) -> None:
    assert client.get("/v1/textures/nope/tiles/6/0/0.png").status_code == 404


def test_tilejson(client, texture) -> None:
    res = client.get(f"/v1/textures/{texture['id']}/tilejson.json", params={"seed": 3, "size": 128})
    body = res.json()
    assert body["tilejson"] == "3.0.0" and body["tileSize"] == 128
    assert body["tiles"][0].startswith("http://testserver/v1/textures/")
    assert "seed=3" in body["tiles"][0] and "{z}/{x}/{y}.png" in body["tiles"][0]
    assert body["minzoom"] <= NATIVE_ZOOM <= body["maxzoom"]
    assert body["center"] == [0, 0, NATIVE_ZOOM]  # viewers open at one tile pixel = one exemplar pixel


def test_tilejson_uses_the_public_base_url_not_the_host_header(client, texture, services) -> None:
    services.settings.public_base_url = "https://tiles.example.com/api/"
    try:
        res = client.get(f"/v1/textures/{texture['id']}/tilejson.json", headers={"Host": "evil.example"})
    finally:
        services.settings.public_base_url = None
    assert res.json()["tiles"][0].startswith("https://tiles.example.com/api/v1/textures/")


def test_tile_work_is_bounded(client, texture, services) -> None:
    """size x supersampling: 1024 px at zoom 4 is 16 M sampler calls (~20 s), over the
    4 M budget: 413 at once (tests/reliability/test_costly_requests.py renders the largest)."""
    res = client.get(tile_url(texture, 4, 0, 0), params={"size": 1024})
    assert res.status_code == 413, res.text
    assert "samples" in res.json()["detail"] and "limit" in res.json()["detail"]
    assert services.settings.max_tile_samples == 4 * 2**20


def test_banded_tiles_match_whole_tiles(services) -> None:
    """Large tiles render in bands (so small tiles can go between); same pixels."""
    from worker.tiles import render_tile

    runtime = services.registry.get(None)
    code = np.zeros(8, np.float32)
    whole = render_tile(runtime, code, 3, 4, 1, -2, 128)
    calls = []
    banded = render_tile(runtime, code, 3, 4, 1, -2, 128, band_samples=5 * 128 * 16,
                         before_band=lambda: calls.append(1))
    assert len(calls) == 26 and np.allclose(banded, whole, atol=1e-6)
