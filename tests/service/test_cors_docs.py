"""Integration with other tools: CORS (TEXSPACE_CORS_ORIGINS, off by default), /docs from
bundled Swagger UI files (no CDN) and the contract served as /openapi.yaml."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from fastapi.testclient import TestClient

from service.context import build_services
from service.main import STATIC_DIR, create_app
from service.settings import Settings

ORIGIN = "http://maps.example:5173"
CONTRACT = Path(__file__).resolve().parents[2] / "openapi.yaml"


@pytest.fixture
def cors_client(settings: Settings):
    services = build_services(settings.model_copy(update={"cors_origins": [ORIGIN]}), immediate=True)
    with TestClient(create_app(services=services)) as client:
        yield client
    services.engine.dispose()


def test_cors_is_off_by_default(client: TestClient, texture: dict) -> None:
    assert Settings().cors_origins == []
    res = client.get(f"/v1/textures/{texture['id']}", headers={"Origin": ORIGIN})
    assert res.status_code == 200 and "access-control-allow-origin" not in res.headers
    pre = client.options(f"/v1/textures/{texture['id']}/volumes",
                         headers={"Origin": ORIGIN, "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in pre.headers


def test_preflight_then_job_submission_from_another_origin(cors_client: TestClient, photo: bytes) -> None:
    texture = cors_client.post("/v1/textures", files={"image": ("b.png", photo, "image/png")}).json()
    pre = cors_client.options(f"/v1/textures/{texture['id']}/volumes", headers={
        "Origin": ORIGIN, "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "content-type, idempotency-key, x-api-key"})
    assert pre.status_code == 200, pre.text
    assert pre.headers["access-control-allow-origin"] == ORIGIN
    assert "POST" in pre.headers["access-control-allow-methods"]
    allowed = pre.headers["access-control-allow-headers"].lower()
    assert all(h in allowed for h in ("content-type", "idempotency-key", "x-api-key"))
    job = cors_client.post(f"/v1/textures/{texture['id']}/volumes", json={"resolution": 4},
                           headers={"Origin": ORIGIN, "Idempotency-Key": "cors-1"})
    assert job.status_code == 202
    assert job.headers["access-control-allow-origin"] == ORIGIN
    assert "location" in job.headers["access-control-expose-headers"].lower()


def test_simple_request_tiles_and_errors_carry_cors_headers(cors_client: TestClient, photo: bytes) -> None:
    texture = cors_client.post("/v1/textures", files={"image": ("b.png", photo, "image/png")}).json()
    tile = cors_client.get(f"/v1/textures/{texture['id']}/tiles/6/0/0.png?size=64", headers={"Origin": ORIGIN})
    assert tile.status_code == 200 and tile.headers["access-control-allow-origin"] == ORIGIN
    assert "etag" in tile.headers["access-control-expose-headers"].lower()
    missing = cors_client.get("/v1/textures/nope", headers={"Origin": ORIGIN})
    assert missing.status_code == 404 and missing.headers["access-control-allow-origin"] == ORIGIN
    other = cors_client.get(f"/v1/textures/{texture['id']}", headers={"Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    refused = cors_client.options("/v1/textures", headers={"Origin": "http://evil.example",
                                                           "Access-Control-Request-Method": "POST"})
    assert refused.status_code == 400


@pytest.mark.parametrize("value", ["http://a.example/path", "a.example", "ftp://a.example"])
def test_cors_origins_must_be_origins(value: str, monkeypatch) -> None:
    monkeypatch.setenv("TEXSPACE_CORS_ORIGINS", value)
    with pytest.raises(ValueError, match="not an origin"):
        Settings()


def test_cors_origins_from_the_environment(monkeypatch) -> None:
    monkeypatch.setenv("TEXSPACE_CORS_ORIGINS", "https://a.example, http://b.example:8080/")
    assert Settings().cors_origins == ["https://a.example", "http://b.example:8080"]
    monkeypatch.setenv("TEXSPACE_CORS_ORIGINS", "*")
    assert Settings().cors_origins == ["*"]


def test_docs_use_only_bundled_assets(client: TestClient) -> None:
    html = client.get("/docs").text
    urls = re.findall(r"""(?:src|href)=["']([^"']+)["']|url:\s*["']([^"']+)["']""", html)
    urls = [a or b for a, b in urls]
    assert urls and not [u for u in urls if "://" in u or u.startswith("//")], urls
    for url in urls:
        res = client.get(url)
        assert res.status_code == 200, url
    assert (STATIC_DIR / "vendor" / "swagger-ui-dist" / "LICENSE").is_file()
    assert client.get("/redoc").status_code == 404  # ReDoc would load from a CDN
    for url in ("/docs", "/openapi.yaml"):
        head = client.head(url)
        assert head.status_code == 200 and head.content == b"", url


def test_openapi_yaml_is_the_contract(client: TestClient) -> None:
    res = client.get("/openapi.yaml")
    assert res.status_code == 200 and res.headers["content-type"].startswith("application/yaml")
    assert res.text == CONTRACT.read_text(encoding="utf-8")
    assert yaml.safe_load(res.text)["openapi"].startswith("3.1")
