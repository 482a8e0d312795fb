"""Fixtures shared by every test folder. Keep small: folder conftests hold the rest."""
from __future__ import annotations

from collections.abc import Iterator

import pytest

from service.spawn import free_port
from tests.helpers import REDIS_URL, fresh_postgres_database


@pytest.fixture(scope="session")
def moto_s3_url() -> Iterator[str]:
    """An S3-compatible server (moto, server mode) on loopback for the whole session."""
    moto_server = pytest.importorskip("moto.server", reason="moto[server] is in the test extra")
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=free_port(), verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    try:
        yield f"http://{host}:{port}"
    finally:
        server.stop()


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A fresh, empty PostgreSQL database on the local server (dropped afterwards)."""
    with fresh_postgres_database() as url:
        yield url


@pytest.fixture
def redis_url() -> str:
    """The local Redis server, or a skip saying why not."""
    import redis  # a dependency: a missing one fails; only an absent server skips
    try:
        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3).ping()
    except redis.RedisError as exc:
        pytest.skip(f"Redis unreachable at {REDIS_URL}: {exc}")
    return REDIS_URL
