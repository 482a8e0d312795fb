"""Limits checked at the door, before anything is stored or queued.

* ``check_mesh``: parse and validate an uploaded mesh at submission time, so a bad mesh
  is a 422 / 413 problem at once (and nothing is stored) instead of a failed job later.
* ``check_queue_room``: back-pressure. When ``max_queued_jobs`` jobs already wait, new
  submissions get ``503`` with ``Retry-After`` instead of growing the queue without bound.
* ``check_free_space``: the local folders the service writes to have ``min_free_bytes``
  free (``/readyz`` asks, so a load balancer stops sending work before writes fail).

Byte limits on request bodies are enforced while the body streams in
(``service/middleware.py``); image pixel limits are read from the header before decoding
(``worker/images.py: read_image``).
"""
from __future__ import annotations

import shutil

from sqlalchemy import func, select

from worker.bake import BakeLimits, load_mesh
from worker.errors import InsufficientStorage

from .container import Services
from .db import session_scope
from .errors import Problem
from .settings import Settings
from .tables import Job


def bake_limits(settings: Settings) -> BakeLimits:
    """The mesh limits of the settings, in the worker's terms."""
    return BakeLimits(max_faces=settings.max_mesh_faces, max_vertices=settings.max_mesh_vertices,
                      max_resolution=settings.max_bake_resolution)


def check_mesh(settings: Settings, data: bytes, filename: str) -> None:
    """Raise InvalidMesh / LimitExceeded if the mesh cannot be baked (parse + validate only;
    the UV atlas is made later by the job). Cost: one trimesh parse, ~1 s for 200k faces."""
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


def check_free_space(settings: Settings) -> None:
    """Raise InsufficientStorage when the volume of the data folder (SQLite database and
    queue, job scratch, caches) or of the local storage folder has less than
    ``min_free_bytes`` free (0: no check)."""
    minimum = settings.min_free_bytes
    if not minimum:
        return
    folders = {"data folder": settings.data_dir}
    if settings.storage_backend == "local":
        folders["storage folder"] = settings.resolved_storage_dir
    for what, folder in folders.items():
        free = shutil.disk_usage(folder).free
        if free < minimum:
            raise InsufficientStorage(f"the {what}'s volume has {free / 2**20:.1f} MiB free, under "
                                      f"TEXSPACE_MIN_FREE_BYTES ({minimum / 2**20:.1f} MiB)")
