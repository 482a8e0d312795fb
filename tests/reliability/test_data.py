"""Data hygiene: deleting a texture cancels and deletes its jobs and removes every file
they stored (storage listed before and after); writes are temp-file-then-rename, so an
interrupted write leaves neither a partial object nor a temporary file."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service import jobs
from service.context import build_services
from service.main import create_app
from service.runner import run_job_attempt
from service.storage import LocalStorage
from tests.helpers import brick_png
from tests.reliability.helpers import BAD, make_settings, row_counts, stored_files


@pytest.fixture
def held(tmp_path: Path):
    """The app with an in-memory queue that nothing consumes: jobs run only when the test
    calls run_job_attempt."""
    services = build_services(make_settings(tmp_path, queue_backend="memory"))
    with TestClient(create_app(services=services)) as client:
        yield services, client
    services.engine.dispose()


def test_delete_texture_removes_jobs_and_files(held) -> None:
    services, client = held
    keep = client.post("/v1/textures", files={"image": ("keep.png", brick_png(64))}).json()
    keep_job = client.post(keep["links"]["volumes"], json={"resolution": 8}).json()
    run_job_attempt(services, keep_job["id"])
    before = stored_files(services)

    doomed = client.post("/v1/textures", files={"image": ("doomed.png", brick_png())}).json()
    done = client.post(doomed["links"]["volumes"], json={"resolution": 8}).json()
    assert run_job_attempt(services, done["id"]) == "succeeded"
    baked = client.post(doomed["links"]["bakes"], files={"mesh": ("cube.obj", (BAD / "cube.obj").read_bytes())},
                        data={"resolution": "16"}).json()                     # queued, input stored
    running = client.post(doomed["links"]["volumes"], json={"resolution": 8, "seed": 1}).json()
    claim = jobs.claim(services, running["id"])                                # a worker holds it
    queued = client.post(doomed["links"]["volumes"], json={"resolution": 8, "seed": 2}).json()
    assert {f.split("/")[1] for f in stored_files(services) if f.startswith("jobs/")} >= {done["id"], baked["id"]}

    res = client.delete(doomed["links"]["self"])
    assert res.status_code == 204
    assert stored_files(services) == before                   # nothing of the texture or its jobs is left
    assert row_counts(services) == (1, 1)
    for job in (done, baked, running, queued):
        assert client.get(job["links"]["self"]).status_code == 404
    assert jobs.heartbeat(services, claim, 0.5)[0] is False    # the running attempt has lost its lease
    assert run_job_attempt(services, queued["id"]) is None      # its queue message is dropped
    assert stored_files(services) == before
    assert client.get(f"/v1/jobs/{keep_job['id']}/result").status_code == 200   # the other texture is untouched


def test_job_finishing_after_its_texture_was_deleted_leaves_no_files(held, monkeypatch) -> None:
    """The race: the texture is deleted while a job runs, and the job stores its result
    before it notices. The runner removes what it stored."""
    services, client = held
    texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
    job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
    from service import job_kinds

    real_store = job_kinds._store_result

    def delete_then_store(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        assert client.delete(texture["links"]["self"]).status_code == 204    # the DELETE lands first
        assert stored_files(services) == []
        return real_store(*args, **kwargs)                                    # then the result is stored

    monkeypatch.setattr(job_kinds, "_store_result", delete_then_store)
    run_job_attempt(services, job["id"])
    assert stored_files(services) == [] and row_counts(services) == (0, 0)
    assert not list(services.work_dir.iterdir())


def test_interrupted_write_leaves_no_partial_object(tmp_path: Path, monkeypatch) -> None:
    storage = LocalStorage(tmp_path / "store")
    storage.put_bytes("textures/a/exemplar.png", b"old content")
    real_copy = shutil.copyfile

    def copy_half_then_fail(src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        data = Path(src).read_bytes()
        Path(dst).write_bytes(data[: len(data) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(shutil, "copyfile", copy_half_then_fail)
    for key in ("textures/a/exemplar.png", "textures/b/exemplar.png"):
        with pytest.raises(OSError):
            storage.put_bytes(key, b"new content that never lands")
    monkeypatch.setattr(shutil, "copyfile", real_copy)
    files = sorted(str(p.relative_to(storage.root)) for p in storage.root.rglob("*") if p.is_file())
    assert files == ["textures/a/exemplar.png"]                 # no temp files, no partial b
    assert storage.get_bytes("textures/a/exemplar.png") == b"old content"


def test_backup_and_restore_as_the_readme_says(tmp_path: Path) -> None:
    """docs/OPERATIONS.md "Backup and restore", embedded setup: an online SQLite backup plus a copy of
    the storage folder bring back every texture and job result, byte for byte."""
    import sqlite3

    services = build_services(make_settings(tmp_path / "live"), immediate=True)
    with TestClient(create_app(services=services)) as client:
        texture = client.post("/v1/textures", files={"image": ("t.png", brick_png())}).json()
        job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
        tile = client.get(f"/v1/textures/{texture['id']}/tiles/6/1/-2.png").content
        result = client.get(f"/v1/jobs/{job['id']}/result").content
        data = services.settings.data_dir
        backup = tmp_path / "backup"
        backup.mkdir()
        with sqlite3.connect(data / "texspace.db") as src, sqlite3.connect(backup / "texspace.db") as dst:
            src.backup(dst)                                       # 1. the database (online, consistent)
        shutil.copytree(data / "storage", backup / "storage")     # 2. then the storage folder
    services.engine.dispose()

    restored = tmp_path / "restored" / "data"
    restored.mkdir(parents=True)
    shutil.copy(backup / "texspace.db", restored / "texspace.db")
    shutil.copytree(backup / "storage", restored / "storage")
    services = build_services(make_settings(tmp_path / "restored"), immediate=True)
    with TestClient(create_app(services=services)) as client:
        assert client.get(texture["links"]["self"]).json()["code"] == texture["code"]
        assert client.get(f"/v1/textures/{texture['id']}/tiles/6/1/-2.png").content == tile
        assert client.get(f"/v1/jobs/{job['id']}/result").content == result
        assert client.get(texture["links"]["exemplar"]).content == brick_png()
    services.engine.dispose()


def test_failed_database_insert_leaves_no_file(held, monkeypatch) -> None:
    """The file is stored before its row; if the row cannot be written, the file goes too."""
    services, client = held
    from service import db

    real_scope = db.session_scope

    class Broken(Exception):
        pass

    def failing_scope(factory):  # noqa: ANN001, ANN202
        from contextlib import contextmanager

        @contextmanager
        def scope():  # noqa: ANN202
            with real_scope(factory) as session:
                yield session
                if any(type(o).__name__ == "Texture" for o in session.new):
                    raise Broken("database went away")
        return scope()

    monkeypatch.setattr("service.routes.textures.session_scope", failing_scope)
    res = client.post("/v1/textures", files={"image": ("t.png", brick_png())})  # answered, with its request id
    assert res.status_code == 500 and res.json()["type"] == "urn:texspace:problem:internal-error"
    assert stored_files(services) == [] and row_counts(services) == (0, 0)


def test_concurrent_deletes_of_one_texture_answer_one_204(held) -> None:
    """Four requests deleting the same texture at once answered 500 (rmtree of a folder the
    other purge removed) and 204 twice: now one 204, the rest 404, nothing left behind."""
    from concurrent.futures import ThreadPoolExecutor

    services, client = held
    before = stored_files(services)
    for _ in range(3):
        doomed = client.post("/v1/textures", files={"image": ("doomed.png", brick_png(64))}).json()
        job = client.post(doomed["links"]["volumes"], json={"resolution": 8}).json()
        run_job_attempt(services, job["id"])
        with ThreadPoolExecutor(4) as pool:
            codes = sorted(pool.map(lambda _: client.delete(doomed["links"]["self"]).status_code, range(4)))
        assert codes == [204, 404, 404, 404], codes
    assert stored_files(services) == before


def test_a_prefix_deleted_twice_at_once_is_not_an_error(tmp_path: Path) -> None:
    storage = LocalStorage(tmp_path)
    for k in range(50):
        storage.put_bytes(f"textures/t/refined/{k}/sampler.onnx", b"x")
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda _: storage.delete_prefix("textures/t"), range(4)))
    assert not (tmp_path / "textures" / "t").exists()
