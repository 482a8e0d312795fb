"""The whole product through HTTP, in both deployments: upload -> tile -> volume job ->
bake job on a real mesh -> downloads load; Idempotency-Key; cancel queued and running."""
from __future__ import annotations

import io
import json
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from PIL import Image

from service.vocabulary import TERMINAL_STATES
from tests.helpers import brick_png

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.timeout(600)]
MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"


@pytest.fixture(scope="module", params=["embedded", pytest.param("scaleout", marks=pytest.mark.scaleout)])
def deployment(request):
    return request.getfixturevalue(request.param)


@pytest.fixture(scope="module")
def http(deployment) -> httpx.Client:
    with deployment.client() as client:
        yield client


@pytest.fixture(scope="module")
def texture(http) -> dict:
    res = http.post("/v1/textures", files={"image": ("brick.png", brick_png(128), "image/png")},
                    data={"name": "brick"})
    assert res.status_code == 201, res.text
    return res.json()


def wait_for(http: httpx.Client, job_id: str, states=TERMINAL_STATES, timeout: float = 240.0,
             min_progress: float | None = None) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = http.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in states and (min_progress is None or job["progress"] >= min_progress):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} not in {states} after {timeout}s: {job}")


def test_upload_and_tile(http, texture) -> None:
    assert http.get(texture["links"]["self"]).json()["code"] == texture["code"]
    res = http.get(f"/v1/textures/{texture['id']}/tiles/6/-1/3.png")
    assert res.status_code == 200 and res.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(res.content)).size == (256, 256)
    again = http.get(f"/v1/textures/{texture['id']}/tiles/6/-1/3.png",
                     headers={"If-None-Match": res.headers["etag"]})
    assert again.status_code == 304


def test_volume_job(http, texture) -> None:
    res = http.post(texture["links"]["volumes"], json={"resolution": 16, "seed": 2, "format": "npy"})
    assert res.status_code == 202 and res.headers["location"].startswith("/v1/jobs/")
    job = wait_for(http, res.json()["id"])
    assert job["state"] == "succeeded", job
    volume = np.load(io.BytesIO(http.get(job["links"]["result"]).content))
    assert volume.shape == (16, 16, 16, 3) and np.isfinite(volume).all()


def test_bake_job_glb_with_texture(http, texture) -> None:
    mesh = (MESHES / "bunny.obj").read_bytes()  # no UVs: the worker unwraps it with xatlas
    res = http.post(texture["links"]["bakes"], files={"mesh": ("bunny.obj", mesh)},
                    data={"resolution": "256", "seed": "0", "format": "glb"})
    assert res.status_code == 202, res.text
    job = wait_for(http, res.json()["id"])
    assert job["state"] == "succeeded", job
    result = http.get(job["links"]["result"])
    scene = trimesh.load(io.BytesIO(result.content), file_type="glb")
    geometry = next(iter(scene.geometry.values()))
    assert len(geometry.faces) >= 900
    texture_image = geometry.visual.material.baseColorTexture
    assert texture_image is not None and texture_image.size == (256, 256)
    assert np.asarray(texture_image).std() > 0  # not a blank image


def test_bake_obj_zip(http, texture) -> None:
    mesh = (MESHES / "cube.obj").read_bytes()
    res = http.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                    data={"resolution": "64", "format": "obj"})
    job = wait_for(http, res.json()["id"])
    assert job["state"] == "succeeded", job
    import zipfile

    names = zipfile.ZipFile(io.BytesIO(http.get(job["links"]["result"]).content)).namelist()
    assert any(n.endswith(".obj") for n in names) and any(n.endswith(".png") for n in names)


def test_idempotency_key(http, texture) -> None:
    key = {"Idempotency-Key": f"e2e-{time.time_ns()}"}
    first = http.post(texture["links"]["volumes"], json={"resolution": 8}, headers=key)
    second = http.post(texture["links"]["volumes"], json={"resolution": 8}, headers=key)
    assert first.status_code == second.status_code == 202
    assert first.json()["id"] == second.json()["id"]
    assert wait_for(http, first.json()["id"])["state"] == "succeeded"


