"""Deleting a texture without leaving anything behind.

A texture owns its stored files (``textures/<id>/...``) and its jobs; each job owns
``jobs/<job id>/...`` (bake input, result). :func:`purge_texture` removes the files first,
then the rows, in one transaction, then sweeps the files again. Files first: on a full disk
the database's delete needs room for its journal (SQLite writes the deleted pages to its
WAL), which the files free, so deleting is how a full service gets space back. The sweep
after takes what a job still running stored meanwhile. A worker still running one of
those jobs notices at its next heartbeat (its row is gone, so the lease is lost) and
stops; if it stores a result after the sweep, ``runner.run_job_attempt`` removes it
(``forget_job_files``).
"""
from __future__ import annotations

import logging

from sqlalchemy import delete, select

from . import keys
from .container import Services
from .db import session_scope
from .tables import Job, Texture

log = logging.getLogger(__name__)


def purge_texture(services: Services, texture_id: str) -> list[str] | None:
    """Delete the texture, cancel and delete its jobs, remove all their files.
    Returns the ids of the jobs removed; None when the texture row was already gone (another
    request deleted it first: its files are still swept, harmlessly)."""
    with session_scope(services.sessions) as session:
        job_ids = list(session.scalars(select(Job.id).where(Job.texture_id == texture_id)))
    _remove_files(services, texture_id, job_ids)
    with session_scope(services.sessions) as session:
        job_ids = list(session.scalars(select(Job.id).where(Job.texture_id == texture_id)))
        session.execute(delete(Job).where(Job.texture_id == texture_id))
        deleted = session.execute(delete(Texture).where(Texture.id == texture_id)).rowcount
    _remove_files(services, texture_id, job_ids)
    if job_ids:
        log.info("texture deleted with its jobs", extra={"texture_id": texture_id, "jobs": job_ids})
    return job_ids if deleted else None


def _remove_files(services: Services, texture_id: str, job_ids: list[str]) -> None:
    """Every stored file of the texture and of its jobs, and the local copies of its samplers."""
    for job_id in job_ids:
        forget_job_files(services, job_id)
    services.storage.delete_prefix(keys.texture_prefix(texture_id))
    for cached in services.cached_samplers(texture_id):
        cached.unlink(missing_ok=True)


def forget_job_files(services: Services, job_id: str) -> None:
    """Remove every stored file of a job (input and result)."""
    services.storage.delete_prefix(keys.job_prefix(job_id))
