"""huey wiring. Messages carry only a job id; the job table is the truth.

``queue_backend`` picks SqliteHuey (a file under data_dir, the embedded default),
RedisHuey or PostgresHuey (scale-out), or MemoryHuey (tests). ``immediate`` mode runs
each task synchronously at enqueue time, for unit tests without infrastructure.

Two lanes, each a queue of its own on the same broker: ``main`` (``queue_name``) carries
volume, bake and region jobs; ``fit`` (``<queue_name>-fit``) carries fits, which run for
minutes on torch. A worker consumes the lanes of the kinds it runs (``worker_kinds``), so
fits can have machines of their own and never wait behind, or hold up, the other jobs.
"""
from __future__ import annotations

from huey import MemoryHuey, PostgresHuey, RedisHuey, SqliteHuey
from huey.api import Huey

from .settings import Settings
from .vocabulary import JobKind


LANES = ("main", "fit")


def lane_of(kind: JobKind | str | None) -> str:
    """The lane (queue) that carries jobs of ``kind``."""
    return "fit" if kind == JobKind.FIT else "main"


def worker_lanes(settings: Settings) -> list[str]:
    """The lanes a worker with ``settings.worker_kinds`` consumes, in LANES order."""
    return [lane for lane in LANES if any(lane_of(kind) == lane for kind in settings.worker_kinds)]


def make_huey(settings: Settings, *, immediate: bool = False, lane: str = "main") -> Huey:
    """The huey instance of ``lane`` the settings ask for (tasks: runner.register_tasks)."""
    name = settings.queue_name if lane == "main" else f"{settings.queue_name}-{lane}"
    common = {"results": False, "immediate": immediate}
    if immediate or settings.queue_backend == "memory":
        return MemoryHuey(name, **common)
    if settings.queue_backend == "redis":
        return RedisHuey(name, url=settings.queue_url or "redis://127.0.0.1:6379/0", **common)
    if settings.queue_backend == "postgres":
        dsn = settings.queue_url or settings.resolved_database_url
        dsn = dsn.replace("postgresql+psycopg://", "postgresql://")
        return PostgresHuey(name, dsn=dsn, **common)
    filename = str((settings.data_dir / "queue.db").resolve())
    return SqliteHuey(name, filename=filename, **common)


def queue_depth(huey: Huey) -> int:
    """Messages waiting in the broker (may lag the job table by in-flight messages)."""
    return int(huey.pending_count())


def ping(huey: Huey) -> None:
    """Raise if the broker does not answer."""
    huey.pending_count()
