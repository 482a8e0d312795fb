"""Health, readiness, metrics, the list of model versions and the limits in force."""
from __future__ import annotations

import logging

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from .. import db, queue
from ..db import session_scope
from ..deps import ServicesDep
from ..errors import problem_responses
from ..limits import check_free_space
from ..schemas import Health, Limits, ModelList, ModelOut
from ..tables import ModelVersion

router = APIRouter(tags=["system"])
log = logging.getLogger(__name__)


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Liveness: the process answers."""
    return Health(status="ok")


def _readiness(services) -> tuple[bool, dict[str, str]]:  # noqa: ANN001
    checks: dict[str, str] = {}
    for name, check in (("database", lambda: db.ping(services.engine)),
                        ("queue", lambda: queue.ping(services.huey)),
                        ("storage", services.storage.ping),
                        ("disk", lambda: check_free_space(services.settings)),
                        ("model", lambda: _model_ready(services))):
        try:
            check()
            checks[name] = "ok"
        except Exception as exc:  # report every failing dependency, not just the first
            checks[name] = f"error: {type(exc).__name__}: {getattr(exc, 'detail', exc)}"
    return all(v == "ok" for v in checks.values()), checks


def _model_ready(services) -> None:  # noqa: ANN001
    if not services.registry.ready():
        raise RuntimeError("model does not evaluate")


@router.get("/readyz", response_model=Health, responses={503: {"model": Health, "description": "not ready"}})
async def readyz(services: ServicesDep) -> Response:
    """Readiness: model loaded and evaluating, database, queue and storage reachable, and
    ``TEXSPACE_MIN_FREE_BYTES`` free on the local data and storage folders."""
    ok, checks = await run_in_threadpool(_readiness, services)
    body = Health(status="ok" if ok else "unavailable", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ok else 503)


@router.get("/metrics", response_class=Response,
            responses={200: {"description": "Prometheus text format", "content": {"text/plain": {}}}})
def metrics(services: ServicesDep) -> Response:
    return Response(generate_latest(services.metrics.registry), media_type=CONTENT_TYPE_LATEST)


@router.get("/v1/models", response_model=ModelList, responses=problem_responses(503))
def list_models(services: ServicesDep) -> ModelList:
    """Every model version the service knows: loaded ones serve tiles; others were seen before."""
    registry = services.registry
    with session_scope(services.sessions) as session:
        rows = list(session.scalars(select(ModelVersion)))
    items = {r.version: ModelOut(version=r.version, variant=r.variant, loaded=False, default=False,
                                 pixels_per_unit=None, manifest=r.manifest) for r in rows}
    for version, runtime in registry.models.items():
        items[version] = ModelOut(version=version, variant=str(runtime.manifest["variant"]), loaded=True,
                                  default=version == registry.default.version,
                                  pixels_per_unit=runtime.pixels_per_unit, manifest=runtime.manifest)
    return ModelList(items=sorted(items.values(), key=lambda m: (not m.default, not m.loaded, m.version)),
                     default=registry.default.version)


@router.get("/v1/limits", response_model=Limits)
def get_limits(services: ServicesDep) -> Limits:
    """The limits in force: upload and mesh sizes, tile sizes and planes, volume, bake and
    region bounds, a fit's default and longest time budget. The page and the Python client
    read them here instead of copying numbers."""
    return Limits.of(services.settings)
