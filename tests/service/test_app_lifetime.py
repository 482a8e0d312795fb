"""A dropped app frees its services: database engine, queue and model registry (the
encoder's and sampler's ONNX sessions, tens of MB each).

One app lives as long as its process in production, but an embedder or a test suite builds
many. FastAPI keeps every endpoint it has analysed in a module-level cache, so an endpoint
that closes over the app kept every app, and its loaded models, alive: the test suite grew
to 13.8 GB at its peak and then 21 GB once an upload encoded 72 crops (the CI runner has 24).

Logs run as a served process has them (service/logs.py: INFO, one formatting handler): huey's
"Executing <task>" records hold the task, whose class holds the app's job runner, so a
handler that kept records (as pytest's capture does until a test ends) would keep the app;
the formatting one must not. Without this set-up the test passed alone (root at WARNING,
no records made) and failed after any test that ran the CLI (root left at INFO).
"""
from __future__ import annotations

import contextlib
import gc
import io
import logging
import threading
import weakref

from fastapi.testclient import TestClient

from service.context import build_services
from service.logs import ContextFormatter
from service.main import create_app
from service.settings import Settings
from worker.tiles import NATIVE_ZOOM

from tests.service.helpers import tile_url, upload_photo


@contextlib.contextmanager
def served_logging():
    """The root logger as a served process sets it (INFO, one handler formatting each record
    and dropping it), with the test harness's record-keeping handlers set aside meanwhile
    (inside the test: pytest adds its own as each phase starts)."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.setFormatter(ContextFormatter("%(levelname)s %(name)s: %(message)s"))
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    try:
        yield out
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def test_a_dropped_app_frees_its_services_and_models(settings: Settings, photo: bytes) -> None:
    with served_logging() as log:
        _use_and_drop_an_app(settings, photo, log)


def _use_and_drop_an_app(settings: Settings, photo: bytes, log: io.StringIO) -> None:
    services = build_services(settings, immediate=True)
    with TestClient(create_app(services=services)) as client:
        texture = upload_photo(client, photo, name="brick")
        for path in ("/docs", "/openapi.yaml", "/openapi.json", "/readyz", tile_url(texture, NATIVE_ZOOM, 0, 0)):
            assert client.get(path).status_code == 200, path
        job = client.post(texture["links"]["regions"], json={"z": NATIVE_ZOOM, "x0": 0, "y0": 0, "width": 32,
                                                             "height": 32})  # a queued job, run in place
        assert job.status_code == 202, job.text
        assert client.get(job.json()["links"]["self"]).json()["state"] == "succeeded"
    assert services._registry is not None  # the upload loaded the models
    services.engine.dispose()
    for thread in threading.enumerate():  # the app's start-up loader, if it is still finishing
        if thread.name == "warm-up":
            thread.join(timeout=30)
    freed_services, freed_registry = weakref.ref(services), weakref.ref(services._registry)
    del services, client
    gc.collect()
    assert "Executing" in log.getvalue()  # the job's records were made, and formatted
    assert freed_services() is None, "something global still holds the app's services"
    assert freed_registry() is None, "something global still holds the model registry"
