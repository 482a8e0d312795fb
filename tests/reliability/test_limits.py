"""Limits as settings: request bytes (refused while streaming), tile size / zoom /
coordinates, volume resolution, mesh vertices, and queue back-pressure."""
from __future__ import annotations

import asyncio
import concurrent.futures
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service import limits
from service.context import build_services
from service.main import create_app
from tests.helpers import brick_png, chained_glb
from worker.errors import Busy
from tests.reliability.helpers import BAD, PROBLEM, make_settings, row_counts, stored_files

CHUNK = 64 * 1024


def test_request_body_is_refused_while_streaming(tmp_path: Path) -> None:
    """A chunked upload without Content-Length, far larger than the limit: the app answers
    413 after reading little more than the limit, not after the whole body."""
    services = build_services(make_settings(tmp_path, max_upload_bytes=1024, max_mesh_bytes=1024),
                              immediate=True)
    app = create_app(services=services)
    total_chunks, pulled, sent = 1024, [], []  # 64 MiB offered

    head = (b'--xyz\r\nContent-Disposition: form-data; name="image"; filename="a.png"\r\n'
            b"Content-Type: image/png\r\n\r\n")

    async def receive():  # noqa: ANN202
        pulled.append(1)
        body = (head if len(pulled) == 1 else b"") + b"\0" * CHUNK
        return {"type": "http.request", "body": body, "more_body": len(pulled) < total_chunks}

    async def send(message) -> None:  # noqa: ANN001
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": "/v1/textures", "raw_path": b"/v1/textures", "query_string": b"",
             "root_path": "", "server": ("127.0.0.1", 80), "client": ("127.0.0.1", 1234),
             "headers": [(b"content-type", b"multipart/form-data; boundary=xyz"), (b"host", b"t")]}
    # A thread of its own: a session-wide fixture (playwright's sync API) may already run
    # an event loop in the main thread, where asyncio.run refuses to start another.
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, app(scope, receive, send)).result()
    start = next(m for m in sent if m["type"] == "http.response.start")
    assert start["status"] == 413
    assert (b"content-type", PROBLEM.encode()) in start["headers"]
    limit = 1024 + (1 << 20)
    assert len(pulled) * CHUNK <= limit + 2 * CHUNK, f"read {len(pulled)} chunks before refusing"
    services.engine.dispose()


def test_declared_content_length_over_limit_is_413_before_reading(tmp_path: Path) -> None:
    services = build_services(make_settings(tmp_path, max_upload_bytes=1024, max_mesh_bytes=1024),
                              immediate=True)
    with TestClient(create_app(services=services)) as client:
        res = client.post("/v1/textures", files={"image": ("big.png", b"\0" * (2 << 20))})
        assert res.status_code == 413 and res.headers["content-type"] == PROBLEM
        assert "larger than" in res.json()["detail"]
        small = client.post("/v1/textures", files={"image": ("b.png", brick_png(32))})
        assert small.status_code == 413 and "1024 bytes" in small.json()["detail"]  # the per-upload limit
        assert stored_files(services) == [] and row_counts(services) == (0, 0)
    services.engine.dispose()


@pytest.mark.parametrize("path, params, status", [
    ("tiles/13/0/0.png", {}, 422),                       # zoom above the range
    ("tiles/1/0/0.png", {}, 422),                        # zoom below the range
    (f"tiles/6/{2**36 + 1}/0.png", {}, 422),             # coordinate beyond exact float64 rasters
    (f"tiles/6/0/{-2**36 - 1}.png", {}, 422),
    ("tiles/6/0/0.png", {"size": 2048}, 422),            # beyond the schema's maximum
    ("tiles/6/0/0.png", {"size": 512}, 413),             # beyond the max_tile_size setting (256 here)
    ("tiles/6/0/0.png", {"seed": -1}, 422),
    ("tiles/6/0/0.png", {"offset": 1e12}, 422),
    ("tiles/6/0/0.gif", {}, 422),
])
def test_tile_limits(client, module_services, texture, path: str, params: dict, status: int) -> None:
    module_services.settings.max_tile_size = 256
    res = client.get(f"/v1/textures/{texture['id']}/{path}", params=params)
    assert res.status_code == status and res.headers["content-type"] == PROBLEM, res.text
    assert client.get(f"/v1/textures/{texture['id']}/tiles/6/{2**36}/-3.png", params={"size": 64}).status_code == 200


def test_volume_resolution_limit(client, texture) -> None:
    res = client.post(texture["links"]["volumes"], json={"resolution": 33})   # setting: 32
    assert res.status_code == 413 and "limit of 32" in res.json()["detail"]
    res = client.post(texture["links"]["volumes"], json={"resolution": 2000})  # schema: <= 1024
    assert res.status_code == 422 and res.headers["content-type"] == PROBLEM


def test_mesh_vertex_limit(client, module_services, texture) -> None:
    module_services.settings.max_mesh_vertices = 5
    try:
        res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", (BAD / "cube.obj").read_bytes())})
        assert res.status_code == 413 and "8 vertices" in res.json()["detail"]
    finally:
        module_services.settings.max_mesh_vertices = 1000


