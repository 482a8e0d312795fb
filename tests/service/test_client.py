"""service/client.py without a server (httpx.MockTransport): waiting on a job's events,
the fallback when the stream drops, failures as exceptions, downloads by file name."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from service.client import ApiError, Client, JobFailed

JOB = {"id": "j1", "kind": "volume", "state": "queued", "progress": 0.0}


def events(*items: tuple[str, dict]) -> bytes:
    return "".join(f"id: {i}\nevent: {name}\ndata: {json.dumps(data)}\n\n"
                   for i, (name, data) in enumerate(items, 1)).encode()


def client_for(handler) -> Client:  # noqa: ANN001
    return Client("http://texspace.test", transport=httpx.MockTransport(handler))


def test_wait_reports_progress_and_returns_the_job() -> None:
    done = {**JOB, "state": "succeeded", "progress": 1.0}

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/v1/jobs/j1/events"
        return httpx.Response(200, content=events(("progress", {"state": "running", "progress": 0.5, "attempt": 1}),
                                                  ("succeeded", done)),
                              headers={"content-type": "text/event-stream"})

    seen: list[dict] = []
    with client_for(handler) as ts:
        assert ts.wait(JOB, progress=seen.append) == done
    assert seen == [{"state": "running", "progress": 0.5, "attempt": 1}]


def test_a_failed_job_raises_with_its_problem() -> None:
    failed = {**JOB, "state": "failed", "error": {"detail": "mesh has no faces"}}

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, content=events(("failed", failed)), headers={"content-type": "text/event-stream"})

    with client_for(handler) as ts, pytest.raises(JobFailed, match="mesh has no faces") as info:
        ts.wait("j1")
    assert info.value.job == failed


def test_a_dropped_stream_falls_back_to_the_job() -> None:
    calls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.url.path)
        if request.url.path.endswith("/events"):
            return httpx.Response(200, content=b": keep-alive\n\n", headers={"content-type": "text/event-stream"})
        return httpx.Response(200, json={**JOB, "state": "succeeded", "progress": 1.0})

    with client_for(handler) as ts:
        assert ts.wait("j1")["state"] == "succeeded"
    assert calls == ["/v1/jobs/j1/events", "/v1/jobs/j1"]


def test_errors_carry_the_problem_document() -> None:
    problem = {"type": "urn:texspace:problem:not-found", "title": "Not found", "status": 404, "detail": "no texture x"}

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(404, json=problem, headers={"content-type": "application/problem+json"})

    with client_for(handler) as ts, pytest.raises(ApiError, match="no texture x") as info:
        ts.texture("x")
    assert info.value.status == 404 and info.value.problem == problem


BUSY = {"type": "urn:texspace:problem:busy", "title": "The service is busy; retry later", "status": 503,
        "detail": "2 uploads are being encoded and 8 wait; retry shortly"}


def test_a_busy_answer_is_asked_again_after_its_retry_after(monkeypatch) -> None:
    """503 / 429 with Retry-After: the same request again (the photo's bytes too) after the
    named wait, capped; up to ``retries`` times, then the problem is raised. Other errors,
    and a 503 without Retry-After (nothing to wait for), raise at once."""
    slept: list[float] = []
    monkeypatch.setattr("service.client.time.sleep", slept.append)
    answers: list[httpx.Response] = []
    bodies: list[bytes] = []

    def handler(request: httpx.Request) -> httpx.Response:
        bodies.append(request.read())
        return answers.pop(0)

    busy = [httpx.Response(503, json=BUSY, headers={"retry-after": "2"}),
            httpx.Response(429, json={**BUSY, "status": 429}, headers={"retry-after": "600"})]
    answers[:] = busy + [httpx.Response(201, json={"id": "t1"})]
    with client_for(handler) as ts:
        assert ts.upload(b"photo bytes", filename="p.png")["id"] == "t1"
    assert slept == [2.0, 30.0] and len(bodies) == 3 and all(b"photo bytes" in body for body in bodies)

    slept.clear()
    answers[:] = [httpx.Response(503, json=BUSY, headers={"retry-after": "1"}) for _ in range(3)]
    with Client("http://texspace.test", transport=httpx.MockTransport(handler), retries=2) as ts, \
            pytest.raises(ApiError, match="being encoded") as info:
        ts.texture("x")
    assert info.value.status == 503 and slept == [1.0, 1.0] and answers == []

    for status, headers in ((503, {}), (422, {"retry-after": "1"})):
        slept.clear()
        answers[:] = [httpx.Response(status, json={**BUSY, "status": status}, headers=headers)]
        with client_for(handler) as ts, pytest.raises(ApiError):
            ts.texture("x")
        assert slept == [] and answers == []


def test_download_keeps_the_servers_file_name(tmp_path: Path) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/v1/jobs/j1/result"
        return httpx.Response(200, content=b"EXR bytes",
                              headers={"content-disposition": 'attachment; filename="volume-64.exr"'})

    with client_for(handler) as ts:
        assert ts.download("j1", tmp_path) == tmp_path / "volume-64.exr"
        assert ts.download("j1", tmp_path / "v.exr") == tmp_path / "v.exr"
    assert (tmp_path / "v.exr").read_bytes() == b"EXR bytes"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.exr", "volume-64.exr"]


def test_download_prefers_the_utf8_file_name(tmp_path: Path) -> None:
    from service.download_names import content_disposition

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, content=b"PNG", headers={"content-disposition": content_disposition("béton_1.png")})

    with client_for(handler) as ts:
        assert ts.download("j1", tmp_path) == tmp_path / "béton_1.png"


def test_the_client_imports_no_numpy_onnx_or_fastapi() -> None:
    code = ("import sys, service.client; heavy = {'numpy', 'onnxruntime', 'fastapi', 'sqlalchemy', 'torch'}; "
            "print(sorted(heavy & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"


def test_fit_sends_every_option_the_server_takes() -> None:
    """The client's fit body is a valid FitIn (extra fields forbidden) carrying each option."""
    from service.schemas import FitIn

    bodies: list[dict] = []

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/v1/textures/t1/fit"
        bodies.append(json.loads(request.content))
        return httpx.Response(202, json=JOB)

    with client_for(handler) as ts:
        ts.fit("t1", seconds=30, grain=None, lattice=None, even=None, detail_seconds=0)
        ts.fit("t1")
    sent = [FitIn.model_validate(body) for body in bodies]
    assert (sent[0].grain, sent[0].lattice, sent[0].even, sent[0].seconds) == (None, None, None, 30)
    assert sent[0].detail_seconds == 0
    assert sent[1].model_dump() == FitIn().model_dump()  # the defaults are the server's


def test_wait_refined_follows_the_uploads_refinement_with_a_bar(capsys) -> None:
    """wait_refined: the texture's refinement job, its progress drawn as a bar (a paused
    refinement says so), then the texture as it is after it."""
    texture = {"id": "t1", "sampler": "encoder", "refinement": {"job_id": "f1", "state": "queued"}}
    refined = {**texture, "sampler": "fitted", "refinement": {"job_id": "f1", "state": "succeeded"}}
    stream = events(("progress", {"state": "running", "progress": 0.1, "attempt": 1, "stage": None}),
                    ("progress", {"state": "queued", "progress": 0.1, "attempt": 0, "stage": "interim"}),
                    ("succeeded", {"id": "f1", "kind": "fit", "state": "succeeded", "progress": 1.0}))
    answers = iter([texture, refined])

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/f1/events":
            return httpx.Response(200, content=stream, headers={"content-type": "text/event-stream"})
        assert request.url.path == "/v1/textures/t1"
        return httpx.Response(200, json=next(answers))

    with client_for(handler) as ts:
        assert ts.wait_refined("t1", progress=True)["sampler"] == "fitted"
    bar = capsys.readouterr().err
    assert "job f1" in bar and "paused after its interim" in bar and "10%" in bar


def test_wait_honours_its_timeout_through_keep_alives() -> None:
    """A stream that only keeps alive (a long job) restarted the read timeout with each
    comment line; wait(timeout=...) must still end when its seconds are up."""
    import time

    def keep_alive():
        for _ in range(200):  # 20 s of keep-alives
            time.sleep(0.1)
            yield b": keep-alive\n\n"

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, content=keep_alive(), headers={"content-type": "text/event-stream"})
        return httpx.Response(200, json={**JOB, "state": "running", "progress": 0.5})

    started = time.monotonic()
    with client_for(handler) as ts, pytest.raises(TimeoutError):
        ts.wait("j1", timeout=0.5)
    assert time.monotonic() - started < 3.0


