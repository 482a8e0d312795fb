"""Job lifecycle on the job table (docs/ARCHITECTURE.md, Contract 3): submit, claim, lease, finish,
cancel, reap. Every state change is a conditional UPDATE, so racing API processes,
workers and reapers can never move a job twice.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import json
import logging
import statistics
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel
from sqlalchemy import and_, func, select, update
from sqlalchemy.exc import IntegrityError

from worker.errors import Canceled

from .auth import current_owner, owner_var
from .container import Services
from .db import session_scope
from .errors import Problem, problem_for
from .limits import check_queue_room
from .tables import Job, Texture, new_id, utcnow
from .vocabulary import TERMINAL_STATES, JobKind, JobState

log = logging.getLogger(__name__)


def request_hash(kind: str, texture_id: str | None, params: BaseModel | dict[str, Any], extra: bytes = b"") -> str:
    """Fingerprint of a submission, to tell an idempotent retry from a different request.
    Parameters left at their defaults are not part of it: a retry sent again after an upgrade
    that added an option is still the same request."""
    if isinstance(params, BaseModel):
        params = params.model_dump(mode="json", exclude_defaults=True)
    blob = json.dumps([kind, texture_id, params], sort_keys=True).encode() + extra
    return hashlib.sha256(blob).hexdigest()


def submit(services: Services, *, kind: str, texture_id: str | None, params: dict[str, Any],
           input_key: str | None = None, idempotency_key: str | None = None,
           fingerprint: str | None = None, job_id: str | None = None) -> tuple[Job, bool]:
    """Create a queued job and send its id to the queue; return (job, created).

    With an ``idempotency_key`` already used, return that earlier job (created=False);
    a different request under the same key is a 422 problem.
    """
    fingerprint = fingerprint or request_hash(kind, texture_id, params)
    idempotency_key = tenant_key(idempotency_key)
    if idempotency_key:
        existing = find_by_idempotency_key(services, idempotency_key)
        if existing is not None:
            return same_request(existing, fingerprint), False
    check_queue_room(services, kind)  # back-pressure: 503 (full) or 429 (the tenant's share) + Retry-After
    sampler = (served_sampler(services, texture_id, waiting=bool(params.get("after_refinement")))
               if texture_id and kind != JobKind.FIT else None)
    job = Job(id=job_id or new_id(), kind=kind, texture_id=texture_id, params=params, input_key=input_key,
              state=JobState.QUEUED, attempt=0, max_attempts=services.settings.max_attempts, progress=0.0,
              cancel_requested=False, idempotency_key=idempotency_key, request_hash=fingerprint,
              owner_id=current_owner(), sampler=sampler)
    try:
        with session_scope(services.sessions) as session:
            session.add(job)
    except IntegrityError:  # a concurrent request with the same key won the insert
        existing = find_by_idempotency_key(services, idempotency_key or "")
        if existing is None:
            raise
        return same_request(existing, fingerprint), False
    try:
        enqueue(services, job.id)
    except Exception:  # broker down: the row is saved (the truth); the reaper re-sends the message
        log.exception("could not send the job to the queue; the reaper will re-send it")
    return get(services, job.id), True


def queue_refinement(services: Services, texture: Texture, params: dict[str, Any]) -> bool:
    """Submit an upload's in-place refinement (job id: ``texture.refinement_job_id``), owned
    by the texture's owner; True if queued. It never fails the caller: with the fit queue or
    its owner's share of it full, the refinement is deferred (``Texture.refinement_deferred``:
    the texture says so and serves the encoder's code until ``queue_deferred_refinements``
    queues it); with any other error the texture keeps its encoder code, unrefined."""
    queued, deferred = False, None
    token = owner_var.set(texture.owner_id)
    try:
        if not texture.refinement_deferred and owner_has_deferred(services, texture.owner_id):
            # first come, first refined: a new upload does not take the room an older deferred one waits for
            log.warning("refinement deferred: earlier uploads of this tenant wait for room in the fit queue",
                        extra={"texture_id": texture.id})
            deferred = params
        else:
            submit(services, kind=JobKind.FIT, texture_id=texture.id, params=params, job_id=texture.refinement_job_id)
            queued = True
    except Problem as exc:
        full = exc.slug in ("queue-full", "queue-share-used")
        log.warning("refinement %s: %s", "deferred" if full else "not queued", exc.detail,
                    extra={"texture_id": texture.id})
        deferred = params if full else None
    except Exception as exc:
        log.warning("texture not refined: %s", exc, extra={"texture_id": texture.id})
    finally:
        owner_var.reset(token)
    if queued:
        values = {"refinement_deferred": None} if texture.refinement_deferred else {}
    elif deferred:
        values = {"refinement_deferred": deferred}
    else:  # not refined: neither a job nor a deferral (a deferred one the reaper would take again and again)
        values = {"refinement_job_id": None, "refinement_deferred": None}
    if values:
        with session_scope(services.sessions) as session:
            session.execute(update(Texture).where(Texture.id == texture.id).values(**values))
    return queued


def owner_has_deferred(services: Services, owner: str | None) -> bool:
    """Whether an upload of ``owner`` waits with a deferred refinement."""
    with session_scope(services.sessions) as session:
        return session.scalar(select(Texture.id).where(
            Texture.refinement_deferred.is_not(None),
            Texture.owner_id.is_(None) if owner is None else Texture.owner_id == owner).limit(1)) is not None


def queue_deferred_refinements(services: Services, batch: int = 50) -> int:
    """Queue deferred refinements while their fit queue has room, oldest upload first; an
    owner whose share is still full is skipped until a later pass. Returns how many were queued."""
    with session_scope(services.sessions) as session:
        waiting = session.scalars(select(Texture).where(Texture.refinement_deferred.is_not(None))
                                  .order_by(Texture.created_at, Texture.id).limit(batch)).all()
    queued, full = 0, set()
    for texture in waiting:
        if texture.owner_id in full:
            continue
        if queue_refinement(services, texture, texture.refinement_deferred):
            queued += 1
        else:
            full.add(texture.owner_id)
    return queued


def refinement_pending(services: Services, texture: Texture) -> bool:
    """Whether ``texture``'s in-place refinement may still replace the sampler it serves (the
    encoder's, or the refinement's own interim): its job is neither gone nor failed nor
    canceled (succeeded counts as pending: ``texture`` may have been read before the swap)."""
    if not texture.refinement_may_replace_sampler():
        return False
    if texture.refinement_deferred:
        return True  # queued by the reaper as the fit queue frees
    with session_scope(services.sessions) as session:
        state = session.scalar(select(Job.state).where(Job.id == texture.refinement_job_id))
    return state is not None and state not in (JobState.FAILED, JobState.CANCELED)


def served_sampler(services: Services, texture_id: str, waiting: bool = False) -> dict[str, Any] | None:
    """What ``texture_id`` renders with now (a job's ``sampler``): ``kind`` (encoder, interim,
    fitted), ``version`` (the model's, plus ``+fit.HASH`` of its own sampler), ``refining``
    (its refinement is queued or running and may still replace it) and
    ``waiting_for_refinement`` (``waiting``, a job's after_refinement, and refining)."""
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
    if texture is None:
        return None
    refining = refinement_pending(services, texture)
    key = texture.sampler_key
    kind = ("interim" if texture.sampler_interim else "fitted") if key else "encoder"
    version = texture.model_version + (f"+fit.{hashlib.sha256(key.encode()).hexdigest()[:8]}" if key else "")
    return {"kind": kind, "version": version, "refining": bool(refining),
            "waiting_for_refinement": bool(waiting and refining)}


def record_sampler(services: Services, job_id: str, sampler: dict[str, Any]) -> None:
    """Store what a job renders with, as it starts."""
    with session_scope(services.sessions) as session:
        session.execute(update(Job).where(Job.id == job_id).values(sampler=sampler))


def release_waiting(services: Services, texture_id: str) -> None:
    """Send again the queued jobs of ``texture_id`` (those held for its refinement, which ended)."""
    with session_scope(services.sessions) as session:
        held = session.scalars(select(Job.id).where(Job.texture_id == texture_id, Job.state == JobState.QUEUED,
                                                    Job.kind != JobKind.FIT)).all()
    for job_id in held:
        enqueue(services, job_id)  # a duplicate message is harmless: claim() is conditional


def same_request(job: Job, fingerprint: str) -> Job:
    """The earlier job of an Idempotency-Key, if the request is the same; else a 422."""
    if job.request_hash and job.request_hash != fingerprint:
        raise Problem(422, "this Idempotency-Key was already used for a different request",
                      slug="idempotency-key-reused")
    return job


def tenant_key(key: str | None) -> str | None:
    """The stored form of an Idempotency-Key: per API key when keys are enabled, so two
    tenants using the same key never see each other's job (idempotent: applied once)."""
    owner = current_owner()
    if not key or not owner or key.startswith(owner + ":"):
        return key
    return f"{owner}:{hashlib.sha256(key.encode()).hexdigest()}"


def find_by_idempotency_key(services: Services, key: str) -> Job | None:
    key = tenant_key(key)
    with session_scope(services.sessions) as session:
        return session.scalars(select(Job).where(Job.idempotency_key == key)).first()


def get(services: Services, job_id: str) -> Job | None:
    with session_scope(services.sessions) as session:
        return session.get(Job, job_id)


def enqueue(services: Services, job_id: str) -> None:
    """Send the job id to its kind's queue (the row must be committed first)."""
    with session_scope(services.sessions) as session:
        session.execute(update(Job).where(Job.id == job_id).values(enqueued_at=utcnow()))
        kind = session.scalar(select(Job.kind).where(Job.id == job_id))
    send = services.task_for(kind)
    try:
        send(job_id)
    except Exception:  # a broker connection dropped since its last use fails once, then reconnects
        log.warning("queue send failed; retrying once", exc_info=True)
        send(job_id)


@dataclass
class Claim:
    """A running attempt of a job held by this worker."""

    job: Job
    attempt: int


def claim(services: Services, job_id: str) -> Claim | None:
    """Move a queued job to running under a fresh lease; None if it is not ours to run."""
    now = utcnow()
    lease = now + dt.timedelta(seconds=services.settings.lease_seconds)
    with session_scope(services.sessions) as session:
        job = session.get(Job, job_id)
        if job is None or job.state != JobState.QUEUED:
            return None
        attempt = job.attempt + 1
        moved = session.execute(
            update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED, Job.attempt == job.attempt)
            .values(state=JobState.RUNNING, attempt=attempt, worker_id=services.worker_id, heartbeat_at=now,
                    lease_expires_at=lease, started_at=job.started_at or now, error=None,
                    progress=job.progress if job.stage else 0.0)  # (a paused fit goes on from where it was)
        ).rowcount
    if moved != 1:
        return None
    return Claim(job=get(services, job_id), attempt=attempt)


def _mine(claim_: Claim):  # noqa: ANN202
    return and_(Job.id == claim_.job.id, Job.state == JobState.RUNNING, Job.attempt == claim_.attempt)


def heartbeat(services: Services, claim_: Claim, progress: float) -> tuple[bool, bool]:
    """Extend the lease and record progress; return (still ours, cancel requested)."""
    now = utcnow()
    lease = now + dt.timedelta(seconds=services.settings.lease_seconds)
    with session_scope(services.sessions) as session:
        moved = session.execute(update(Job).where(_mine(claim_)).values(
            heartbeat_at=now, lease_expires_at=lease, progress=progress)).rowcount
        cancel = session.scalar(select(Job.cancel_requested).where(Job.id == claim_.job.id))
    return moved == 1, bool(cancel)


def finish(services: Services, claim_: Claim, state: str, **values: Any) -> bool:
    """Record the end of our attempt (succeeded / failed / canceled / back to queued)."""
    assert state in TERMINAL_STATES or state == JobState.QUEUED
    done = {"finished_at": utcnow()} if state in TERMINAL_STATES else {}
    with session_scope(services.sessions) as session:
        moved = session.execute(update(Job).where(_mine(claim_)).values(
            state=state, lease_expires_at=None, **done, **values)).rowcount
    return moved == 1


def cancel(services: Services, job_id: str) -> Job:
    """Cancel a job: a queued one at once, a running one by flag (seen between slabs)."""
    with session_scope(services.sessions) as session:
        job = session.get(Job, job_id)
        if job is None:
            raise Problem(404, f"job {job_id!r} does not exist", slug="not-found")
        if job.state in TERMINAL_STATES:
            raise Problem(409, f"job {job_id} is already {job.state}", slug="job-finished")
        session.execute(update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED).values(
            state=JobState.CANCELED, cancel_requested=True, finished_at=utcnow(),
            error=problem_for(Canceled("canceled while queued")).to_dict()))
        session.execute(update(Job).where(Job.id == job_id, Job.state == JobState.RUNNING).values(
            cancel_requested=True))
    return get(services, job_id)


