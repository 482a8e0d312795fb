"""Limits checked at the door, before anything is stored or queued.

* ``check_mesh``: check an uploaded mesh's header, then parse and validate it, at
  submission time, so a bad mesh is a 422 / 413 problem at once (and nothing is stored)
  instead of a failed job later.
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
import threading
import time
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import func, select

from worker.bake import MESH_TYPES, BakeLimits, Mesh, read_mesh
from worker.errors import Busy, InsufficientStorage
from worker.mesh_size import check_mesh_size

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
                      max_nodes=settings.max_mesh_nodes, max_depth=settings.max_mesh_depth,
                      max_resolution=settings.max_bake_resolution)


#: full mesh parses one API process runs at once (each up to ~1 s of CPU, much of it holding
#: the GIL, and ~100 MB at the limits), requests that may wait for one (each holds a thread
#: of the pool the other routes run on), and for how long; beyond, 503 busy + Retry-After
MESH_PARSES = 2
MESH_PARSES_WAITING = 4
MESH_PARSE_WAIT_SECONDS = 10.0


class CpuSlots:
    """At most ``slots`` holders at once, at most ``max_waiting`` waiting ``wait_seconds``;
    beyond, ``Busy`` (503 + Retry-After) saying what ``work`` is in progress ("meshes are
    being checked"). One that would wait longer than ``wait_seconds`` by the holders' recent
    pace (a moving average of how long each held its slot) is refused at once instead of
    after waiting in vain: under load an encode takes several times its idle time."""

    PACE_WEIGHT = 0.3  # of the latest holder's time in the moving average

    def __init__(self, slots: int, max_waiting: int, wait_seconds: float, work: str) -> None:
        self.slots, self.max_waiting, self.wait_seconds, self.work = slots, max_waiting, wait_seconds, work
        self._cond = threading.Condition()
        self._held = self._waiting = 0
        self.pace: float | None = None  # seconds a holder keeps its slot, moving average

    def expected_wait(self) -> float:
        """Seconds the next arrival would wait by the recent pace: its turn comes after
        ``waiting + 1`` slots free, ``slots`` at a time (0 before any holder has finished)."""
        return 0.0 if self.pace is None else math.ceil((self._waiting + 1) / self.slots) * self.pace

    @contextmanager
    def slot(self):  # noqa: ANN201
        with self._cond:
            if self._held >= self.slots:
                if self._waiting >= self.max_waiting:
                    raise Busy(f"{self._held} {self.work} and {self._waiting} wait; retry shortly", retry_after=2)
                if self.expected_wait() > self.wait_seconds:
                    raise Busy(f"{self._held} {self.work} and {self._waiting} wait, about {self.expected_wait():.0f} s "
                               f"at the recent pace, past the {self.wait_seconds:g} s an arrival may wait; retry "
                               "shortly", retry_after=math.ceil(self.pace))
                self._waiting += 1
                try:
                    if not self._cond.wait_for(lambda: self._held < self.slots, timeout=self.wait_seconds):
                        raise Busy(f"{self._held} {self.work}: no room within {self.wait_seconds:g} s; retry "
                                   "shortly", retry_after=2)
                finally:
                    self._waiting -= 1
            self._held += 1
        started = time.monotonic()
        try:
            yield
        finally:
            held_for = time.monotonic() - started
            with self._cond:
                self._held -= 1
                self.pace = held_for if self.pace is None else (
                    (1 - self.PACE_WEIGHT) * self.pace + self.PACE_WEIGHT * held_for)
                self._cond.notify()


MESH_PARSE_SLOTS = CpuSlots(MESH_PARSES, MESH_PARSES_WAITING, MESH_PARSE_WAIT_SECONDS, "meshes are being checked")

#: uploads that may wait for an encode slot (``Settings.upload_encodes``), per slot, and for
#: how long: a client uploading a batch at once waits its turn rather than being refused
UPLOADS_WAITING_PER_SLOT = 4
UPLOAD_WAIT_SECONDS = 30.0


def upload_slots(settings: Settings) -> CpuSlots:
    """The bound on uploads one API process decodes and encodes at once: each is about a
    second of CPU at 1024^2 (the encoder, 13 candidate tiles and their style statistics) and
    up to ~1 GB at the pixel limit, so a burst of them would starve tiles and memory."""
    return CpuSlots(settings.upload_encodes, UPLOADS_WAITING_PER_SLOT * settings.upload_encodes,
                    UPLOAD_WAIT_SECONDS, "uploads are being encoded")


def check_mesh(settings: Settings, data: bytes, filename: str) -> Mesh:
    """The parsed mesh (the job's input: the worker does not parse the file again); raise
    InvalidMesh / LimitExceeded if it cannot be baked (parse + validate only; the UV atlas is
    made later by the job), Busy while ``MESH_PARSES`` others are parsed and
    ``MESH_PARSES_WAITING`` wait. The file's header is checked first, without waiting
    (``worker/mesh_size.py``: faces, vertices, a GLB's nodes and depth, in milliseconds), so
    the parse that follows is bounded by the limits: ~1 s for 200k faces or 4,096 nodes."""
    limits = bake_limits(settings)
    ext = Path(filename).suffix.lower().lstrip(".")
    if ext in MESH_TYPES and data:        # (else load_mesh says what is wrong)
        check_mesh_size(data, ext, limits)
    with MESH_PARSE_SLOTS.slot():
        return read_mesh(data, filename, limits)   # (its header check again: milliseconds)


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
