"""Real ``texspace`` processes for fault tests: start, wait, signal, on loopback ports.

Every process runs in its own session, so a test only ever signals processes it started.
"""
from __future__ import annotations

import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from service import spawn
from service.spawn import free_port
from tests.helpers import wait_ready

FAST_JOBS = {  # short leases so a killed worker's job comes back within seconds
    "TEXSPACE_LEASE_SECONDS": "2", "TEXSPACE_HEARTBEAT_SECONDS": "0.3", "TEXSPACE_REAPER_INTERVAL_SECONDS": "0.5",
    "TEXSPACE_REQUEUE_AFTER_SECONDS": "3", "TEXSPACE_MAX_ATTEMPTS": "6", "TEXSPACE_WORKERS": "1",
    "TEXSPACE_LOG_JSON": "true", "PYTHONUNBUFFERED": "1",
    "TEXSPACE_AUTO_FIT": "false",  # no minute-long fit job behind every upload
}


@dataclass
class Cluster:
    """An API process and workers sharing one environment (database, queue, storage)."""

    root: Path
    env: dict[str, str]
    port: int = field(default_factory=free_port)
    api: subprocess.Popen | None = None
    workers: list[subprocess.Popen] = field(default_factory=list)
    logs: list[Path] = field(default_factory=list)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _spawn(self, args: list[str], name: str) -> subprocess.Popen:
        log_path = self.root / f"{name}-{len(self.logs)}.log"
        self.logs.append(log_path)
        return spawn.spawn(args, self.env | {"TEXSPACE_PORT": str(self.port)}, log_path)

    def start_api(self, timeout: float = 60.0) -> None:
        self.api = self._spawn(["api"], "api")
        # liveness (/healthz), what these fault tests have always waited for, not /readyz
        wait_ready(self.base_url, [self.api], timeout, output=self.log_tail, name="api", path="/healthz")

    def start_worker(self) -> subprocess.Popen:
        proc = self._spawn(["worker", "--no-migrate"], "worker")
        self.workers.append(proc)
        return proc

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=30.0)

    def log_tail(self, chars: int = 2500) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-chars:]}" for p in self.logs if p.exists())

    def stop(self) -> None:
        spawn.stop([self.api, *self.workers])


def base_env(data_dir: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TEXSPACE_")}
    return env | FAST_JOBS | {"TEXSPACE_DATA_DIR": str(data_dir)} | extra


def wait_job(http: httpx.Client, job_id: str, done, timeout: float = 120.0, what: str = "") -> dict:  # noqa: ANN001
    """Poll the job until ``done(job)`` holds; tolerate the API being briefly unreachable."""
    deadline = time.monotonic() + timeout
    job: dict = {}
    while time.monotonic() < deadline:
        try:
            job = http.get(f"/v1/jobs/{job_id}").json()
        except httpx.HTTPError:
            job = {}
        if job and done(job):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id}: {what or 'condition'} not met in {timeout}s: {job}")