def reap(services: Services) -> dict[str, int]:
    """Re-queue running jobs whose lease expired (or fail them after max attempts), and
    re-send queued jobs whose message may have been lost. Safe to run in many processes."""
    now = utcnow()
    counts = {"requeued": 0, "failed": 0, "resent": 0, "refinements": queue_deferred_refinements(services)}
    with session_scope(services.sessions) as session:
        expired = session.scalars(select(Job).where(Job.state == JobState.RUNNING,
                                                    Job.lease_expires_at < now)).all()
    for job in expired:
        if job.cancel_requested:  # the cancel is what ends it, not the attempts spent
            error = problem_for(Canceled("canceled; its worker stopped (lease expired) before it ended the job"))
            values = {"state": JobState.CANCELED, "finished_at": now, "error": error.to_dict(), "lease_expires_at": None}
        elif job.attempt >= job.max_attempts:
            error = Problem(500, f"worker lost the job {job.attempt} time(s) (lease expired); giving up after "
                            f"{job.max_attempts}", slug="lease-expired", title="The worker stopped")
            values = {"state": JobState.FAILED, "finished_at": now, "error": error.to_dict(), "lease_expires_at": None}
        else:
            values = {"state": JobState.QUEUED, "lease_expires_at": None, "worker_id": None}
        with session_scope(services.sessions) as session:
            moved = session.execute(update(Job).where(
                Job.id == job.id, Job.state == JobState.RUNNING, Job.attempt == job.attempt,
                Job.lease_expires_at < now).values(**values)).rowcount
        if moved == 1:
            if values["state"] == JobState.QUEUED:
                counts["requeued"] += 1
                log.warning("lease expired, re-queued", extra={"job_id": job.id})
                enqueue(services, job.id)
            else:
                counts["failed"] += 1
    stale = now - dt.timedelta(seconds=services.settings.requeue_after_seconds)
    with session_scope(services.sessions) as session:
        lost = session.scalars(select(Job.id).where(Job.state == JobState.QUEUED, Job.enqueued_at < stale)).all()
        queued = session.scalar(select(func.count()).select_from(Job).where(Job.state == JobState.QUEUED))
    if lost and services.pending_count() >= queued:
        lost = []  # the broker holds a message for every queued job: they are only waiting
    for job_id in lost:
        counts["resent"] += 1
        enqueue(services, job_id)  # a duplicate message is harmless: claim() is conditional
    return counts


