"""The FastAPI app factory: it only wires settings, services, middleware and routes."""
from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response

from worker import images

from . import __version__, auth
from .context import Services, build_services
from .errors import PROBLEM_MEDIA_TYPE, install_error_handlers
from .logs import setup_logging
from .middleware import RequestContextMiddleware
from .recolour import warn_if_stale
from .reencode import warn_if_stale_choice
from .routes import jobs, system, textures, tiles
from .settings import Settings
from .site import SiteFiles

log = logging.getLogger(__name__)
STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Swagger UI for /docs, bundled like the page's libraries (web/copy-vendor.mjs): no CDN
SWAGGER_UI = "/vendor/swagger-ui-dist"
#: the hand-written contract (a source checkout); a wheel install serves the app's own schema
CONTRACT = Path(__file__).resolve().parent.parent / "openapi.yaml"
#: what a page on another origin may send and read (TEXSPACE_CORS_ORIGINS)
CORS_REQUEST_HEADERS = ["Content-Type", "X-API-Key", "Idempotency-Key", "If-None-Match", "Last-Event-ID",
                        "X-Request-ID"]
CORS_RESPONSE_HEADERS = ["ETag", "Location", "Retry-After", "X-Request-ID", "Content-Disposition",
                         "Idempotent-Replayed", "WWW-Authenticate", "X-Texspace-Tile"]


def create_app(settings: Settings | None = None, *, services: Services | None = None) -> FastAPI:
    """Build the app. ``services`` may be given (tests pass in-memory queues)."""
    settings = settings or (services.settings if services else Settings())
    services = services or build_services(settings)
    app = FastAPI(title="texspace", version=__version__, lifespan=_warm_up, docs_url=None, redoc_url=None,
                  description="Neural 3D texture space: encode a photo, then synthesise infinite tiles, "
                              "volumes and UV-baked meshes from its 8-number code.")
    app.state.services = services
    services.metrics.watch(services)
    # uploads: bounded decoded pixels, a bounded wait for room (docs/OPERATIONS.md)
    images.set_decode_budget(settings.decode_budget_pixels, settings.decode_wait_seconds,
                             settings.decode_max_waiting)
    install_error_handlers(app)
    for module in (system, textures, tiles, jobs):
        app.include_router(module.router, **({} if module is system else auth.router_options()))
    app.add_middleware(RequestContextMiddleware, metrics=services.metrics,
                       max_body_bytes=max(settings.max_upload_bytes, settings.max_mesh_bytes) + (1 << 20))
    if settings.cors_origins:  # outermost: preflights are answered before auth, errors carry the headers
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "HEAD", "POST", "PATCH", "DELETE"],
                           allow_headers=CORS_REQUEST_HEADERS, expose_headers=CORS_RESPONSE_HEADERS, max_age=600)
    app.openapi = lambda: _openapi(app)
    _add_docs(app)
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
            return
        try:
            warn_if_stale(app.state.services)
            warn_if_stale_choice(app.state.services)
        except Exception:  # a hint for operators: never in the way of serving
            log.exception("could not count textures made by an older recipe")

    threading.Thread(target=load, name="warm-up", daemon=True).start()
    yield


def _add_docs(app: FastAPI) -> None:
    """/docs (Swagger UI from the bundled files, so it renders offline) and /openapi.yaml."""

    # the endpoints read the app from the request, never from this closure: FastAPI keeps every
    # endpoint it has analysed in a module-level cache, which would then keep the app alive
    @app.get("/docs", include_in_schema=False, response_class=HTMLResponse)
    def docs(request: Request) -> HTMLResponse:
        root, api = request.scope.get("root_path", "").rstrip("/"), request.app
        return get_swagger_ui_html(openapi_url=f"{root}{api.openapi_url}", title=f"{api.title} - API docs",
                                   swagger_js_url=f"{root}{SWAGGER_UI}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{root}{SWAGGER_UI}/swagger-ui.css",
                                   swagger_favicon_url=f"{root}{SWAGGER_UI}/favicon-32x32.png")

    @app.get("/openapi.yaml", include_in_schema=False)
    def openapi_yaml(request: Request) -> Response:
        if CONTRACT.is_file():
            text = CONTRACT.read_text(encoding="utf-8")
        else:
            import yaml

            text = yaml.safe_dump(request.app.openapi(), sort_keys=False, allow_unicode=True)
        return Response(text, media_type="application/yaml")


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