def test_ids_are_one_path_segment_each() -> None:
    """Client.texture('../../v1/jobs') read the jobs list and Client.delete('../textures/<id>')
    deleted that texture: ids are percent-encoded into one segment."""
    seen: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.url.raw_path.decode())
        return httpx.Response(200, json={**JOB, "id": "x"}) if request.method == "GET" else httpx.Response(204)

    with client_for(handler) as ts:
        ts.texture("../../v1/jobs")
        ts.delete("../textures/abc")
        ts.job("a/b")
    assert seen == ["/v1/textures/..%2F..%2Fv1%2Fjobs", "/v1/textures/..%2Ftextures%2Fabc", "/v1/jobs/a%2Fb"]


def test_bake_sends_list_fields_the_app_accepts(client, texture, tmp_path: Path) -> None:
    """Against the app itself: ``maps=[...]`` is the form field repeated (a str of the list
    answered 422), booleans are true / false, and the download is named after the bake."""
    mesh = Path(__file__).resolve().parents[1] / "data" / "meshes" / "cube.obj"
    with Client("http://testserver", transport=client._transport) as ts:
        job = ts.bake(texture["id"], mesh, resolution=64, maps=["height", "normal"], after_refinement=False,
                      normal_strength=6.0)
        assert job["params"]["maps"] == ["height", "normal"] and job["params"]["normal_strength"] == 6.0
        done = ts.wait(job, timeout=60)
        assert done["result"]["filename"] == "brick_cube_bake_64px_seed0.zip"
        assert ts.download(done, tmp_path).name == "brick_cube_bake_64px_seed0.zip"
        with pytest.raises(ApiError) as info:
            ts.bake(texture["id"], mesh, maps=["gloss"])
    assert info.value.status == 422