def release_worker(services: Services) -> list[str]:
    """On shutdown: hand this worker's running jobs back to the queue at once, instead of
    letting their leases run out, their attempts not spent (the worker stopped, the job did not
    fail). Their threads, if they finish later, cannot record anything (finish() only updates
    the attempt it claimed while still running). From here on this worker claims nothing."""
    services.stopping.set()
    with session_scope(services.sessions) as session:
        held = session.scalars(select(Job.id).where(Job.state == JobState.RUNNING,
                                                    Job.worker_id == services.worker_id)).all()
    released = []
    for job_id in held:
        with session_scope(services.sessions) as session:
            moved = session.execute(update(Job).where(
                Job.id == job_id, Job.state == JobState.RUNNING, Job.worker_id == services.worker_id,
                Job.cancel_requested.is_(False)).values(
                state=JobState.QUEUED, lease_expires_at=None, worker_id=None, attempt=Job.attempt - 1)).rowcount
        if moved == 1:
            released.append(job_id)
            enqueue(services, job_id)
    return released


# --- the fit lane's order ----------------------------------------------------------------
# An upload's refinement runs in two stages: its fit until the interim is served, then (when
# other uploads wait for theirs) a pause, its state stored, and a continuation queued behind
# them. The lane runs first stages before continuations and whole fits, and among tenants the
# one whose fits ran least recently first, so that a burst of one tenant's uploads delays
# another tenant's first refinement by at most one stage.
# Each stage holds the lane for its share of the budget and an overhead (the start: photo,
# structure, VGG targets, the first probe; the end: last probe, export, colour table). The
# estimates take the median overhead of the last succeeded fits (``lane_time``), which varies
# with the CPU: 6 s on a 2-core AVX-512 EPYC, 15-20 s on a 2-core AVX2 one.
FIT_STAGE_OVERHEAD_SECONDS = 6.0  # before any fit has finished
RECENT_FITS = 5


