"""Tenants: with API keys on, textures and jobs belong to the key that made them; other
keys get 404 (never 403: ids do not leak); keys are stored hashed; per-key rate limit;
``texspace keys create|list|revoke``."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from service import auth
from service.cli import main as cli_main
from service.context import Services, build_services
from service.main import create_app
from service.tables import ApiKey, Job, Texture
from tests.helpers import brick_png
from tests.reliability.helpers import PROBLEM, database_settings, make_settings


@pytest.fixture(scope="module")
def tenants(tmp_path_factory, database_url) -> Iterator[tuple[Services, TestClient, dict, dict]]:
    """Two keys on the embedded SQLite database, then on PostgreSQL (conftest: database_url)."""
    settings = make_settings(tmp_path_factory.mktemp("tenants"), api_keys_enabled=True,
                             api_key_pepper="test-pepper", rate_limit_per_minute=6000, rate_limit_burst=1000,
                             **database_settings(database_url))
    services = build_services(settings, immediate=True)
    _, key_a = auth.create_key(services, "alice")
    _, key_b = auth.create_key(services, "bob")
    with TestClient(create_app(services=services)) as client:
        yield services, client, {"X-API-Key": key_a}, {"X-API-Key": key_b}
    services.engine.dispose()


@pytest.fixture(scope="module")
def owned(tenants) -> tuple[dict, dict]:
    """A texture and a finished volume job of alice."""
    _, client, alice, _ = tenants
    texture = client.post("/v1/textures", files={"image": ("a.png", brick_png())}, headers=alice).json()
    job = client.post(texture["links"]["volumes"], json={"resolution": 8}, headers=alice).json()
    assert job["state"] == "succeeded", job
    return texture, job


def test_no_key_or_a_wrong_key_is_401(tenants) -> None:
    _, client, _, _ = tenants
    for headers in ({}, {"X-API-Key": "tsk_not-a-key"}):
        res = client.get("/v1/textures", headers=headers)
        assert res.status_code == 401 and res.headers["content-type"] == PROBLEM
        assert "X-API-Key" in res.headers["www-authenticate"] and res.json()["detail"]
    assert client.get("/healthz").status_code == 200  # system endpoints stay open


def test_owner_sees_everything_of_its_own(tenants, owned) -> None:
    _, client, alice, _ = tenants
    texture, job = owned
    assert client.get(texture["links"]["self"], headers=alice).status_code == 200
    tile = client.get(f"/v1/textures/{texture['id']}/tiles/6/0/0.png", params={"size": 64}, headers=alice)
    assert tile.status_code == 200
    assert tile.headers["cache-control"].startswith("private")  # no shared cache may hand it to others
    assert [t["id"] for t in client.get("/v1/textures", headers=alice).json()["items"]] == [texture["id"]]
    assert client.get(job["links"]["result"], headers=alice).status_code == 200


@pytest.mark.parametrize("method, url, kwargs", [
    ("GET", "{texture}", {}),
    ("PATCH", "{texture}", {"json": {"name": "mine now"}}),
    ("DELETE", "{texture}", {}),
    ("GET", "{texture}/exemplar", {}),
    ("GET", "{texture}/tiles/6/0/0.png", {}),
    ("GET", "{texture}/tilejson.json", {}),
    ("POST", "{texture}/volumes", {"json": {"resolution": 8}}),
    ("POST", "{texture}/regions", {"json": {"z": 6, "x0": 0, "y0": 0, "width": 8, "height": 8}}),
    ("GET", "{job}", {}),
    ("POST", "{job}/cancel", {}),
    ("GET", "{job}/result", {}),
    ("GET", "{job}/events", {}),
])
def test_another_key_gets_404(tenants, owned, method: str, url: str, kwargs: dict) -> None:
    services, client, alice, bob = tenants
    texture, job = owned
    url = url.format(texture=texture["links"]["self"], job=job["links"]["self"])
    res = client.request(method, url, headers=bob, **kwargs)
    assert res.status_code == 404 and res.headers["content-type"] == PROBLEM, res.text
    # and nothing changed for the owner
    assert client.get(texture["links"]["self"], headers=alice).json()["name"] == texture["name"]
    assert client.get(job["links"]["self"], headers=alice).json()["state"] == "succeeded"


def test_lists_and_interpolation_are_per_tenant(tenants, owned) -> None:
    _, client, alice, bob = tenants
    texture, job = owned
    assert client.get("/v1/textures", headers=bob).json()["items"] == []
    assert client.get("/v1/jobs", headers=bob).json()["items"] == []
    assert client.get("/v1/jobs", params={"texture_id": texture["id"]}, headers=bob).json()["items"] == []
    theirs = client.post("/v1/textures", files={"image": ("b.png", brick_png(64))}, headers=bob).json()
    res = client.post("/v1/textures/interpolate", json={"a": theirs["id"], "b": texture["id"], "t": 0.5},
                      headers=bob)
    assert res.status_code == 404
    mixed = client.post("/v1/textures/interpolate", json={"a": theirs["id"], "b": theirs["id"], "t": 0.5},
                        headers=bob).json()
    assert {t["id"] for t in client.get("/v1/textures", headers=bob).json()["items"]} == {theirs["id"], mixed["id"]}


def test_same_idempotency_key_in_two_tenants_makes_two_jobs(tenants) -> None:
    _, client, alice, bob = tenants
    ids = []
    for headers in (alice, bob):
        texture = client.post("/v1/textures", files={"image": ("x.png", brick_png(64))}, headers=headers).json()
        first = client.post(texture["links"]["volumes"], json={"resolution": 8},
                            headers=headers | {"Idempotency-Key": "shared-key"})
        again = client.post(texture["links"]["volumes"], json={"resolution": 8},
                            headers=headers | {"Idempotency-Key": "shared-key"})
        assert first.status_code == again.status_code == 202 and first.json()["id"] == again.json()["id"]
        ids.append(first.json()["id"])
    assert ids[0] != ids[1]


def test_keys_are_stored_hashed(tenants) -> None:
    services, _, alice, _ = tenants
    key = alice["X-API-Key"]
    with services.sessions() as session:
        hashes = list(session.scalars(select(ApiKey.key_hash)))
        owners = set(session.scalars(select(Texture.owner_id))) | set(session.scalars(select(Job.owner_id)))
    assert auth.hash_key("test-pepper", key) in hashes and key not in hashes
    assert auth.hash_key("another-pepper", key) not in hashes  # the pepper matters
    assert None not in owners
    db_bytes = b"".join(p.read_bytes() for p in services.settings.data_dir.glob("texspace.db*"))
    assert key.encode() not in db_bytes


def test_rate_limit_per_key(tmp_path: Path) -> None:
    services = build_services(make_settings(tmp_path, api_keys_enabled=True, rate_limit_per_minute=6,
                                            rate_limit_burst=3), immediate=True)
    _, key_a = auth.create_key(services, "a")
    _, key_b = auth.create_key(services, "b")
    with TestClient(create_app(services=services)) as client:
        codes = [client.get("/v1/textures", headers={"X-API-Key": key_a}).status_code for _ in range(4)]
        assert codes == [200, 200, 200, 429]
        res = client.get("/v1/textures", headers={"X-API-Key": key_a})
        assert res.status_code == 429 and res.headers["content-type"] == PROBLEM
        assert 1 <= int(res.headers["retry-after"]) <= 10
        assert client.get("/v1/textures", headers={"X-API-Key": key_b}).status_code == 200
    services.engine.dispose()


def test_token_bucket_refills() -> None:
    limiter = auth.RateLimiter(per_minute=60, burst=2)
    assert [limiter.take("k", now=0.0) for _ in range(2)] == [0.0, 0.0]
    assert limiter.take("k", now=0.0) == pytest.approx(1.0)
    assert limiter.take("k", now=1.01) == 0.0


def test_keys_cli_create_list_revoke(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TEXSPACE_API_KEYS_ENABLED", "true")
    cli_main(["keys", "create", "carol", "--note", "ci"])
    out = capsys.readouterr().out
    key_id = out.split("id:")[1].split()[0]
    key = out.split("key:")[1].split()[0]
    assert key.startswith(auth.KEY_PREFIX)
    cli_main(["keys", "list"])
    listed = capsys.readouterr().out
    assert key_id in listed and "active" in listed and "carol" in listed and key not in listed

    services = build_services(make_settings(tmp_path, api_keys_enabled=True), immediate=True)
    with TestClient(create_app(services=services)) as client:
        assert client.get("/v1/textures", headers={"X-API-Key": key}).status_code == 200
        cli_main(["keys", "revoke", key_id])
        assert "revoked" in capsys.readouterr().out
        auth._state(services)[0].clear()  # another process revoked it; skip the 5 s cache
        assert client.get("/v1/textures", headers={"X-API-Key": key}).status_code == 401
    with pytest.raises(SystemExit):
        cli_main(["keys", "revoke", key_id])
    services.engine.dispose()
