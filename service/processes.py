"""Long-running processes: the API (uvicorn), the worker (huey consumer + reaper), and
``serve`` (both, for the embedded default)."""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time

from . import db
from .context import build_services
from .jobs import reap, release_worker
from .queue import worker_lanes
from .settings import Settings

log = logging.getLogger(__name__)


def run_api(settings: Settings) -> None:
    import uvicorn

    uvicorn.run("service.main:app_from_env", factory=True, host=settings.host, port=settings.port,
                log_config=None, timeout_graceful_shutdown=5, http=read_timeout_protocol(settings),
                timeout_keep_alive=settings.http_keep_alive_seconds,
                limit_concurrency=settings.http_limit_concurrency)


def read_timeout_protocol(settings: Settings) -> type:
    """uvicorn's h11 protocol with a read deadline (uvicorn has none): a connection whose
    request headers and body have not all arrived ``http_read_timeout_seconds`` after it
    opened (or after the first byte of a later request on it) is closed, so slowloris
    clients and bodies shorter than their Content-Length do not hold connections forever.
    Idle time between requests is the keep-alive timeout's business, not this deadline's:
    counting it here closed kept-alive connections under clients that paused before
    their next request, mid-send. Requests already read (a long tile, an event stream)
    are not affected."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    timeout = settings.http_read_timeout_seconds

    class ReadTimeoutProtocol(H11Protocol):
        _read_deadline = None

        def _arm_read_deadline(self) -> None:
            if self._read_deadline is not None:
                self._read_deadline.cancel()
            self._read_deadline = self.loop.call_later(timeout, self._read_timed_out)

        def connection_made(self, transport) -> None:  # noqa: ANN001
            super().connection_made(transport)
            self._arm_read_deadline()

        def data_received(self, data: bytes) -> None:
            if self._read_deadline is None:      # the first byte of a request after a response
                self._arm_read_deadline()
            super().data_received(data)

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self._read_deadline is not None:  # the keep-alive timeout watches the idle time
                self._read_deadline.cancel()
                self._read_deadline = None

        def connection_lost(self, exc: Exception | None) -> None:
            if self._read_deadline is not None:
                self._read_deadline.cancel()
            super().connection_lost(exc)

        def _read_timed_out(self) -> None:
            self._read_deadline = None
            if not self.transport.is_closing() and self.conn.their_state in (h11.IDLE, h11.SEND_BODY):
                log.info("closing a connection: request not read within %ss", timeout)
                self.transport.close()

    return ReadTimeoutProtocol


def start_reaper(services, stop: threading.Event) -> threading.Thread:  # noqa: ANN001
    """A thread that periodically re-queues jobs with expired leases."""
    def loop() -> None:
        while not stop.wait(services.settings.reaper_interval_seconds):
            try:
                counts = reap(services)
                if any(counts.values()):
                    log.info("reaper", extra=counts)
            except Exception:  # keep reaping after a database hiccup
                log.exception("reaper pass failed")

    thread = threading.Thread(target=loop, name="reaper", daemon=True)
    thread.start()
    return thread


LANE_POLL_SECONDS = 0.5


def start_lane(huey, stop: threading.Event) -> threading.Thread:  # noqa: ANN001
    """One thread consuming a second lane beside the consumer's: its jobs run one at a
    time (in ``texspace serve``, one fit at a time beside the other jobs)."""

    def loop() -> None:
        while not stop.is_set():
            try:
                task = huey.dequeue()
                if task is None:
                    stop.wait(LANE_POLL_SECONDS)
                    continue
                huey.execute(task)
            except Exception:  # a broker hiccup or a crashed task: the job table has the truth
                log.exception("lane %s: task failed", huey.name)
                stop.wait(LANE_POLL_SECONDS)

    thread = threading.Thread(target=loop, name=f"lane-{huey.name}", daemon=True)
    thread.start()
    return thread


def lower_priority(niceness: int) -> None:
    """Add ``niceness`` to this process's nice value (0: nothing): jobs are batch work, so a
    worker beside an API on the same cores leaves tiles the CPU (Linux CFS weights: at nice
    10 a busy worker thread gets about a tenth of what a busy API thread gets)."""
    if niceness <= 0:
        return
    try:
        os.nice(niceness)
    except OSError:  # not permitted here: run at the normal priority
        log.warning("could not lower the worker's priority by %s", niceness)


def run_worker(settings: Settings, *, migrate: bool = True) -> None:
    """Consume the lanes of ``settings.worker_kinds`` until SIGINT / SIGTERM: the first
    with ``settings.workers`` threads, the fit lane beside it (if both) with one, all at
    ``settings.worker_nice`` lower priority than the API."""
    lower_priority(settings.worker_nice)
    services = build_services(settings, migrate=migrate)
    try:
        services.registry  # load models now, not inside the first job
    except Exception:  # a missing model fails each job with a problem; keep consuming
        log.exception("model registry not loaded")
    stop = threading.Event()
    start_reaper(services, stop)
    hueys = {"main": services.huey, "fit": services.fit_huey}
    first, *others = worker_lanes(settings)
    for lane in others:
        start_lane(hueys[lane], stop)
    consumer = hueys[first].create_consumer(workers=settings.workers, worker_type="thread", periodic=False,
                                            initial_delay=0.05, max_delay=0.5, graceful_signal="INT")
    log.info("worker started", extra={"workers": settings.workers, "queue": settings.queue_backend,
                                      "kinds": settings.worker_kinds, "worker_id": services.worker_id})
    try:
        consumer.run()
    finally:
        stop.set()
        try:
            released = release_worker(services)
            if released:
                log.info("handed running jobs back to the queue", extra={"jobs": released})
        except Exception:  # the reaper will re-queue them when their leases expire
            log.exception("could not release running jobs")


def _die_with_parent() -> None:
    """In the child, before exec: get SIGTERM when the parent dies (Linux), because
    uvicorn re-raises SIGTERM after its shutdown and our ``finally`` never runs."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:  # not Linux: the finally below still stops the worker on normal exits
        pass


def run_serve(settings: Settings) -> None:
    """Migrate, start one worker process (restarted if it dies), and run the API here."""
    settings.ensure_dirs()
    db.migrate(settings.resolved_database_url)
    command = [sys.executable, "-m", "service.cli", "worker", "--no-migrate"]
    stopping = threading.Event()
    state: dict[str, subprocess.Popen] = {}

    def supervise() -> None:
        while not stopping.is_set():
            proc = subprocess.Popen(command, env=os.environ.copy(), preexec_fn=_die_with_parent)
            state["proc"] = proc
            log.info("worker process started", extra={"pid": proc.pid})
            while proc.poll() is None and not stopping.is_set():
                time.sleep(0.2)
            if not stopping.is_set():
                log.warning("worker process exited (code %s); restarting", proc.returncode)
                time.sleep(0.5)

    supervisor = threading.Thread(target=supervise, name="worker-supervisor", daemon=True)
    supervisor.start()
    try:
        run_api(settings)
    finally:
        stopping.set()
        proc = state.get("proc")
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
