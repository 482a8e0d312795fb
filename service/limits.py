"""Limits checked at the door, before anything is stored or queued.

* ``check_mesh``: check an uploaded mesh's header, then parse and validate it, at
  submission time, so a bad mesh is a 422 / 413 problem at once (and nothing is stored)
  instead of a failed job later.
* ``check_queue_room``: back-pressure. When ``max_queued_jobs`` jobs already wait, new
  submissions get ``503`` with ``Retry-After`` instead of growing the queue without bound.

Byte limits on request bodies are enforced while the body streams in
(``service/middleware.py``); image pixel limits are read from the header before decoding
(``worker/images.py: read_image``).
"""
from __future__ import annotations

from sqlalchemy import func, select

from worker.bake import BakeLimits, load_mesh

from .container import Services
from .db import session_scope
from .errors import Problem
from .settings import Settings
from .tables import Job


def bake_limits(settings: Settings) -> BakeLimits:
    """The mesh limits of the settings, in the worker's terms."""
    return BakeLimits(max_faces=settings.max_mesh_faces, max_vertices=settings.max_mesh_vertices,
                      max_nodes=settings.max_mesh_nodes, max_depth=settings.max_mesh_depth,
                      max_resolution=settings.max_bake_resolution)


def check_mesh(settings: Settings, data: bytes, filename: str) -> None:
    """Raise InvalidMesh / LimitExceeded if the mesh cannot be baked (parse + validate only;
    the UV atlas is made later by the job). The file's header is checked first
    (``worker/mesh_size.py``: faces, vertices, a GLB's nodes and depth, in milliseconds), so
    the parse that follows is bounded by the limits: ~1 s for 200k faces or 4,096 nodes."""
    load_mesh(data, filename, bake_limits(settings))


def queued_jobs(services: Services) -> int:
    with session_scope(services.sessions) as session:
        return int(session.scalar(select(func.count()).select_from(Job).where(Job.state == "queued")))


def check_queue_room(services: Services) -> None:
    """503 + Retry-After when the queue already holds ``max_queued_jobs`` jobs."""
    settings = services.settings
    waiting = queued_jobs(services)
    if waiting >= settings.max_queued_jobs:
        retry = settings.queue_full_retry_after_seconds
        raise Problem(503, f"{waiting} jobs are already queued (limit {settings.max_queued_jobs}); "
                           f"retry in {retry} s", slug="queue-full", title="The job queue is full",
                      headers={"Retry-After": str(retry)})
