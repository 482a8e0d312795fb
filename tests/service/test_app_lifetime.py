"""A dropped app frees its services: database engine, queue and model registry (the
encoder's and sampler's ONNX sessions, tens of MB each).

One app lives as long as its process in production, but an embedder or a test suite builds
many. FastAPI keeps every endpoint it has analysed in a module-level cache, so an endpoint
that closes over the app kept every app, and its loaded models, alive: the test suite grew
to 13.8 GB at its peak and then 21 GB once an upload encoded 72 crops (the CI runner has 24).
"""
from __future__ import annotations

import gc
import threading
import weakref

from fastapi.testclient import TestClient

from service.context import build_services
from service.main import create_app
from service.settings import Settings
from tests.service.helpers import upload_photo


def test_a_dropped_app_frees_its_services_and_models(settings: Settings, photo: bytes) -> None:
    services = build_services(settings, immediate=True)
    with TestClient(create_app(services=services)) as client:
        upload_photo(client, photo, name="brick")
        for path in ("/docs", "/openapi.yaml", "/openapi.json", "/readyz"):  # each endpoint kind once
            assert client.get(path).status_code == 200, path
    assert services._registry is not None  # the upload loaded the models
    services.engine.dispose()
    for thread in threading.enumerate():  # the app's start-up loader, if it is still finishing
        if thread.name == "warm-up":
            thread.join(timeout=30)
    freed_services, freed_registry = weakref.ref(services), weakref.ref(services._registry)
    del services, client
    gc.collect()
    assert freed_services() is None, "something global still holds the app's services"
    assert freed_registry() is None, "something global still holds the model registry"
