"""Hostile requests: each gets the exact 4xx it deserves, never a 500, on the
embedded SQLite database and on PostgreSQL (which refuses NUL in text and enforces
varchar lengths); the service stays healthy after each. PostgreSQL cases are skipped,
saying why, where no server answers."""
from __future__ import annotations

import base64
import dataclasses
import json
import logging

import pytest
from fastapi.testclient import TestClient

from service.context import Services
from service.deps import public_base_url
from service.logs import request_id_var
from service.purge import purge_texture
from service.tables import Job, new_id
from tests.helpers import brick_png
from tests.reliability.helpers import BAD, PROBLEM

from .test_bad_input import assert_still_serving


@pytest.fixture(scope="module")
def services(module_services: Services) -> Services:
    """The app's services under the shorter name these tests use (``client`` serves them)."""
    return module_services


def upload(client: TestClient, name: str | None = None) -> dict:
    res = client.post("/v1/textures", files={"image": ("brick.png", brick_png(), "image/png")},
                      data={"name": name} if name else {})
    assert res.status_code == 201, res.text
    return res.json()


@pytest.fixture(scope="module")
def texture(client) -> dict:
    return upload(client)


def assert_validation_problem(res, word: str = "") -> None:
    assert res.status_code == 422, res.text
    assert res.headers["content-type"] == PROBLEM
    body = res.json()
    assert body["status"] == 422 and body["type"] == "urn:texspace:problem:validation-error", body
    assert word.lower() in body["detail"].lower(), body["detail"]


# --- NUL and control characters -----------------------------------------------------------

BAD_CHARS = ["\x00", "\x1b", "\x7f", "\u0085"]


def raw_upload(filename: str, field: str = "image", body: bytes | None = None) -> bytes:
    """A multipart upload whose filename holds the raw characters (httpx would escape them)."""
    body = brick_png() if body is None else body
    return (f'--b\r\nContent-Disposition: form-data; name="{field}"; filename="'.encode() + filename.encode() +
            b'"\r\nContent-Type: application/octet-stream\r\n\r\n' + body + b"\r\n--b--\r\n")


@pytest.mark.parametrize("char", BAD_CHARS, ids=["nul", "esc", "del", "nel"])
@pytest.mark.parametrize("where", ["texture path", "job path", "exemplar path", "tile path", "tilejson path",
                                   "texture_id filter", "patch path", "patch name", "upload filename",
                                   "upload name", "interpolate name", "interpolate id", "cursor", "region path",
                                   "delete path", "events path", "bake filename"])
def test_control_characters_are_refused_at_the_edge(client, services, texture, where: str, char: str) -> None:
    bad = f"ab{char}cd"
    quoted = bad.encode().hex()  # percent-encode every byte, NUL included
    path_id = "".join(f"%{quoted[i:i + 2]}" for i in range(0, len(quoted), 2))
    tid = texture["id"]
    calls = {
        "texture path": lambda: client.get(f"/v1/textures/{path_id}"),
        "job path": lambda: client.get(f"/v1/jobs/{path_id}"),
        "exemplar path": lambda: client.get(f"/v1/textures/{path_id}/exemplar"),
        "tile path": lambda: client.get(f"/v1/textures/{path_id}/tiles/6/0/0.png"),
        "tilejson path": lambda: client.get(f"/v1/textures/{path_id}/tilejson.json"),
        "texture_id filter": lambda: client.get("/v1/jobs", params={"texture_id": bad}),
        "patch path": lambda: client.patch(f"/v1/textures/{path_id}", json={"name": "x"}),
        "patch name": lambda: client.patch(f"/v1/textures/{tid}", json={"name": bad}),
        "upload filename": lambda: client.post("/v1/textures", content=raw_upload(bad),
                                               headers={"content-type": "multipart/form-data; boundary=b"}),
        "upload name": lambda: client.post("/v1/textures", files={"image": ("b.png", brick_png(), "image/png")},
                                           data={"name": bad}),
        "interpolate name": lambda: client.post("/v1/textures/interpolate",
                                                json={"a": tid, "b": tid, "t": 0.5, "name": bad}),
        "interpolate id": lambda: client.post("/v1/textures/interpolate", json={"a": bad, "b": tid, "t": 0.5}),
        "cursor": lambda: client.get("/v1/textures", params={"cursor": bad}),
        "region path": lambda: client.post(f"/v1/textures/{path_id}/regions",
                                           json={"z": 6, "x0": 0, "y0": 0, "width": 64, "height": 64}),
        "delete path": lambda: client.delete(f"/v1/textures/{path_id}"),
        "events path": lambda: client.get(f"/v1/jobs/{path_id}/events"),
        # was cleaned to "ab_cd.obj" and baked: refused like an upload's filename instead
        "bake filename": lambda: client.post(f"/v1/textures/{tid}/bakes", content=raw_upload(
            bad + ".obj", "mesh", (BAD / "cube.obj").read_bytes()),
            headers={"content-type": "multipart/form-data; boundary=b"}),
    }
    with services.sessions() as session:
        before = session.query(Job).count()
    assert_validation_problem(calls[where](), "control characters")
    with services.sessions() as session:
        assert session.query(Job).count() == before
    assert client.get(f"/v1/textures/{tid}").json()["name"] == texture["name"]
    assert_still_serving(client)


