"""The FastAPI app factory: it only wires settings, services, middleware and routes."""
from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI

from worker import images

from . import __version__, auth
from .context import Services, build_services
from .errors import PROBLEM_MEDIA_TYPE, install_error_handlers
from .logs import setup_logging
from .middleware import RequestContextMiddleware
from .routes import jobs, system, textures, tiles
from .settings import Settings
from .site import SiteFiles

log = logging.getLogger(__name__)
STATIC_DIR = Path(__file__).resolve().parent / "static"


def create_app(settings: Settings | None = None, *, services: Services | None = None) -> FastAPI:
    """Build the app. ``services`` may be given (tests pass in-memory queues)."""
    settings = settings or (services.settings if services else Settings())
    services = services or build_services(settings)
    app = FastAPI(title="texspace", version=__version__, lifespan=_warm_up,
                  description="Neural 3D texture space: encode a photo, then synthesise infinite tiles, "
                              "volumes and UV-baked meshes from its 8-number code.")
    app.state.services = services
    services.metrics.watch(services)
    images.set_decode_budget(settings.decode_budget_pixels)  # uploads: bounded decoded pixels (docs/OPERATIONS.md)
    install_error_handlers(app)
    for module in (system, textures, tiles, jobs):
        app.include_router(module.router, **({} if module is system else auth.router_options()))
    app.add_middleware(RequestContextMiddleware, metrics=services.metrics,
                       max_body_bytes=max(settings.max_upload_bytes, settings.max_mesh_bytes) + (1 << 20))
    app.openapi = lambda: _openapi(app)
    if (STATIC_DIR / "index.html").is_file():  # the web page (its own engineer's part)
        app.mount("/", SiteFiles(directory=STATIC_DIR, html=True, routes=list(app.router.routes)), name="static")
    return app


@asynccontextmanager
async def _warm_up(app: FastAPI) -> AsyncIterator[None]:
    """Load the models in the background at start, so the first request does not pay
    for it; /readyz says 503 until they answer."""

    def load() -> None:
        try:
            app.state.services.registry
        except Exception:  # reported by /readyz and by each request that needs a model
            log.exception("model registry could not be loaded")

    threading.Thread(target=load, name="warm-up", daemon=True).start()
    yield


def _openapi(app: FastAPI) -> dict:
    """FastAPI's schema with error responses declared as application/problem+json."""
    if app.openapi_schema:
        return app.openapi_schema
    from fastapi.openapi.utils import get_openapi

    schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            for code, response in operation.get("responses", {}).items():
                content = response.get("content", {})
                if code[0] in "45" and "application/json" in content:
                    content[PROBLEM_MEDIA_TYPE] = content.pop("application/json")
    app.openapi_schema = schema
    return schema


def app_from_env() -> FastAPI:
    """uvicorn factory (``uvicorn --factory service.main:app_from_env``)."""
    settings = Settings()
    setup_logging(settings.log_level, settings.log_json)
    return create_app(settings)
