"""Structured logs: one JSON object per line, carrying the request id and job id.

The ids live in context variables set by the request middleware and the job runner,
so every log call below them is tagged without passing ids around.
"""
from __future__ import annotations

import contextvars
import datetime as dt
import json
import logging
import sys

request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar("request_id", default=None)
job_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar("job_id", default=None)

# attributes every LogRecord has; anything else was passed with extra= and is logged
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime", "taskName"}


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": dt.datetime.fromtimestamp(record.created, dt.timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if (rid := request_id_var.get()) is not None and "request_id" not in vars(record):
            entry["request_id"] = rid
        if (jid := job_id_var.get()) is not None:
            entry["job_id"] = jid
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class ContextFormatter(logging.Formatter):
    """Plain text for people at a terminal, still with the ids."""

    def format(self, record: logging.LogRecord) -> str:
        ids = " ".join(f"{k}={v}" for k, v in (("req", request_id_var.get()), ("job", job_id_var.get())) if v)
        base = super().format(record)
        return f"{base} [{ids}]" if ids else base


class StderrHandler(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is when a record is emitted, not as it was at set-up:
    an embedder (or a test harness) that swaps stderr and closes the old one after a command
    ran would otherwise leave every later log line failing on a closed stream."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)  # (StreamHandler's would fix the stream now)

    @property
    def stream(self):  # noqa: ANN201 (a text stream)
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # noqa: ANN001 (StreamHandler.setStream assigns it)
        raise AttributeError("StderrHandler always writes to the current sys.stderr")


def setup_logging(level: str = "INFO", json_lines: bool = True) -> None:
    """Send all logs (ours, uvicorn's, huey's) to stderr in one format."""
    handler = StderrHandler()
    handler.setFormatter(JsonFormatter() if json_lines else
                         ContextFormatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access", "huey", "huey.consumer"):
        logger = logging.getLogger(name)
        logger.handlers[:] = []
        logger.propagate = True
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
    # our request middleware logs each request with its id; uvicorn's access log would repeat it
    logging.getLogger("uvicorn.access").disabled = True