def test_limits_are_the_servers_read_once() -> None:
    """limits() asks GET /v1/limits once per client and answers the server's numbers."""
    served = {"max_tile_size": 512, "planes": ["xy", "xz", "yz"], "fit_seconds": 45.0, "max_fit_seconds": 600.0}
    calls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.url.path)
        return httpx.Response(200, json=served)

    with client_for(handler) as ts:
        assert ts.limits() == served and ts.limits()["fit_seconds"] == 45.0
    assert calls == ["/v1/limits"]


def test_a_photos_width_reaches_the_texture_and_bakes_at_real_size(client, photo) -> None:
    """Against the app: ``upload(width_m=)`` and ``set_width`` store the photo's width; a bake
    with ``unit_m`` then reports its texels per metre."""
    mesh = Path(__file__).resolve().parents[1] / "data" / "meshes" / "cube.obj"
    with Client("http://testserver", transport=client._transport) as ts:
        texture = ts.upload(photo, filename="b.png", width_m=1.25)
        assert texture["width_m"] == 1.25
        assert ts.set_width(texture["id"], 0.5)["width_m"] == 0.5
        done = ts.wait(ts.bake(texture["id"], mesh, resolution=64, unit_m=1.0), timeout=60)
        assert done["result"]["texels_per_metre"] > 0 and done["params"]["unit_m"] == 1.0
