"""Structured logs: one JSON object per line with the request id and job id."""
from __future__ import annotations

import json
import logging

from service.logs import JsonFormatter, job_id_var, request_id_var


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
