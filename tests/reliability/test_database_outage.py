"""The database stops answering: requests get ``503 database-unavailable`` with Retry-After
(not ``500 internal-error``), no driver message reaches the client, and service resumes
when the database is back, without a restart. On SQLite (a database file that cannot be
opened, and one locked by another writer past the busy timeout) and on PostgreSQL (a
server that refuses connections), through the conftest's ``database_url``."""
from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from sqlalchemy import create_engine

from service.db import make_engine
from service.errors import DATABASE_RETRY_AFTER_SECONDS

from tests.reliability.helpers import PROBLEM


@contextmanager
def sessions_bound_to(services, engine) -> Iterator[None]:  # noqa: ANN001
    """Every session the app opens meanwhile talks to ``engine``."""
    services.sessions.configure(bind=engine)
    try:
        yield
    finally:
        services.sessions.configure(bind=services.engine)
        engine.dispose()


def unreachable_engine(services, tmp_path):  # noqa: ANN001
    """An engine of the deployment's kind whose database does not answer."""
    if services.engine.dialect.name == "sqlite":
        return make_engine(f"sqlite:///{tmp_path}/no-such-folder/texspace.db")
    return create_engine("postgresql+psycopg://texspace@127.0.0.1:1/texspace", connect_args={"connect_timeout": 2})


def assert_database_unavailable(res) -> None:  # noqa: ANN001
    assert res.status_code == 503, res.text
    assert res.headers["content-type"] == PROBLEM
    assert res.headers["retry-after"] == str(DATABASE_RETRY_AFTER_SECONDS)
    body = res.json()
    assert body["type"] == "urn:texspace:problem:database-unavailable", body
    assert "database" in body["detail"] and "sqlite" not in body["detail"].lower(), body["detail"]
    assert "127.0.0.1" not in body["detail"] and "SELECT" not in body["detail"]


def test_requests_during_an_outage_are_503_with_retry_after(client, module_services, texture, tmp_path) -> None:
    with sessions_bound_to(module_services, unreachable_engine(module_services, tmp_path)):
        assert_database_unavailable(client.get("/v1/textures"))
        assert_database_unavailable(client.get(f"/v1/textures/{texture['id']}"))
        assert_database_unavailable(client.post(texture["links"]["volumes"], json={"resolution": 8}))
    res = client.get(f"/v1/textures/{texture['id']}")     # back: no restart needed
    assert res.status_code == 200 and res.json()["id"] == texture["id"]


def test_sqlite_locked_past_its_busy_timeout_is_503(client, module_services, texture) -> None:
    if module_services.engine.dialect.name != "sqlite":
        pytest.skip("SQLite's own lock")
    path = module_services.engine.url.database
    # the app's busy timeout is 30 s; 0.2 s here, so the lock outlasts it at once
    impatient = create_engine(f"sqlite:///{path}", connect_args={"timeout": 0.2, "check_same_thread": False})
    writer = sqlite3.connect(path, timeout=5)
    writer.execute("BEGIN EXCLUSIVE")      # another process's long write
    try:
        with sessions_bound_to(module_services, impatient):
            assert_database_unavailable(client.post(texture["links"]["volumes"], json={"resolution": 8}))
    finally:
        writer.rollback()
        writer.close()
    assert client.get(f"/v1/textures/{texture['id']}").status_code == 200