def test_cancel_running_and_queued(http, texture, deployment) -> None:
    workers = 1 if deployment.name == "embedded" else 2
    # long jobs occupy every worker thread; one more waits in the queue
    long = [http.post(texture["links"]["volumes"], json={"resolution": 128, "seed": s}).json()
            for s in range(workers)]
    queued = http.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 99}).json()
    for job in long:
        wait_for(http, job["id"], states={"running"}, timeout=60)
    assert http.get(f"/v1/jobs/{queued['id']}").json()["state"] == "queued"
    res = http.post(f"/v1/jobs/{queued['id']}/cancel")
    assert res.status_code == 202 and res.json()["state"] == "canceled"
    for job in long:
        res = http.post(f"/v1/jobs/{job['id']}/cancel")
        assert res.status_code == 202 and res.json()["cancel_requested"]
    for job in long:
        done = wait_for(http, job["id"], timeout=60)
        assert done["state"] == "canceled", done
        assert http.get(f"/v1/jobs/{job['id']}/result").status_code == 409
    assert http.get(f"/v1/jobs/{queued['id']}").json()["state"] == "canceled"


def test_events_metrics_and_logs(http, texture, deployment) -> None:
    submitted = http.post(texture["links"]["volumes"], json={"resolution": 8},
                          headers={"X-Request-ID": "e2e-trace-1"})
    assert submitted.headers["x-request-id"] == "e2e-trace-1"
    job = submitted.json()
    with http.stream("GET", f"/v1/jobs/{job['id']}/events", timeout=120) as res:
        text = "".join(res.iter_text())
    assert "event: succeeded" in text
    metrics = http.get("/metrics").text
    assert "texspace_jobs{state=\"succeeded\"}" in metrics and "texspace_queue_depth" in metrics
    entries = [json.loads(line) for path in deployment.logs
               for line in path.read_text().splitlines() if line.startswith("{")]
    assert any(e.get("request_id") == "e2e-trace-1" and e.get("route") == "/v1/textures/{texture_id}/volumes"
               for e in entries)
    assert any(e.get("job_id") == job["id"] and e["message"] == "job succeeded" for e in entries)


def test_killed_worker_loses_nothing(http, texture, deployment) -> None:
    """SIGKILL the worker holding a job: its lease expires, the reaper re-queues the job,
    and another (or the restarted) worker finishes it as attempt 2. Runs last: it kills."""
    import os
    import signal

    # 160^3 (4.1 M samples): a few seconds even on a quiet machine, so the poll sees it
    # running (96^3 once ended in 0.5 s, between two polls)
    job = http.post(texture["links"]["volumes"], json={"resolution": 160, "seed": 5}).json()
    running = wait_for(http, job["id"], states={"running"}, timeout=120, min_progress=0.01)
    host, pid = running["worker_id"].rsplit(":", 1)
    ours = {p.pid for p in deployment.procs} | _children(deployment)
    assert int(pid) in ours, "the job's worker must be a process this test started"
    os.kill(int(pid), signal.SIGKILL)
    done = wait_for(http, job["id"], timeout=300)
    assert done["state"] == "succeeded", done
    assert done["attempt"] == 2 and done["worker_id"] != running["worker_id"]
    volume = np.load(io.BytesIO(http.get(done["links"]["result"]).content))
    assert volume.shape == (160, 160, 160, 3)


def _children(deployment) -> set[int]:
    """Pids of the children of our processes (``serve`` runs its worker as a child)."""
    found = set()
    for proc in deployment.procs:
        for task in Path(f"/proc/{proc.pid}/task").glob("*"):
            try:
                found |= {int(p) for p in (task / "children").read_text().split()}
            except OSError:
                pass
    return found