def test_printable_unicode_names_are_fine(client, texture) -> None:
    res = client.patch(f"/v1/textures/{texture['id']}", json={"name": "Ziegel \u00e9t\u00e9 \u6728\u76ee \U0001f9f1"})
    assert res.status_code == 200 and res.json()["name"].endswith("\U0001f9f1")
    client.patch(f"/v1/textures/{texture['id']}", json={"name": texture["name"]})


# --- interpolate's generated name ---------------------------------------------------------

def test_interpolated_name_fits_the_column(client) -> None:
    a, b = upload(client, "a" * 200), upload(client, "b" * 200)
    res = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": b["id"], "t": 0.123456})
    assert res.status_code == 201, res.text
    name = res.json()["name"]
    assert len(name) <= 200 and name.startswith("aaaa") and " x bbbb" in name and name.endswith(" @ 0.123456")
    assert client.get(f"/v1/textures/{res.json()['id']}").json()["name"] == name  # stored as answered
    short = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": a["id"], "t": 1}).json()
    assert len(short["name"]) <= 200
    client.delete(f"/v1/textures/{a['id']}"), client.delete(f"/v1/textures/{b['id']}")


# --- tampered cursors ---------------------------------------------------------------------

def _cursor(value) -> str:  # noqa: ANN001
    return base64.urlsafe_b64encode(json.dumps(value).encode()).decode().rstrip("=")


STAMP = "2024-01-01T00:00:00+00:00"
CURSORS = {
    "id list": _cursor([STAMP, ["x"]]),
    "id dict": _cursor([STAMP, {"a": 1}]),
    "id int": _cursor([STAMP, 5]),
    "id null": _cursor([STAMP, None]),
    "stamp int": _cursor([5, "abc"]),
    "stamp list": _cursor([[STAMP], "abc"]),
    "stamp garbage": _cursor(["yesterday", "abc"]),
    "dict": _cursor({"a": 1, "b": 2}),
    "three items": _cursor([STAMP, "a", "b"]),
    "scalar": _cursor(7),
    "id with nul": _cursor([STAMP, "a\x00b"]),
    "not base64": "!!!!",
    "not json": base64.urlsafe_b64encode(b"\xff\xfe").decode(),
}


@pytest.mark.parametrize("name", sorted(CURSORS))
@pytest.mark.parametrize("url", ["/v1/textures", "/v1/jobs"])
def test_tampered_cursor_is_422(client, texture, url: str, name: str) -> None:
    assert_validation_problem(client.get(url, params={"cursor": CURSORS[name]}), "cursor")
    assert_still_serving(client)


