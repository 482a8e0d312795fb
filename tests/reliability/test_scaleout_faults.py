"""Scale-out faults: the queue broker (Redis) restarts, PostgreSQL drops every connection
of the service. Both are survived: processes reconnect, and no job is lost (a job whose
queue message vanished is re-sent by the reaper from the job table).

Uses a *separate* redis-server started here on a free loopback port (never the shared
one) and a fresh PostgreSQL database; skipped, saying why, when either is unavailable.
"""
from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from service.spawn import free_port
from tests.helpers import PG_ADMIN_URL, brick_png

from .procs import Cluster, base_env, wait_job

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.scaleout, pytest.mark.timeout(300)]
LONG = 128  # a ~5 s volume job


class OwnRedis:
    """A throw-away redis-server (no persistence: a restart loses every queued message)."""

    def __init__(self, root: Path) -> None:
        self.root, self.port, self.proc = root, free_port(), None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.root)], stdout=open(self.root / "redis.log", "ab"), stderr=subprocess.STDOUT,
            start_new_session=True)
        import redis

        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                if redis.Redis.from_url(self.url, socket_connect_timeout=1).ping():
                    return
            except redis.RedisError:
                time.sleep(0.1)
        raise AssertionError("own redis-server did not start")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(10)


@pytest.fixture
def own_redis(tmp_path: Path):
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed")
    server = OwnRedis(tmp_path)
    server.start()
    try:
        yield server
    finally:
        server.stop()


def upload(http: httpx.Client) -> dict:
    res = http.post("/v1/textures", files={"image": ("brick.png", brick_png())})
    assert res.status_code == 201, res.text
    return res.json()


def succeeded(job: dict) -> bool:
    assert job["state"] not in ("failed", "canceled"), job
    return job["state"] == "succeeded"


def test_redis_restart_loses_no_job(tmp_path: Path, postgres_url: str, own_redis: OwnRedis) -> None:
    env = base_env(tmp_path / "data", TEXSPACE_DATABASE_URL=postgres_url, TEXSPACE_QUEUE_BACKEND="redis",
                   TEXSPACE_QUEUE_URL=own_redis.url)
    cluster = Cluster(tmp_path, env)
    try:
        cluster.start_api()
        worker = cluster.start_worker()
        with cluster.client() as http:
            texture = upload(http)
            first = http.post(texture["links"]["volumes"], json={"resolution": 8}).json()
            wait_job(http, first["id"], succeeded, timeout=60)
            # a long job occupies the one worker thread; the next one's message waits in Redis
            long = http.post(texture["links"]["volumes"], json={"resolution": LONG}).json()
            wait_job(http, long["id"], lambda j: j["state"] == "running", timeout=30)
            waiting = http.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 1}).json()
            own_redis.stop()  # the waiting job's message is gone with it
            during = http.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 2})
            assert during.status_code == 202, during.text  # the row is the truth; the reaper re-sends
            ready = http.get("/readyz")
            assert ready.status_code == 503 and ready.json()["checks"]["queue"].startswith("error")
            own_redis.start()
            for job in (long, waiting, during.json()):
                done = wait_job(http, job["id"], succeeded, timeout=90, what="succeeded after the restart")
                assert done["attempt"] == 1
            assert http.get("/readyz").status_code == 200
            after = http.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 3}).json()
            done = wait_job(http, after["id"], succeeded, timeout=60)
            assert done["worker_id"].endswith(f":{worker.pid}")  # the same worker reconnected
    finally:
        cluster.stop()


def terminate_connections(database_url: str) -> int:
    """Kill every server process connected to the service's database; return how many."""
    import psycopg

    name = database_url.rsplit("/", 1)[1]
    with psycopg.connect(PG_ADMIN_URL, autocommit=True) as admin:
        rows = admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                             "WHERE datname = %s AND pid <> pg_backend_pid()", (name,)).fetchall()
    return len(rows)


@pytest.mark.parametrize("queue_backend", ["redis", "postgres"])
def test_postgres_connection_drop_is_survived(tmp_path: Path, postgres_url: str, own_redis: OwnRedis,
                                              queue_backend: str) -> None:
    env = base_env(tmp_path / "data", TEXSPACE_DATABASE_URL=postgres_url, TEXSPACE_QUEUE_BACKEND=queue_backend,
                   TEXSPACE_QUEUE_URL=own_redis.url if queue_backend == "redis" else postgres_url,
                   TEXSPACE_REQUEUE_AFTER_SECONDS="600")  # delivered directly, not rescued by the reaper
    cluster = Cluster(tmp_path, env)
    try:
        cluster.start_api()
        worker = cluster.start_worker()
        with cluster.client() as http:
            texture = upload(http)
            long = http.post(texture["links"]["volumes"], json={"resolution": LONG}).json()
            wait_job(http, long["id"], lambda j: j["state"] == "running" and j["progress"] > 0.05, timeout=30)
            assert terminate_connections(postgres_url) >= 2  # the API's and the worker's
            assert http.get(f"/v1/textures/{texture['id']}").status_code == 200  # pre-ping reconnects
            done = wait_job(http, long["id"], succeeded, timeout=90, what="long job succeeded")
            assert done["attempt"] == 1  # heartbeats resumed before the lease ran out
            terminate_connections(postgres_url)
            again = http.post(texture["links"]["volumes"], json={"resolution": 8})
            assert again.status_code == 202, again.text
            done = wait_job(http, again.json()["id"], succeeded, timeout=60)
            assert done["worker_id"].endswith(f":{worker.pid}")
    finally:
        cluster.stop()


def test_two_sigterms_in_a_row_leave_the_job_queued_with_its_attempts(tmp_path: Path, postgres_url: str,
                                                                      own_redis: OwnRedis) -> None:
    """A graceful restart, twice, while a volume runs: each stopping worker hands the job back
    and claims nothing more (it once claimed it again, crashed on shutdown, and the second
    restart failed the job at attempt 4 of 3); the next worker finishes it at attempt 1."""
    import signal

    env = base_env(tmp_path / "data", TEXSPACE_DATABASE_URL=postgres_url, TEXSPACE_QUEUE_BACKEND="redis",
                   TEXSPACE_QUEUE_URL=own_redis.url)
    cluster = Cluster(tmp_path, env)
    try:
        cluster.start_api()
        with cluster.client() as http:
            texture = upload(http)
            job = http.post(texture["links"]["volumes"], json={"resolution": LONG}).json()
            for _ in range(2):
                worker = cluster.start_worker()
                wait_job(http, job["id"], lambda j: j["state"] == "running" and j["progress"] >= 0.02, timeout=60)
                worker.send_signal(signal.SIGTERM)
                assert worker.wait(20) is not None
                after = http.get(f"/v1/jobs/{job['id']}").json()
                assert after["state"] in ("queued", "succeeded"), after
                if after["state"] == "succeeded":  # it finished before the signal landed: nothing to hand back
                    break
                assert after["attempt"] == 0 and after["worker_id"] is None and after["error"] is None, after
            cluster.start_worker()
            done = wait_job(http, job["id"], succeeded, timeout=90)
            assert done["attempt"] == 1
    finally:
        cluster.stop()
