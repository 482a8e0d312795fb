"""Limits checked at the door, before anything is stored or queued.

* ``check_mesh``: parse and validate an uploaded mesh at submission time, so a bad mesh
  is a 422 / 413 problem at once (and nothing is stored) instead of a failed job later.
* ``check_queue_room``: back-pressure. When ``max_queued_jobs`` jobs (``max_queued_fits``
  fits: they have a lane and a limit of their own) already wait, new submissions get ``503``
  with ``Retry-After`` instead of growing the queue without bound; a tenant holding its share
  of either (``tenant_queue_share``) gets ``429``.
* ``check_free_space``: the local folders the service writes to have ``min_free_bytes``
  free (``/readyz`` asks, so a load balancer stops sending work before writes fail).

Byte limits on request bodies are enforced while the body streams in
(``service/middleware.py``); image pixel limits are read from the header before decoding
(``worker/images.py: read_image``).
"""
from __future__ import annotations

import math
import shutil

from sqlalchemy import func, select

from worker.bake import BakeLimits, load_mesh
from worker.errors import InsufficientStorage

from .auth import current_owner
from .container import Services
from .db import session_scope
from .errors import Problem
from .settings import Settings
from .tables import Job
from .vocabulary import JobKind, JobState


def bake_limits(settings: Settings) -> BakeLimits:
    """The mesh limits of the settings, in the worker's terms."""
    return BakeLimits(max_faces=settings.max_mesh_faces, max_vertices=settings.max_mesh_vertices,
                      max_resolution=settings.max_bake_resolution)


def check_mesh(settings: Settings, data: bytes, filename: str) -> None:
    """Raise InvalidMesh / LimitExceeded if the mesh cannot be baked (parse + validate only;
    the UV atlas is made later by the job). Cost: one trimesh parse, ~1 s for 200k faces."""
    load_mesh(data, filename, bake_limits(settings))


def queued_jobs(services: Services, *, fits: bool = False, owner: str | None = None,
                tenant: bool = False) -> int:
    """Queued jobs of the fit lane (``fits``) or of the other one; of ``owner`` only with ``tenant``."""
    where = [Job.state == JobState.QUEUED, (Job.kind == JobKind.FIT) if fits else (Job.kind != JobKind.FIT)]
    if tenant:
        where.append(Job.owner_id.is_(None) if owner is None else Job.owner_id == owner)
    with session_scope(services.sessions) as session:
        return int(session.scalar(select(func.count()).select_from(Job).where(*where)))


def tenant_share(settings: Settings, limit: int) -> int:
    """The queued jobs one tenant may hold of a queue of ``limit``: ``tenant_queue_share`` of it."""
    return max(1, math.floor(limit * settings.tenant_queue_share))


def check_queue_room(services: Services, kind: str) -> None:
    """Back-pressure on the lane ``kind`` runs in: 503 + Retry-After when it already holds its
    limit of queued jobs (``max_queued_fits`` for fits, ``max_queued_jobs`` for the rest, so a
    burst of uploads' refinements never refuses another tenant's volume), 429 + Retry-After when
    the caller's tenant (``auth.current_owner``, with API keys on) holds its share of that
    limit, so one tenant's burst leaves room for the others."""
    settings = services.settings
    fits = kind == JobKind.FIT
    limit = settings.max_queued_fits if fits else settings.max_queued_jobs
    what = "fits" if fits else "jobs"
    retry = str(settings.queue_full_retry_after_seconds)
    waiting = queued_jobs(services, fits=fits)
    if waiting >= limit:
        raise Problem(503, f"{waiting} {what} are already queued (limit {limit}); retry in {retry} s",
                      slug="queue-full", title="The job queue is full", headers={"Retry-After": retry})
    # without API keys every caller is the one anonymous tenant: the whole queue is its share
    share = tenant_share(settings, limit) if settings.api_keys_enabled else limit
    mine = queued_jobs(services, fits=fits, owner=current_owner(), tenant=True) if share < limit else 0
    if mine >= share:
        raise Problem(429, f"you already have {mine} {what} queued, your share of the queue ({share} of {limit}); "
                           f"retry in {retry} s, as they finish", slug="queue-share-used",
                      title="Your share of the job queue is used", headers={"Retry-After": retry})


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
