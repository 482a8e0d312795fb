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

import threading
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import func, select

from worker.bake import MESH_TYPES, BakeLimits, load_mesh
from worker.errors import Busy
from worker.mesh_size import check_mesh_size

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


#: full mesh parses one API process runs at once (each up to ~1 s of CPU, much of it holding
#: the GIL, and ~100 MB at the limits), requests that may wait for one (each holds a thread
#: of the pool the other routes run on), and for how long; beyond, 503 busy + Retry-After
MESH_PARSES = 2
MESH_PARSES_WAITING = 4
MESH_PARSE_WAIT_SECONDS = 10.0


class ParseSlots:
    """At most ``slots`` holders at once, at most ``max_waiting`` waiting ``wait_seconds``."""

    def __init__(self, slots: int, max_waiting: int, wait_seconds: float) -> None:
        self.slots, self.max_waiting, self.wait_seconds = slots, max_waiting, wait_seconds
        self._cond = threading.Condition()
        self._held = self._waiting = 0

    @contextmanager
    def slot(self):  # noqa: ANN201
        with self._cond:
            if self._held >= self.slots:
                if self._waiting >= self.max_waiting:
                    raise Busy(f"{self._held} meshes are being checked and {self._waiting} wait; retry shortly",
                               retry_after=2)
                self._waiting += 1
                try:
                    if not self._cond.wait_for(lambda: self._held < self.slots, timeout=self.wait_seconds):
                        raise Busy(f"no room to check the mesh within {self.wait_seconds:g} s", retry_after=2)
                finally:
                    self._waiting -= 1
            self._held += 1
        try:
            yield
        finally:
            with self._cond:
                self._held -= 1
                self._cond.notify()


MESH_PARSE_SLOTS = ParseSlots(MESH_PARSES, MESH_PARSES_WAITING, MESH_PARSE_WAIT_SECONDS)


def check_mesh(settings: Settings, data: bytes, filename: str) -> None:
    """Raise InvalidMesh / LimitExceeded if the mesh cannot be baked (parse + validate only;
    the UV atlas is made later by the job), Busy while ``MESH_PARSES`` others are parsed and
    ``MESH_PARSES_WAITING`` wait. The file's header is checked first, without waiting
    (``worker/mesh_size.py``: faces, vertices, a GLB's nodes and depth, in milliseconds), so
    the parse that follows is bounded by the limits: ~1 s for 200k faces or 4,096 nodes."""
    limits = bake_limits(settings)
    ext = Path(filename).suffix.lower().lstrip(".")
    if ext in MESH_TYPES and data:        # (else load_mesh says what is wrong)
        check_mesh_size(data, ext, limits)
    with MESH_PARSE_SLOTS.slot():
        load_mesh(data, filename, limits)   # (its header check again: milliseconds)


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
