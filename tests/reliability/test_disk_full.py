"""A full disk, by fault injection: the red team's 48 MB tmpfs answered uploads and deletes
with 500, kept /readyz at 200 and re-rendered a volume three times before failing it with
an error naming server paths.

Writes that fail for space (an ENOSPC OSError from storage or a writer, the database's own
"full" error wrapped as SQLAlchemy wraps it) are a 507 ``insufficient-storage`` problem that
names no path; a job that fails so is not retried; a DELETE frees the files before it asks
the database for journal room, so deleting is how space comes back; /readyz is 503 below
``TEXSPACE_MIN_FREE_BYTES``."""
from __future__ import annotations

import errno
import os
import shutil
import sqlite3
from collections import namedtuple
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event

from service.context import build_services
from service.errors import storage_full
from service.main import create_app
from service.runner import run_job_attempt
from tests.helpers import brick_png

from tests.reliability.helpers import PROBLEM, make_settings, row_counts, stored_files

FULL_TYPE = "urn:texspace:problem:insufficient-storage"
SERVER_PATH = "/srv/texspace/data/storage/textures/0123/.tmp-x7"  # what a real ENOSPC names


def enospc() -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), SERVER_PATH)


def database_full(services) -> Exception:  # noqa: ANN001
    """The driver's own "full" error, as the engine in use raises it."""
    if services.engine.dialect.name == "sqlite":
        return sqlite3.OperationalError("database or disk is full")
    import psycopg

    return psycopg.errors.DiskFull(f'could not extend file "{SERVER_PATH}": No space left on device')


@pytest.fixture
def held(tmp_path: Path, database_url):  # noqa: ANN001
    """The app on SQLite or PostgreSQL with an in-memory queue nothing consumes, and the
    row counts it started with (the PostgreSQL database serves the whole module)."""
    overrides = {"database_url": database_url} if database_url else {}
    services = build_services(make_settings(tmp_path, queue_backend="memory", **overrides))
    with TestClient(create_app(services=services)) as client:
        yield services, client, row_counts(services)
    services.engine.dispose()


