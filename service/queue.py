"""huey wiring. Messages carry only a job id; the job table is the truth.

``queue_backend`` picks SqliteHuey (a file under data_dir, the embedded default),
RedisHuey or PostgresHuey (scale-out), or MemoryHuey (tests). ``immediate`` mode runs
each task synchronously at enqueue time, for unit tests without infrastructure.
"""
from __future__ import annotations

from huey import MemoryHuey, PostgresHuey, RedisHuey, SqliteHuey
from huey.api import Huey

from .settings import Settings


def make_huey(settings: Settings, *, immediate: bool = False) -> Huey:
    """The huey instance the settings ask for (tasks are registered by runner.register_tasks)."""
    name = settings.queue_name
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
