"""One tenant's burst of 1,000 uploads, on SQLite and on PostgreSQL: it fills at most its
share of the fit queue (the rest of its refinements deferred, not dropped), another tenant's
volume is not refused and its first refinement runs after at most one of the burst's fits."""
from __future__ import annotations

import datetime as dt
import time
from collections.abc import Iterator

import pytest
from sqlalchemy import func, select

from service import jobs, limits
from service.auth import owner_var
from service.context import Services, build_services
from service.db import session_scope
from service.errors import Problem
from service.tables import Job, Texture, new_id, utcnow
from service.vocabulary import JobKind, JobState
from tests.reliability.helpers import database_settings, make_settings

BURST = 1_000
PARAMS = {"seconds": 90.0, "in_place": True}


@pytest.fixture(scope="module")
def burst(tmp_path_factory, database_url) -> Iterator[Services]:
    """Alice's 1,000 uploads as the upload route leaves them: her share of the fit queue
    queued (100 fits, share 0.5: 50), the rest deferred. Rows are written directly: 1,000
    encodes through the API would take minutes and test nothing more here."""
    settings = make_settings(tmp_path_factory.mktemp("burst"), api_keys_enabled=True, queue_backend="memory", **database_settings(database_url))
    services = build_services(settings)
    version = services.registry.get(None).version
    share = limits.tenant_share(settings, settings.max_queued_fits)
    start = utcnow() - dt.timedelta(minutes=10)
    with session_scope(services.sessions) as session:
        for k in range(BURST):
            at = start + dt.timedelta(milliseconds=k)
            texture = Texture(id=new_id(), code=[0.0] * 8, model_version=version, owner_id="alice",
                              refinement_job_id=new_id(), created_at=at,
                              refinement_deferred=PARAMS if k >= share else None)
            session.add(texture)
            if k < share:
                session.add(Job(id=texture.refinement_job_id, kind=JobKind.FIT, texture_id=texture.id, params=PARAMS,
                                state=JobState.QUEUED, attempt=0, max_attempts=3, progress=0.0, owner_id="alice",
                                created_at=at))
    yield services
    services.engine.dispose()


def test_alice_gets_429_for_more_than_her_share(burst: Services) -> None:
    token = owner_var.set("alice")
    try:
        with pytest.raises(Problem) as refused:
            limits.check_queue_room(burst, JobKind.FIT)
        assert refused.value.status == 429 and refused.value.headers["Retry-After"]
        limits.check_queue_room(burst, JobKind.VOLUME)  # her volumes are another queue
    finally:
        owner_var.reset(token)


def test_a_burst_holds_its_share_and_another_tenant_goes_after_one_fit(burst: Services) -> None:
    """(After the 429 test: both read the burst as the fixture made it, this one adds bob.)"""
    services = burst
    token = owner_var.set("bob")
    try:
        limits.check_queue_room(services, JobKind.VOLUME)  # fits are counted apart: room for bob's volume
        limits.check_queue_room(services, JobKind.FIT)     # and bob has his own share of the fit queue
        texture = Texture(id=new_id(), code=[0.0] * 8, model_version=services.registry.get(None).version,
                          owner_id="bob", refinement_job_id=new_id())
        with session_scope(services.sessions) as session:
            session.add(texture)
        assert jobs.queue_refinement(services, texture, PARAMS)
    finally:
        owner_var.reset(token)
    order = [job.owner_id for job in jobs.fit_order(services)]
    assert order.index("bob") <= 1  # behind at most the burst's oldest fit
    assert order.count("alice") == limits.tenant_share(services.settings, services.settings.max_queued_fits)
    # alice's deferred refinements stay deferred while her share is full; the reaper's pass is cheap
    started = time.perf_counter()
    assert jobs.reap(services)["refinements"] == 0
    assert time.perf_counter() - started < 5.0  # (about 0.05 s here: one query, no submit)
    with session_scope(services.sessions) as session:
        deferred = session.scalar(select(func.count()).select_from(Texture).where(Texture.refinement_deferred.is_not(None)))
    assert deferred == BURST - order.count("alice")
