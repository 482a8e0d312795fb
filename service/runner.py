"""Running one job attempt: claim, heartbeat thread, call the job kind, record the end.

Retry policy: domain errors (bad mesh, limits, ...) are final, since a re-run would fail
the same way, and so is a write that failed for space (a full disk or database,
``errors.storage_full``) until an operator frees some; unexpected errors re-queue until
``max_attempts``; a worker killed outright is noticed by the reaper when its lease
expires. A kind that raises ``Paused`` (an upload's fit at its interim's second, while
other uploads wait) goes back to the queue without using an attempt, its progress kept.

Fit-lane messages are turns: the lane runs the fit ``jobs.pick_fit`` chooses, whichever
queued fit the message names.
"""
from __future__ import annotations

import logging
import shutil
import threading
import time

from worker.errors import Canceled, Paused, TexspaceError

from . import jobs
from .container import Services
from .errors import problem_for, storage_full
from .job_kinds import KINDS
from .logs import job_id_var
from .purge import forget_job_files
from .vocabulary import JobKind, JobState

log = logging.getLogger(__name__)
TASK_NAME = "texspace.run_job"


def register_tasks(huey, services: Services):  # noqa: ANN001, ANN201
    """Register the one task (``run_job(job_id)``) on ``huey`` bound to ``services``.

    Returns the task wrapper: calling it with a job id enqueues a message.
    """

    def run_job(job_id: str) -> None:
        run_job_attempt(services, job_id)

    return huey.task(name=TASK_NAME)(run_job)


class Lease:
    """Heartbeat thread for one attempt: extends the lease, saves progress, sees cancels."""

    def __init__(self, services: Services, claim: jobs.Claim) -> None:
        self.services = services
        self.claim = claim
        self.progress = 0.0
        self.lost = threading.Event()
        self.cancel = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"lease-{claim.job.id[:8]}", daemon=True)

    def __enter__(self) -> "Lease":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _loop(self) -> None:
        token = job_id_var.set(self.claim.job.id)
        try:
            while not self._stop.wait(self.services.settings.heartbeat_seconds):
                self.beat()
        finally:
            job_id_var.reset(token)

    def beat(self) -> None:
        try:
            ours, cancel = jobs.heartbeat(self.services, self.claim, self.progress)
        except Exception:  # a database hiccup must not kill the job; the lease has slack
            log.exception("heartbeat failed")
            return
        if not ours:
            log.warning("lease lost; stopping this attempt")
            self.lost.set()
        if cancel:
            self.cancel.set()

    def report(self, fraction: float) -> None:
        self.progress = float(min(max(fraction, 0.0), 1.0))

    def should_cancel(self) -> bool:
        return self.cancel.is_set() or self.lost.is_set()


def run_job_attempt(services: Services, job_id: str) -> str | None:
    """Run one attempt of ``job_id`` if it is queued (a fit: of the fit the lane's order puts
    first); return the state it ended in. A worker that is stopping claims nothing (the job
    stays queued; the message goes back to the queue for another worker)."""
    if services.stopping.is_set():
        jobs.enqueue(services, job_id)
        return None
    named = jobs.get(services, job_id)
    fit_turn = named is not None and named.kind == JobKind.FIT
    claim = jobs.claim_fit_turn(services, job_id) if fit_turn else None
    job_id = claim.job.id if claim is not None else job_id
    token = job_id_var.set(job_id)
    try:
        if not fit_turn:
            claim = jobs.claim(services, job_id)
        if claim is None:
            log.info("job not claimable (already running, finished or canceled); message dropped")
            return None
        log.info("job started", extra={"kind": claim.job.kind, "attempt": claim.attempt})
        for stale in services.work_dir.glob(f"{job_id}-*"):  # scratch of attempts killed outright
            shutil.rmtree(stale, ignore_errors=True)
        workdir = services.work_dir / f"{job_id}-{claim.attempt}"
        workdir.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        resend = True
        try:
            with Lease(services, claim) as lease:
                if claim.job.cancel_requested:
                    raise Canceled("canceled before it started")
                values = KINDS[claim.job.kind](services, claim.job, workdir, lease.report, lease.should_cancel)
                if lease.lost.is_set():
                    raise Canceled("lease lost")
            state, values = JobState.SUCCEEDED, {**values, "progress": 1.0}
        except Paused as exc:  # back in line, the attempt not spent (a paused fit keeps its progress)
            state, values = JobState.QUEUED, {"attempt": claim.attempt - 1, "stage": exc.stage, "progress": lease.progress}
            resend = exc.resend
        except Canceled as exc:
            state, values = JobState.CANCELED, {"error": problem_for(exc).to_dict()}
        except TexspaceError as exc:
            state, values = JobState.FAILED, {"error": problem_for(exc).to_dict()}
        except Exception as exc:
            full = storage_full(exc)
            if full is not None:  # the same write fails again until space is freed: not retried
                log.warning("job failed: storage full (%s)", exc)
                state, values = JobState.FAILED, {"error": problem_for(full).to_dict()}
            else:  # unexpected: retry while attempts remain
                log.exception("job attempt crashed")
                problem = problem_for(exc).to_dict()
                problem["detail"] = f"{type(exc).__name__}: {exc}"
                retry = claim.attempt < claim.job.max_attempts
                state, values = (JobState.QUEUED if retry else JobState.FAILED), {"error": problem}
        finally:
            shutil.rmtree(workdir, ignore_errors=True)
        if claim.job.kind == JobKind.FIT and state in (JobState.QUEUED, JobState.SUCCEEDED) and "error" not in values:
            values["result_details"] = jobs.lane_time(claim.job, values.get("result_details"),
                                                      time.monotonic() - started)
        if jobs.finish(services, claim, state, **values):
            log.info("job %s", state, extra={"seconds": round(time.monotonic() - started, 3)})
            if state == JobState.QUEUED and resend:
                jobs.enqueue(services, job_id)
            if claim.job.kind == JobKind.FIT and state != JobState.QUEUED and claim.job.texture_id:
                jobs.release_waiting(services, claim.job.texture_id)  # jobs held for this refinement
        else:
            log.warning("job ended as %s but its lease was taken over; result discarded", state)
            if jobs.get(services, job_id) is None:  # deleted with its texture meanwhile: leave no files
                forget_job_files(services, job_id)
        return state
    finally:
        job_id_var.reset(token)
