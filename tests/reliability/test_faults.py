"""Faults survived by real processes (loopback only, seconds per scenario):

* SIGKILL the worker mid-job, three times in a row: the expired lease re-queues the job,
  the next worker finishes it, ``attempt`` counts the tries, and the result is one whole
  file written once.
* SIGTERM the worker mid-job: it hands the job back (or finishes it); nothing is lost.
* Kill and restart the API: textures and queued jobs are all still there and finish.

The scale-out faults (Redis restart, PostgreSQL connections dropped) are in
``test_scaleout_faults.py``. ``tests/e2e`` covers one SIGKILL in both deployments; here
the kills repeat and the stored result is inspected.
"""
from __future__ import annotations

import io
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import brick_png

from .procs import Cluster, base_env, wait_job

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.timeout(300)]
RESOLUTION = 128  # about 5 s of sampling on one thread: long enough to be killed mid-way


@pytest.fixture
def cluster(tmp_path: Path):
    cluster = Cluster(tmp_path, base_env(tmp_path / "data"))
    cluster.start_api()
    try:
        yield cluster
    finally:
        cluster.stop()


def upload(http) -> dict:  # noqa: ANN001
    res = http.post("/v1/textures", files={"image": ("brick.png", brick_png())})
    assert res.status_code == 201, res.text
    return res.json()


def result_files(root: Path, job_id: str) -> list[Path]:
    return sorted(p for p in (root / "data" / "storage" / "jobs" / job_id).rglob("*") if p.is_file())


def test_sigkill_worker_three_times_mid_job(cluster: Cluster) -> None:
    with cluster.client() as http:
        texture = upload(http)
        job = http.post(texture["links"]["volumes"], json={"resolution": RESOLUTION, "seed": 3}).json()
        held_by = []
        for round_ in range(1, 4):
            worker = cluster.start_worker()
            running = wait_job(http, job["id"], lambda j: j["state"] == "running" and j["attempt"] == round_
                               and j["progress"] >= 0.02, timeout=60, what=f"attempt {round_} running")
            assert running["worker_id"].endswith(f":{worker.pid}"), running  # this worker holds it
            os.kill(worker.pid, signal.SIGKILL)
            worker.wait(10)
            held_by.append(running["worker_id"])
            assert result_files(cluster.root, job["id"]) == []  # nothing half-written was stored
        finisher = cluster.start_worker()
        done = wait_job(http, job["id"], lambda j: j["state"] in ("succeeded", "failed", "canceled"), timeout=90,
                        what="finished")
        assert done["state"] == "succeeded", (done, cluster.log_tail())
        assert done["attempt"] == 4 and done["worker_id"].endswith(f":{finisher.pid}")
        assert len(set(held_by)) == 3
        files = result_files(cluster.root, job["id"])
        assert [f.name for f in files] == [done["result"]["filename"]]  # one object, no temp files
        assert files[0].stat().st_size == done["result"]["size"]
        volume = np.load(io.BytesIO(http.get(done["links"]["result"]).content))
        assert volume.shape == (RESOLUTION,) * 3 + (3,) and np.isfinite(volume).all()
        assert not list((cluster.root / "data" / "work").glob(f"{job['id']}-*"))  # scratch cleaned
        # a repeat of the same volume gives the same bytes: the re-runs wrote equal content
        again = http.post(texture["links"]["volumes"], json={"resolution": RESOLUTION, "seed": 3}).json()
        again = wait_job(http, again["id"], lambda j: j["state"] == "succeeded", timeout=60)
        assert http.get(again["links"]["result"]).content == files[0].read_bytes()


def test_sigterm_worker_hands_back_or_finishes(cluster: Cluster) -> None:
    with cluster.client() as http:
        texture = upload(http)
        job = http.post(texture["links"]["volumes"], json={"resolution": RESOLUTION}).json()
        worker = cluster.start_worker()
        wait_job(http, job["id"], lambda j: j["state"] == "running" and j["progress"] >= 0.02, timeout=60)
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(20) is not None
        after = http.get(f"/v1/jobs/{job['id']}").json()
        assert after["state"] in ("queued", "succeeded"), after  # handed back at once, or done
        if after["state"] == "queued":  # handed back by a stopping worker: its attempt not spent
            assert after["worker_id"] is None and after["lease_expires_at"] is None and after["attempt"] == 0
        cluster.start_worker()
        done = wait_job(http, job["id"], lambda j: j["state"] == "succeeded", timeout=60)
        assert len(result_files(cluster.root, job["id"])) == 1
        assert done["attempt"] == 1  # restarts never use up a job's attempts


def test_api_restart_loses_nothing(cluster: Cluster) -> None:
    """Jobs queued while no worker runs survive an API SIGKILL and restart, then finish."""
    with cluster.client() as http:
        texture = upload(http)
        ids = [http.post(texture["links"]["volumes"], json={"resolution": 8, "seed": s}).json()["id"]
               for s in range(3)]
    os.kill(cluster.api.pid, signal.SIGKILL)
    cluster.api.wait(10)
    cluster.start_api()
    with cluster.client() as http:
        assert http.get(f"/v1/textures/{texture['id']}").json()["code"] == texture["code"]
        assert {j["id"] for j in http.get("/v1/jobs", params={"state": "queued"}).json()["items"]} == set(ids)
        cluster.start_worker()
        for job_id in ids:
            assert wait_job(http, job_id, lambda j: j["state"] == "succeeded", timeout=60)["attempt"] == 1
