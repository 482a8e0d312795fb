"""End-to-end deployments: real ``texspace`` processes on free loopback ports.

* embedded: ``texspace serve`` (API + one worker process, SQLite + SqliteHuey + local folder)
* scaleout: ``texspace api`` + 2 ``texspace worker`` processes on PostgreSQL + Redis + an
  S3-compatible server (moto), each process with its own data folder (nothing shared
  on disk). Skipped, with the reason, when PostgreSQL or Redis cannot be reached.
"""
from __future__ import annotations

import os
import subprocess
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from service import spawn
from service.spawn import free_port
from tests.helpers import REDIS_URL, fresh_postgres_database, wait_ready

READY_TIMEOUT = 120.0


@dataclass
class Deployment:
    name: str
    base_url: str
    procs: list[subprocess.Popen] = field(default_factory=list)
    logs: list[Path] = field(default_factory=list)

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=60.0)

    def log_tail(self, chars: int = 3000) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-chars:]}" for p in self.logs)


def _start(args: list[str], env: dict[str, str], log_path: Path) -> subprocess.Popen:
    return spawn.spawn(args, env, log_path)


def _wait_ready(dep: Deployment) -> None:
    wait_ready(dep.base_url, dep.procs, READY_TIMEOUT, output=dep.log_tail, name=dep.name)


def _stop(dep: Deployment) -> None:
    spawn.stop(dep.procs)


def _base_env(data_dir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TEXSPACE_")}
    env.update(TEXSPACE_DATA_DIR=str(data_dir), TEXSPACE_LOG_JSON="true", TEXSPACE_HEARTBEAT_SECONDS="0.5",
               TEXSPACE_WORKERS="1", TEXSPACE_LEASE_SECONDS="4", TEXSPACE_REAPER_INTERVAL_SECONDS="1",
               TEXSPACE_AUTO_FIT="false", PYTHONUNBUFFERED="1")
    return env


@pytest.fixture(scope="module")
def embedded(tmp_path_factory) -> Iterator[Deployment]:
    root = tmp_path_factory.mktemp("embedded")
    port = free_port()
    env = _base_env(root / "data") | {"TEXSPACE_PORT": str(port)}
    dep = Deployment("embedded", f"http://127.0.0.1:{port}", logs=[root / "serve.log"])
    dep.procs.append(_start(["serve"], env, dep.logs[0]))
    try:
        _wait_ready(dep)
        yield dep
    finally:
        _stop(dep)


def _require_redis() -> None:
    import redis  # a dependency: a missing one fails; only an absent server skips
    try:
        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3).ping()
    except redis.RedisError as exc:
        pytest.skip(f"Redis unreachable at {REDIS_URL}: {exc}")


@pytest.fixture(scope="module")
def scaleout(tmp_path_factory, moto_s3_url: str) -> Iterator[Deployment]:
    _require_redis()
    with fresh_postgres_database("texspace_e2e") as database_url:
        yield from _scaleout(tmp_path_factory, moto_s3_url, database_url)


def _scaleout(tmp_path_factory, moto_s3_url: str, database_url: str) -> Iterator[Deployment]:
    root = tmp_path_factory.mktemp("scaleout")
    run = uuid.uuid4().hex[:8]
    port = free_port()
    shared = {"TEXSPACE_DATABASE_URL": database_url, "TEXSPACE_QUEUE_BACKEND": "redis",
              "TEXSPACE_QUEUE_URL": REDIS_URL, "TEXSPACE_QUEUE_NAME": f"texspace-e2e-{run}",
              "TEXSPACE_STORAGE_BACKEND": "s3", "TEXSPACE_S3_ENDPOINT_URL": moto_s3_url,
              "TEXSPACE_S3_BUCKET": f"texspace-e2e-{run}", "TEXSPACE_S3_ACCESS_KEY": "test",
              "TEXSPACE_S3_SECRET_KEY": "test", "TEXSPACE_PORT": str(port)}
    dep = Deployment("scaleout", f"http://127.0.0.1:{port}")
    for name, args in (("api", ["api"]), ("worker-1", ["worker"]), ("worker-2", ["worker"])):
        log_path = root / f"{name}.log"
        dep.logs.append(log_path)
        dep.procs.append(_start(args, _base_env(root / name) | shared, log_path))
    try:
        _wait_ready(dep)
        yield dep
    finally:
        _stop(dep)
        import redis

        client = redis.Redis.from_url(REDIS_URL)
        for key in client.scan_iter(f"*texspace-e2e-{run}*"):
            client.delete(key)
