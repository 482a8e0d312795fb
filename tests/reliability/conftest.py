"""Fixtures for the reliability tests: the real app in-process (SQLite, local storage in
a temporary folder, tasks run synchronously or held in memory); plain helpers (settings,
storage snapshots) are in helpers.py."""
from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from service.context import Services, build_services
from service.main import create_app
from tests.helpers import brick_png, fresh_postgres_database
from tests.reliability.helpers import database_settings, make_settings


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def database_url(request) -> Iterator[str | None]:
    """None (the embedded SQLite default), or a fresh PostgreSQL database dropped afterwards
    (skipped, saying why, where no server answers): hostile cases run on both."""
    if request.param == "sqlite":
        yield None
        return
    with fresh_postgres_database() as url:
        yield url


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
