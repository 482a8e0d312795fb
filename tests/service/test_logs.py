"""Structured logs: one JSON object per line with the request id and job id."""
from __future__ import annotations

import io
import json
import logging
import sys

import pytest

from service.logs import JsonFormatter, job_id_var, request_id_var, setup_logging


def format_record(message: str, **extra) -> dict:
    record = logging.LogRecord("t", logging.INFO, __file__, 1, message, (), None)
    for key, value in extra.items():
        setattr(record, key, value)
    return json.loads(JsonFormatter().format(record))


def test_json_lines_carry_context_ids_and_extras() -> None:
    r, j = request_id_var.set("req-1"), job_id_var.set("job-9")
    try:
        entry = format_record("job started", attempt=2)
    finally:
        request_id_var.reset(r)
        job_id_var.reset(j)
    assert entry["message"] == "job started" and entry["level"] == "INFO"
    assert entry["request_id"] == "req-1" and entry["job_id"] == "job-9" and entry["attempt"] == 2
    assert "request_id" not in format_record("outside any request")


def test_access_log_has_request_id(client, caplog) -> None:
    with caplog.at_level(logging.INFO, logger="service.access"):
        client.get("/healthz", headers={"X-Request-ID": "trace-me"})
    record = next(r for r in caplog.records if r.name == "service.access")
    assert record.status == 200 and record.route == "/healthz"
    entry = json.loads(JsonFormatter().format(record))
    assert entry["status"] == 200 and entry["request_id"] == "trace-me"


def test_set_up_logs_follow_stderr_as_it_is_now(monkeypatch) -> None:
    """A command's logging set-up must not bind the stderr of that moment: a test harness (or
    an embedder) that swaps stderr and closes the old one would get every later line failing
    on a closed stream."""
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", root.handlers[:])  # restored after, as the level is
    monkeypatch.setattr(root, "level", root.level)
    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    setup_logging("INFO", json_lines=True)
    logging.getLogger("texspace.test").info("one")
    monkeypatch.setattr(sys, "stderr", second)
    first.close()
    logging.getLogger("texspace.test").info("two")
    assert [json.loads(line)["message"] for line in second.getvalue().splitlines()] == ["two"]
    with pytest.raises(AttributeError):
        root.handlers[0].setStream(io.StringIO())