def test_mesh_parses_are_bounded_and_header_checks_do_not_wait(client, module_services, texture,
                                                                monkeypatch) -> None:
    """With every parse slot taken and no room to wait, a bake is 503 busy + Retry-After and
    stores nothing; a GLB its header refuses is still a 413 at once."""
    slots = limits.CpuSlots(1, 0, 0.1, "meshes are being checked")
    monkeypatch.setattr(limits, "MESH_PARSE_SLOTS", slots)
    cube = (BAD / "cube.obj").read_bytes()
    before = stored_files(module_services), row_counts(module_services)
    with slots.slot():                               # another request's parse
        busy = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", cube)})
        deep = client.post(texture["links"]["bakes"], files={"mesh": ("deep.glb", chained_glb(5000))})
    assert busy.status_code == 503 and busy.headers["content-type"] == PROBLEM, busy.text
    assert busy.json()["type"].endswith(":busy") and int(busy.headers["retry-after"]) >= 1
    assert deep.status_code == 413 and "5000 nodes" in deep.json()["detail"]
    assert (stored_files(module_services), row_counts(module_services)) == before
    assert client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", cube)},
                       data={"resolution": "16"}).status_code == 202


def test_uploads_wait_for_an_encode_slot_then_are_busy(client, module_services, monkeypatch) -> None:
    """Uploads are encoded ``upload_encodes`` at a time: one that finds every slot held waits
    its turn and is stored once a slot frees; with no room to wait it is 503 busy +
    Retry-After, naming the work, and stores nothing."""
    slots = limits.CpuSlots(1, 1, 30.0, "uploads are being encoded")
    monkeypatch.setattr(module_services, "upload_slots", slots)
    photo = {"image": ("brick.png", brick_png(), "image/png")}
    before = stored_files(module_services), row_counts(module_services)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        with slots.slot():                               # another upload's encode
            waiting = pool.submit(client.post, "/v1/textures", files=photo)
            while slots._waiting == 0:                   # it waits for the slot (not refused)
                assert not waiting.done()
                time.sleep(0.01)
            busy = client.post("/v1/textures", files=photo)  # no room to wait: refused at once
        assert waiting.result(timeout=60).status_code == 201
    assert busy.status_code == 503 and busy.headers["content-type"] == PROBLEM, busy.text
    assert busy.json()["type"].endswith(":busy") and int(busy.headers["retry-after"]) >= 1
    assert "uploads are being encoded" in busy.json()["detail"]
    assert row_counts(module_services)[0] == before[1][0] + 1  # the one that waited, only
    monkeypatch.setattr(module_services, "upload_slots", limits.CpuSlots(1, 0, 0.05, "uploads are being encoded"))
    assert client.post("/v1/textures", files=photo).status_code == 201  # a free slot: no wait


def test_slots_refuse_at_once_an_arrival_that_would_wait_past_the_bound() -> None:
    """The slots keep the holders' pace; one arriving where that pace says it would wait past
    the bound is refused at once (503 busy, Retry-After about one holder's time), not after
    waiting in vain."""
    slots = limits.CpuSlots(1, 8, 1.0, "things are done")
    assert slots.expected_wait() == 0.0  # no pace yet: an arrival waits
    with slots.slot():
        time.sleep(0.2)
    assert 0.15 < slots.pace < 1.0
    with slots.slot():                     # held
        slots.pace = 2.0                   # holders grew slow (a busy machine)
        started = time.monotonic()
        with pytest.raises(Busy, match="about 2 s at the recent pace") as refused:
            with slots.slot():
                pass
        assert time.monotonic() - started < 0.5 and refused.value.retry_after == 2
        slots.pace = 0.3                   # fast again: this one would wait its turn
        assert slots.expected_wait() == pytest.approx(0.3)


def test_queue_back_pressure(tmp_path: Path) -> None:
    """With jobs held in memory (no worker), the (max+1)th submission is a 503 with
    Retry-After; a refused bake stores nothing; after a cancel there is room again."""
    settings = make_settings(tmp_path, queue_backend="memory", max_queued_jobs=2,
                             queue_full_retry_after_seconds=7)
    services = build_services(settings)
    with TestClient(create_app(services=services)) as client:
        texture = client.post("/v1/textures", files={"image": ("b.png", brick_png())}).json()
        first = [client.post(texture["links"]["volumes"], json={"resolution": 8, "seed": s}) for s in range(2)]
        assert [r.status_code for r in first] == [202, 202]
        before = stored_files(services)
        full = client.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 9})
        assert full.status_code == 503 and full.headers["retry-after"] == "7"
        assert full.headers["content-type"] == PROBLEM and full.json()["type"].endswith("queue-full")
        bake = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", (BAD / "cube.obj").read_bytes())})
        assert bake.status_code == 503 and stored_files(services) == before
        assert client.get("/v1/jobs").json()["items"].__len__() == 2
        client.post(f"/v1/jobs/{first[0].json()['id']}/cancel")
        assert client.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 9}).status_code == 202
    services.engine.dispose()