def _first_stage(job: Job) -> bool:
    """A queued fit that will publish an interim before anything else: an upload's refinement
    that has not been paused yet."""
    return bool((job.params or {}).get("in_place")) and job.stage is None


def queued_fits(services: Services) -> list[Job]:
    """The queued fits, oldest first."""
    with session_scope(services.sessions) as session:
        return list(session.scalars(select(Job).where(Job.kind == JobKind.FIT, Job.state == JobState.QUEUED)
                                    .order_by(Job.created_at, Job.id)))


def fit_order(services: Services) -> list[Job]:
    """The queued fits in the order the fit lane will run them (``pick_fit``): first stages
    before the rest; within each, the tenant whose fits last ran longest ago, then the oldest."""
    queued = queued_fits(services)
    owners = {job.owner_id for job in queued}
    with session_scope(services.sessions) as session:
        last_ran = dict(session.execute(select(Job.owner_id, func.max(Job.heartbeat_at)).where(
            Job.kind == JobKind.FIT, Job.heartbeat_at.is_not(None)).group_by(Job.owner_id)).all()) if queued else {}
    order: list[Job] = []
    for group in ([j for j in queued if _first_stage(j)], [j for j in queued if not _first_stage(j)]):
        # round robin: each pick moves its tenant to the back (the tick stands for "ran now")
        turn = {owner: (1, last_ran[owner]) if last_ran.get(owner) else (0, 0) for owner in owners}
        for tick, _ in enumerate(list(group)):
            heads = {}  # each tenant's oldest job in the group (the group is oldest first)
            for job in group:
                heads.setdefault(job.owner_id, job)
            owner = min(heads, key=lambda o: (turn[o], heads[o].created_at, heads[o].id))
            job = heads[owner]
            group.remove(job)
            order.append(job)
            turn[owner] = (2, tick)
    return order


