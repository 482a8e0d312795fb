"""Every queue backend carries a job id from the API to a worker (sqlite, redis,
postgres; servers absent -> skipped with the reason), and the service runs its database
on PostgreSQL as on SQLite."""
from __future__ import annotations

import uuid

import pytest
from fastapi.testclient import TestClient

from service.context import build_services
from service.main import create_app
from tests.helpers import brick_png


@pytest.fixture(params=["sqlite", "redis", "postgres"])
def backend_settings(request, settings):
    settings.queue_backend = request.param
    settings.queue_name = f"texspace-test-{uuid.uuid4().hex[:8]}"
    if request.param == "redis":
        settings.queue_url = request.getfixturevalue("redis_url")
    elif request.param == "postgres":
        settings.database_url = request.getfixturevalue("postgres_url")
    return settings


def test_job_travels_through_queue(backend_settings) -> None:
    services = build_services(backend_settings)
    try:
        with TestClient(create_app(services=services)) as client:
            texture = client.post("/v1/textures", files={"image": ("b.png", brick_png())}).json()
            job = client.post(texture["links"]["volumes"], json={"resolution": 8}).json()
            assert job["state"] == "queued"
            assert services.huey.pending_count() == 1
            # what `texspace worker` does with one message
            task = services.huey.dequeue()
            assert task.args == (job["id"],)  # the message carries only the job id
            services.huey.execute(task)
            done = client.get(f"/v1/jobs/{job['id']}").json()
            assert done["state"] == "succeeded" and done["result"]["size"] > 0
            assert client.get("/readyz").json()["checks"]["queue"] == "ok"
    finally:
        services.huey.flush()
        services.engine.dispose()