def fail_statements(services, starting: str, when=lambda: True):  # noqa: ANN001, ANN202
    """Make the database refuse statements beginning with ``starting`` for space while
    ``when()`` holds: raised from the cursor, so SQLAlchemy wraps it as it wraps a real one."""
    def refuse(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001, ANN202
        if statement.lstrip().upper().startswith(starting) and when():
            raise database_full(services)

    event.listen(services.engine, "before_cursor_execute", refuse)
    return lambda: event.remove(services.engine, "before_cursor_execute", refuse)


def no_folders_below_the_top(services) -> bool:  # noqa: ANN001
    root = services.storage.root
    return [p for p in root.rglob("*") if p.parent != root] == []


def assert_storage_full(res) -> None:  # noqa: ANN001
    assert res.status_code == 507 and res.headers["content-type"] == PROBLEM, res.text
    body = res.json()
    assert body["type"] == FULL_TYPE and body["status"] == 507
    assert "full" in body["detail"] and "/" not in body["detail"], body["detail"]  # no server path


def test_an_upload_whose_file_cannot_be_written_is_507_and_leaves_nothing(held, monkeypatch) -> None:
    services, client, rows = held

    def copy_part_then_fail(src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        Path(dst).write_bytes(Path(src).read_bytes()[:100])
        raise enospc()

    monkeypatch.setattr(shutil, "copyfile", copy_part_then_fail)
    assert_storage_full(client.post("/v1/textures", files={"image": ("t.png", brick_png())}))
    monkeypatch.undo()
    assert stored_files(services) == [] and row_counts(services) == rows
    assert no_folders_below_the_top(services)  # no empty textures/<id>/ left either


def test_an_upload_whose_row_cannot_be_written_is_507_and_leaves_nothing(held) -> None:
    services, client, rows = held
    restore = fail_statements(services, "INSERT INTO TEXTURES")
    try:
        assert_storage_full(client.post("/v1/textures", files={"image": ("t.png", brick_png())}))
    finally:
        restore()
    assert stored_files(services) == [] and row_counts(services) == rows
    assert no_folders_below_the_top(services)
    assert client.post("/v1/textures", files={"image": ("t.png", brick_png())}).status_code == 201  # space back


def test_delete_on_a_full_disk_frees_the_files_first_so_the_rows_can_go(held) -> None:
    """The database can delete only once there is room for its journal, which the texture's
    own files give back: deleting rows first answered 500 on 8 of 8 textures."""
    services, client, rows = held
    texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
    job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
    assert run_job_attempt(services, job["id"]) == "succeeded"
    folder = services.storage.root / "textures" / texture["id"]
    restore = fail_statements(services, "DELETE", when=folder.exists)  # full while its files take the space
    try:
        assert client.delete(texture["links"]["self"]).status_code == 204
    finally:
        restore()
    assert stored_files(services) == [] and row_counts(services) == rows
    assert client.get(texture["links"]["self"]).status_code == 404


def test_delete_that_still_finds_the_database_full_is_507_and_can_be_repeated(held) -> None:
    services, client, rows = held
    texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
    restore = fail_statements(services, "DELETE")
    try:
        assert_storage_full(client.delete(texture["links"]["self"]))
    finally:
        restore()
    assert stored_files(services) == []  # its files are freed all the same
    assert client.delete(texture["links"]["self"]).status_code == 204  # once there is room
    assert row_counts(services) == rows


def test_a_job_that_fails_for_space_fails_once_and_names_no_path(held, monkeypatch) -> None:
    services, client, rows = held
    texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
    job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
    services.huey.flush()
    from worker import volume_writers

    def disk_full(self, rgb):  # noqa: ANN001, ANN202
        raise enospc()

    monkeypatch.setattr(volume_writers.NpyWriter, "write", disk_full)
    assert run_job_attempt(services, job["id"]) == "failed"
    body = client.get(job["links"]["self"]).json()
    assert body["state"] == "failed" and body["attempt"] == 1, body  # not re-rendered
    assert body["error"]["type"] == FULL_TYPE and body["error"]["status"] == 507
    assert "/" not in body["error"]["detail"], body["error"]
    assert services.huey.pending_count() == 0  # nothing re-sent
    assert not list(services.work_dir.iterdir())  # its scratch is gone


def test_a_job_that_crashes_otherwise_is_still_retried(held, monkeypatch) -> None:
    services, client, rows = held
    texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
    job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
    services.huey.flush()
    from worker import volume_writers

    def io_error(self, rgb):  # noqa: ANN001, ANN202
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(volume_writers.NpyWriter, "write", io_error)
    assert run_job_attempt(services, job["id"]) == "queued"
    assert client.get(job["links"]["self"]).json()["attempt"] == 1 and services.huey.pending_count() == 1


Usage = namedtuple("Usage", "total used free")


def test_readyz_fails_below_the_free_space_threshold(held, monkeypatch) -> None:
    services, client, rows = held
    minimum = services.settings.min_free_bytes
    assert minimum == 64 * 2**20
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(2**30, 2**30 - minimum, minimum))
    res = client.get("/readyz")
    assert res.status_code == 200 and res.json()["checks"]["disk"] == "ok", res.json()
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(48 * 2**20, 48 * 2**20, 0))
    res = client.get("/readyz")
    assert res.status_code == 503 and res.json()["status"] == "unavailable"
    disk = res.json()["checks"]["disk"]
    assert disk.startswith("error: InsufficientStorage:") and "0.0 MiB free" in disk and "MIN_FREE" in disk, disk
    assert all(v == "ok" for k, v in res.json()["checks"].items() if k != "disk")
    services.settings.min_free_bytes = 0  # the check switched off
    assert client.get("/readyz").status_code == 200


def test_space_errors_are_recognised_through_their_causes() -> None:
    import sqlalchemy.exc

    wrapped = sqlalchemy.exc.OperationalError("DELETE FROM jobs", {}, sqlite3.OperationalError(
        "database or disk is full"))
    assert storage_full(wrapped) is not None
    try:
        try:
            raise enospc()
        except OSError as exc:
            raise RuntimeError("writing the result failed") from exc
    except RuntimeError as chained:
        assert storage_full(chained) is not None
    assert storage_full(OSError(errno.EDQUOT, "Disk quota exceeded")) is not None
    assert storage_full(OSError("OpenImageIO failed on slice 3: No space left on device")) is not None
    assert storage_full(sqlite3.OperationalError("database is locked")) is None
    assert storage_full(OSError(errno.EIO, "Input/output error")) is None
    assert storage_full(ValueError("full")) is None