def pick_fit(services: Services, job_id: str) -> str:
    """The fit the lane should run for a message naming ``job_id``: the first of ``fit_order``.
    A fit-lane message is a turn, not an address: each queued fit sent one, so the lane runs as
    many fits as were queued, in this order (``job_id`` when none is queued: nothing to run)."""
    order = fit_order(services)
    return order[0].id if order else job_id


def claim_fit_turn(services: Services, job_id: str, tries: int = 3) -> Claim | None:
    """Claim the fit a fit-lane message's turn goes to (``pick_fit``); where another worker
    claimed it first, the next in ``fit_order`` (up to ``tries``), so no turn is lost."""
    for _ in range(tries):
        picked = pick_fit(services, job_id)
        claimed = claim(services, picked)
        if claimed is not None or picked == job_id:
            return claimed
    return None


def fits_waiting_for_interim(services: Services, job_id: str) -> bool:
    """Whether an upload other than ``job_id``'s waits for its refinement's first stage: a fit
    past its interim then pauses for it."""
    return any(_first_stage(job) and job.id != job_id for job in queued_fits(services))


def other_fits_queued(services: Services, job_id: str) -> bool:
    """Whether any fit other than ``job_id`` waits for the fit lane: an upload's refinement then
    skips its detail stage (``TEXSPACE_REFINE_DETAIL_SECONDS``), so the uploads behind it get
    their final samplers as soon as without one."""
    return any(job.id != job_id for job in queued_fits(services))


def lane_time(job: Job, details: dict[str, Any] | None, seconds: float) -> dict[str, Any]:
    """A fit's result details after a stage of ``seconds`` on the lane: ``lane_seconds`` and
    ``stages`` add up over its pause and continuation (the estimates' measure)."""
    before = job.result_details or {}
    return {**before, **(details or {}), "lane_seconds": round(before.get("lane_seconds", 0.0) + seconds, 1),
            "stages": before.get("stages", 0) + 1}


def fit_budget_seconds(services: Services, job: Job) -> float:
    """The seconds of fitting ``job`` asked for (an upload's refinement: the server's budget),
    its detail stage's included (model.fit runs one only for photos of 512 px and up: below, a
    fit ends that much sooner than its estimate)."""
    params = job.params or {}
    return float(params.get("seconds", services.settings.fit_seconds)) + float(params.get("detail_seconds", 0.0))


