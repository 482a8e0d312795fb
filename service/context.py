"""Building the services container from the settings, once per process.

:func:`build_services` opens the database, storage and queue lanes and registers the
job task (:mod:`service.runner`) on each lane: process wiring, above the domain modules.
:class:`~service.container.Services` itself lives in :mod:`service.container`.
"""
from __future__ import annotations

from . import db
from .container import Services
from .limits import upload_slots
from .queue import make_huey
from .runner import register_tasks
from .settings import Settings
from .storage import make_storage
from .tilecache import TileCache

__all__ = ["Services", "build_services"]


def build_services(settings: Settings, *, immediate: bool = False, migrate: bool = True) -> Services:
    """Create every shared resource; ``immediate`` runs queued tasks in-process (tests)."""
    settings.ensure_dirs()
    url = settings.resolved_database_url
    if migrate:
        db.migrate(url)
    engine = db.make_engine(url)
    services = Services(settings=settings, engine=engine, sessions=db.make_sessionmaker(engine),
                        storage=make_storage(settings), huey=None,
                        tile_cache=TileCache(settings.tile_cache_bytes), upload_slots=upload_slots(settings))
    services.huey = make_huey(settings, immediate=immediate)
    services.fit_huey = make_huey(settings, immediate=immediate, lane="fit")
    services.run_job = register_tasks(services.huey, services)
    services.run_fit_job = register_tasks(services.fit_huey, services)
    return services