def test_genuine_cursor_still_pages(client, texture) -> None:
    upload(client)
    first = client.get("/v1/textures", params={"limit": 1}).json()
    second = client.get("/v1/textures", params={"limit": 1, "cursor": first["next_cursor"]})
    assert second.status_code == 200 and second.json()["items"][0]["id"] != first["items"][0]["id"]


# --- a 500 carries the request's own id --------------------------------------------------

class _Ids(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[tuple[str, str | None]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.getMessage(), request_id_var.get()))


def test_500_carries_its_own_request_id(client, texture, monkeypatch) -> None:
    from service.routes import textures

    def boom(*_, **__):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("injected failure")

    handler = _Ids()
    logging.getLogger().addHandler(handler)
    try:
        assert client.get("/healthz", headers={"X-Request-ID": "before-1"}).status_code == 200
        monkeypatch.setattr(textures, "texture_outs", boom)
        res = client.get(f"/v1/textures/{texture['id']}", headers={"X-Request-ID": "failing-2"})
    finally:
        logging.getLogger().removeHandler(handler)
        monkeypatch.undo()
    assert res.status_code == 500 and res.headers["content-type"] == PROBLEM
    assert res.headers["x-request-id"] == "failing-2"
    assert res.json()["type"] == "urn:texspace:problem:internal-error"
    errors = [rid for message, rid in handler.records if message.startswith("unhandled error")]
    assert errors == ["failing-2"], handler.records
    assert client.get("/healthz").status_code == 200


# --- region jobs are checked at submission ------------------------------------------------

REGIONS = {
    "z too high": ({"z": 99}, 422, "z"),
    "z too low": ({"z": -3}, 422, "z"),
    "min_zoom negative": ({"format": "pyramid", "min_zoom": -5}, 422, "min_zoom"),
    "min_zoom above z": ({"format": "pyramid", "z": 4, "min_zoom": 8}, 422, "min_zoom"),
    "x0 huge": ({"x0": 2**100}, 422, "x0"),
    "y0 huge": ({"y0": -(2**100)}, 422, "y0"),
    "window past the raster": ({"x0": 2**46 - 10, "width": 64}, 422, "raster"),
    "pyramid too many tiles": ({"format": "pyramid", "z": 12, "width": 8192, "height": 8192, "size": 64},
                               413, "tiles"),
}


@pytest.mark.parametrize("name", sorted(REGIONS))
def test_region_is_validated_at_submission(client, services, texture, name: str) -> None:
    fields, status, word = REGIONS[name]
    body = {"z": 6, "x0": 0, "y0": 0, "width": 64, "height": 64} | fields
    with services.sessions() as session:
        before = session.query(Job).count()
    res = client.post(texture["links"]["regions"], json=body)
    assert res.status_code == status, res.text
    assert res.headers["content-type"] == PROBLEM and word in res.json()["detail"], res.json()
    with services.sessions() as session:
        assert session.query(Job).count() == before  # nothing queued
    assert_still_serving(client)


def test_small_pyramid_is_accepted(client, texture) -> None:
    res = client.post(f"/v1/textures/{texture['id']}/regions",
                      json={"z": 6, "min_zoom": 5, "x0": 0, "y0": 0, "width": 64, "height": 64, "format": "pyramid"})
    assert res.status_code == 202, res.text


# --- HEAD wherever GET ----------------------------------------------------------------------

def running_job(services: Services, texture_id: str) -> str:
    """A job row that stays running (no worker holds it): its event stream never ends by itself."""
    job_id = new_id()
    with services.sessions() as session, session.begin():
        session.add(Job(id=job_id, kind="volume", texture_id=texture_id, params={"resolution": 8}, state="running",
                        attempt=1, max_attempts=3, progress=0.25, cancel_requested=False))
    return job_id