def stage_overhead(services: Services) -> float:
    """Seconds a fit stage holds the lane beyond its budget: the median over the last
    succeeded fits that recorded their lane time (``FIT_STAGE_OVERHEAD_SECONDS`` before any)."""
    with session_scope(services.sessions) as session:
        recent = session.scalars(select(Job).where(Job.kind == JobKind.FIT, Job.state == JobState.SUCCEEDED)
                                 .order_by(Job.finished_at.desc()).limit(4 * RECENT_FITS)).all()
    samples = [(d["lane_seconds"] - fit_budget_seconds(services, j)) / d["stages"]
               for j in recent if "lane_seconds" in (d := j.result_details or {}) and d.get("stages")][:RECENT_FITS]
    return max(0.0, statistics.median(samples)) if samples else FIT_STAGE_OVERHEAD_SECONDS


@dataclass
class FitLane:
    """The fit lane now: its queued fits in run order, its running ones and the seconds a
    stage takes beyond its budget (``fit_lane``)."""

    order: list[Job]
    running: list[Job]
    overhead: float = FIT_STAGE_OVERHEAD_SECONDS


def fit_lane(services: Services) -> FitLane:
    with session_scope(services.sessions) as session:
        running = session.scalars(select(Job).where(Job.kind == JobKind.FIT, Job.state == JobState.RUNNING)).all()
    return FitLane(order=fit_order(services), running=list(running), overhead=stage_overhead(services))


def refinement_wait(services: Services, job: Job, lane: FitLane | None = None) -> dict[str, Any]:
    """Where an upload's refinement stands in the fit lane: ``position`` (fits that run before
    it starts; 0: next or running) and estimates, in seconds from now, of when its interim
    and its final sampler arrive (None once there, or unknown), from ``lane_schedule``.
    ``lane``: ``fit_lane(services)``, read once for many textures."""
    lane = lane or fit_lane(services)
    if job.state == JobState.RUNNING:
        position = 0
    elif job.state == JobState.QUEUED and job.id in (ids := [j.id for j in lane.order]):
        position = ids.index(job.id)
    else:
        return {"position": None, "interim_eta_seconds": None, "final_eta_seconds": None}
    interim_at, final_at = lane_schedule(services, lane)[job.id]
    return {"position": position, "interim_eta_seconds": interim_at, "final_eta_seconds": final_at}


def lane_schedule(services: Services, lane: FitLane) -> dict[str, tuple[float | None, float]]:
    """Seconds from now at which each running and queued fit's interim (None: none to come)
    and final sampler arrive, the lane run as ``pick_fit`` and ``fits_waiting_for_interim``
    run it: the running fits, then the first stages in order (each pauses at its interim while
    another first stage waits; the last goes on to its end), then the continuations and whole
    fits, oldest first (one tenant's order; tenants in fact take turns). A stage holds the lane
    for its share of the budget plus ``lane.overhead``; one lane (more workers end sooner).
    Uploads yet to come are not foreseen: one that arrives pauses the fit in its first stage."""
    interim, overhead = services.settings.fit_interim_seconds, lane.overhead
    first_stages = [j for j in lane.order if interim > 0 and _first_stage(j)]
    later = [j for j in lane.order if j not in first_stages]

    def budget(j: Job) -> float:
        return fit_budget_seconds(services, j)

    def continuation(j: Job) -> float:  # the stage after a pause at the interim
        return budget(j) - interim + overhead

    def rest(j: Job) -> float:  # the rest of a fit that does not pause (progress: its budget's share spent)
        return (budget(j) + overhead) * (1.0 - j.progress)

    t, schedule, paused = 0.0, {}, []
    for j in lane.running:
        spent = j.progress * budget(j)
        to_interim = interim + overhead - spent if interim > 0 and _first_stage(j) and spent < interim else None
        if to_interim is not None and first_stages:  # it pauses at its interim for them
            t += max(0.0, to_interim)
            schedule[j.id] = (t, None)
            paused.append(j)
        else:
            schedule[j.id] = (t + max(0.0, to_interim) if to_interim is not None else None,
                              t + rest(j))
            t = schedule[j.id][1]
    for k, j in enumerate(first_stages):
        t += interim + overhead
        if k < len(first_stages) - 1:
            schedule[j.id] = (t, None)
            paused.append(j)
        else:  # no one waits for an interim behind it: it goes on without a pause
            schedule[j.id] = (t, t + budget(j) - interim)
            t = schedule[j.id][1]
    for j in sorted(later + paused, key=lambda j: (j.created_at, j.id)):
        t += continuation(j) if j in paused else rest(j)
        schedule[j.id] = (schedule.get(j.id, (None, None))[0], t)
    return schedule
