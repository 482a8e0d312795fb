"""Service unit-test fixtures: the real app with an in-memory queue run synchronously
(huey immediate mode), SQLite and local storage in a temporary folder."""
from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from service.context import Services, build_services
from service.main import create_app
from service.settings import Settings
from tests.conftest import fresh_postgres_database


def brick_png(size: int = 96, rgba: bool = False) -> bytes:
    """A real texture photo (scikit-image's CC0 brick wall), cropped small for speed."""
    from skimage import data

    grey = data.brick()[:size, :size]
    rgb = np.stack([grey, (grey * 0.8).astype(np.uint8), (grey * 0.6).astype(np.uint8)], axis=-1)
    if rgba:
        rgb = np.concatenate([rgb, np.full(grey.shape + (1,), 200, np.uint8)], axis=-1)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, "PNG")
    return buf.getvalue()


def shaded_png() -> bytes:
    """The brick photo under a light falling off to the right (0.4x at the far side)."""
    from worker.colour import linear_to_srgb8, srgb_to_linear

    rgb = np.asarray(Image.open(io.BytesIO(brick_png(128))).convert("RGB"), np.float32) / 255
    shade = np.linspace(1.0, 0.4, rgb.shape[1], dtype=np.float32)[None, :, None]
    buf = io.BytesIO()
    Image.fromarray(linear_to_srgb8(srgb_to_linear(rgb) * shade)).save(buf, "PNG")
    return buf.getvalue()


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


def upload_photo(client: TestClient, photo: bytes, **form: str) -> dict:
    """POST a PNG to /v1/textures (``form``: e.g. name=...); the 201 answer's texture."""
    res = client.post("/v1/textures", files={"image": ("brick.png", photo, "image/png")}, data=form)
    assert res.status_code == 201, res.text
    return res.json()


def tile_url(texture: dict, z: int, x: int, y: int, fmt: str = "png") -> str:
    """The API path of tile (z, x, y) of an uploaded texture."""
    return f"/v1/textures/{texture['id']}/tiles/{z}/{x}/{y}.{fmt}"


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