def test_head_answers_like_get_without_a_body(client, services, texture) -> None:
    tid = texture["id"]
    job = client.post(f"/v1/textures/{tid}/volumes", json={"resolution": 8}).json()
    urls = ["/healthz", "/metrics", "/v1/models", "/v1/textures", f"/v1/textures/{tid}",
            f"/v1/textures/{tid}/exemplar", f"/v1/textures/{tid}/tiles/6/0/0.png", f"/v1/textures/{tid}/tilejson.json",
            "/v1/jobs", f"/v1/jobs/{job['id']}", f"/v1/jobs/{job['id']}/result", f"/v1/jobs/{job['id']}/events",
            "/openapi.json"]
    for url in urls:
        get, head = client.get(url), client.head(url)
        assert get.status_code == 200, (url, get.text)
        assert head.status_code == 200 and head.content == b"", (url, head.status_code)
        assert head.headers["content-type"] == get.headers["content-type"], url
        if "content-length" in get.headers and url not in ("/metrics",):
            assert head.headers["content-length"] == get.headers["content-length"], url
    assert client.head(f"/v1/textures/{new_id()}").status_code == 404
    assert client.head("/v1/textures/interpolate").status_code in (404, 405)
    # the stream of a job that is still running: HEAD answers at once, with no events
    head = client.head(f"/v1/jobs/{running_job(services, tid)}/events")
    assert head.status_code == 200 and head.headers["content-type"].startswith("text/event-stream")
    assert head.content == b""
    assert_still_serving(client)


# --- the event stream of a job deleted with its texture -----------------------------------

def test_event_stream_of_a_deleted_job_ends_canceled(client, services) -> None:
    doomed = upload(client)
    job_id = running_job(services, doomed["id"])
    events = []
    with client.stream("GET", f"/v1/jobs/{job_id}/events") as stream:
        for line in stream.iter_lines():
            if line.startswith("event: "):
                events.append(line.removeprefix("event: "))
                if events == ["progress"]:
                    assert purge_texture(services, doomed["id"]) == [job_id]
            elif line.startswith("data: ") and events[-1] == "canceled":
                final = json.loads(line.removeprefix("data: "))
    assert events == ["progress", "canceled"]
    assert final["id"] == job_id and final["state"] == "canceled"
    assert final["error"]["type"] == "urn:texspace:problem:canceled" and "deleted" in final["error"]["detail"]
    assert client.get(f"/v1/jobs/{job_id}").status_code == 404


# --- stored files, tilejson, metrics ---------------------------------------------------------

def test_stored_files_are_never_sniffed(client, texture) -> None:
    exemplar = client.get(f"/v1/textures/{texture['id']}/exemplar")
    assert exemplar.status_code == 200 and exemplar.headers["x-content-type-options"] == "nosniff"
    job = client.post(f"/v1/textures/{texture['id']}/volumes", json={"resolution": 8}).json()
    result = client.get(f"/v1/jobs/{job['id']}/result")
    assert result.status_code == 200 and result.headers["x-content-type-options"] == "nosniff"


def test_public_base_url_wins_over_the_host_header(services) -> None:
    from starlette.requests import Request

    request = Request({"type": "http", "method": "GET", "path": "/", "root_path": "", "scheme": "http",
                       "query_string": b"", "server": ("evil.example", 80),
                       "headers": [(b"host", b"evil.example")]})
    assert public_base_url(request, services) == "http://evil.example"
    configured = services.settings.model_copy(update={"public_base_url": "https://tiles.example.com/api/"})
    assert public_base_url(request, dataclasses.replace(services, settings=configured)) == \
        "https://tiles.example.com/api"


def test_made_up_methods_share_one_metric_series(client) -> None:
    for method in ("FOO", "BAR", "X" * 60):
        assert client.request(method, "/healthz").status_code == 405
    metrics = client.get("/metrics").text
    assert 'method="other"' in metrics
    assert 'method="FOO"' not in metrics and 'method="BAR"' not in metrics and "XXXX" not in metrics
    assert_still_serving(client)
