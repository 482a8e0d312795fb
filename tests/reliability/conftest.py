"""Fixtures for the reliability tests: the real app in-process (SQLite, local storage in
a temporary folder, tasks run synchronously or held in memory), and storage snapshots."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.context import Services, build_services
from service.main import create_app
from service.settings import Settings
from service.tables import Job, Texture
from tests.conftest import fresh_postgres_database
from tests.service.conftest import brick_png

BAD = Path(__file__).resolve().parents[1] / "data" / "bad"
PROBLEM = "application/problem+json"


def make_settings(root: Path, **overrides) -> Settings:
    values = dict(data_dir=root / "data", log_json=False, heartbeat_seconds=0.2, max_volume_resolution=32,
                  max_mesh_faces=1000, max_mesh_vertices=1000, auto_fit=False)
    return Settings(**(values | overrides))


def stored_files(services: Services) -> list[str]:
    """Every file in local storage (relative keys, sorted), temporary files included."""
    root = services.storage.root
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def row_counts(services: Services) -> tuple[int, int]:
    with services.sessions() as session:
        return (session.scalar(select(func.count()).select_from(Texture)),
                session.scalar(select(func.count()).select_from(Job)))


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def database_url(request) -> Iterator[str | None]:
    """None (the embedded SQLite default), or a fresh PostgreSQL database dropped afterwards
    (skipped, saying why, where no server answers): hostile cases run on both."""
    if request.param == "sqlite":
        yield None
        return
    with fresh_postgres_database() as url:
        yield url


def database_settings(database_url: str | None) -> dict:
    """Settings overrides for ``database_url`` (none for the SQLite default)."""
    return {"database_url": database_url} if database_url else {}


@pytest.fixture(scope="module")
def module_services(database_url, tmp_path_factory) -> Iterator[Services]:
    services = build_services(make_settings(tmp_path_factory.mktemp("rel"), **database_settings(database_url)),
                              immediate=True)
    yield services
    services.engine.dispose()


@pytest.fixture(scope="module")
def client(module_services: Services) -> Iterator[TestClient]:
    with TestClient(create_app(services=module_services)) as client:
        yield client


@pytest.fixture(scope="module")
def texture(client: TestClient) -> dict:
    res = client.post("/v1/textures", files={"image": ("brick.png", brick_png(), "image/png")})
    assert res.status_code == 201, res.text
    return res.json()
