"""Service unit-test fixtures: the real app with an in-memory queue run synchronously
(huey immediate mode), SQLite and local storage in a temporary folder."""
from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.context import Services, build_services
from service.main import create_app
from service.settings import Settings
from tests.helpers import brick_png, fresh_postgres_database
from tests.service.helpers import MODEL_DIR, fake_fit_module, upload_photo


@pytest.fixture(scope="session")
def photo() -> bytes:
    return brick_png()


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request) -> Iterator[dict]:
    """Settings for the embedded SQLite default, or for a fresh PostgreSQL database (a test
    that takes it runs on both; ``indirect`` parametrisation picks one)."""
    if request.param == "sqlite":
        yield {}
        return
    with fresh_postgres_database() as url:
        yield {"database_url": url}


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    # auto_fit off: an upload would otherwise run a real fit (torch, a minute) in immediate mode
    return Settings(data_dir=tmp_path / "data", log_json=False, heartbeat_seconds=0.2,
                    max_volume_resolution=32, auto_fit=False)


@pytest.fixture
def services(settings: Settings) -> Iterator[Services]:
    services = build_services(settings, immediate=True)
    yield services
    services.engine.dispose()


@pytest.fixture
def client(services: Services) -> Iterator[TestClient]:
    with TestClient(create_app(services=services)) as client:
        yield client


@pytest.fixture
def texture(client: TestClient, photo: bytes) -> dict:
    return upload_photo(client, photo, name="brick")


@pytest.fixture
def cli_env(tmp_path: Path, monkeypatch) -> Path:
    """For the offline CLI: a working folder with brick.png, its own data dir, no other
    TEXSPACE_* variable, and no refinement fits behind uploads."""
    for key in list(os.environ):
        if key.startswith("TEXSPACE_"):
            monkeypatch.delenv(key)
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TEXSPACE_AUTO_FIT", "false")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "brick.png").write_bytes(brick_png())
    return tmp_path


@pytest.fixture
def fit_calls(monkeypatch) -> list[dict]:
    """model.fit is the stand-in (``fake_fit_module``: no torch, a second), torch counts as
    installed; the calls it gets, in order. A fit publishes no interim unless the test sets
    ``sys.modules["model.fit"].during_interim`` (or takes ``fits_publish_interims``)."""
    calls: list[dict] = []
    monkeypatch.setitem(sys.modules, "model.fit", fake_fit_module(calls))
    monkeypatch.setattr("service.routes.jobs.torch_available", lambda: True)
    monkeypatch.setattr("service.job_kinds.torch_available", lambda: True)
    return calls


@pytest.fixture
def fits_publish_interims(fit_calls) -> None:
    """Every stand-in fit given an interim hook publishes an interim and goes on."""
    sys.modules["model.fit"].during_interim = lambda: None


@pytest.fixture
def refining(settings, tmp_path, fit_calls):
    """(client, services) with auto-fit on, a model that ships a space.pt, and a queue
    that keeps its messages until the test runs them (``run_fit_lane``)."""
    if not all((MODEL_DIR / f).is_file() for f in ("manifest.json", "encoder.onnx", "sampler.onnx")):
        pytest.skip(f"no model export in {MODEL_DIR}")
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    for name in ("manifest.json", "encoder.onnx", "sampler.onnx"):
        (model_dir / name).write_bytes((MODEL_DIR / name).read_bytes())
    (model_dir / "space.pt").write_bytes(b"stand-in: the fake fit never reads it")
    settings.model_dirs = [model_dir]
    settings.auto_fit = True
    settings.queue_backend = "memory"
    services = build_services(settings)
    with TestClient(create_app(services=services)) as client:
        yield client, services
    services.engine.dispose()
