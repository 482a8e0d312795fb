"""ASGI middleware: request id (X-Request-ID in and out), metrics, access log, a
request body limit enforced while the body streams in, HEAD wherever GET (RFC 9110), and
the 500 problem for an unexpected error (answered here, so it carries the request id)."""
from __future__ import annotations

import logging
import re
import time
import uuid

from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect, Request

from .errors import Problem, log_unhandled, problem_for, problem_response
from .logs import request_id_var
from .metrics import Metrics

log = logging.getLogger("service.access")
error_log = logging.getLogger("service.errors")
_SAFE_ID = re.compile(r"^[A-Za-z0-9._:\-]{1,128}$")
#: metric label values for methods; any other method is counted as "other" (one series)
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "TRACE", "CONNECT"})


class _HeadDone(OSError):
    """Raised from ``send`` once a HEAD answer is complete: stops a streaming GET body."""


class BodyTooLarge(StarletteHTTPException):
    """Raised from ``receive``: an HTTPException, so FastAPI's body parsing re-raises it
    as is and the error handlers turn it into a 413 problem."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than the limit of {limit} bytes")


class RequestContextMiddleware:
    """Pure ASGI (no buffering) so SSE and file streams pass through untouched."""

    def __init__(self, app, *, metrics: Metrics, max_body_bytes: int) -> None:  # noqa: ANN001
        self.app = app
        self.metrics = metrics
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope, receive, send) -> None:  # noqa: ANN001
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        incoming = headers.get(b"x-request-id", b"").decode("latin-1")
        request_id = incoming if _SAFE_ID.match(incoming) else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status = {"code": 500, "sent": False, "done": False}
        method = scope["method"]
        head = method == "HEAD"
        if head:  # answered by the GET route, without its body
            scope = dict(scope, method="GET")

        async def send_with_id(message) -> None:  # noqa: ANN001
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                status["sent"] = True
                message.setdefault("headers", [])
                message["headers"] = list(message["headers"]) + [(b"x-request-id", request_id.encode())]
            elif head and message["type"] == "http.response.body":
                if status["done"]:
                    if message.get("more_body", False):
                        raise _HeadDone()
                    return
                status["done"] = True
                message = {"type": "http.response.body", "body": b"", "more_body": False}
            await send(message)

        received = 0

        async def limited_receive():  # noqa: ANN202
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise BodyTooLarge(self.max_body_bytes)
            return message

        try:
            length = int(headers.get(b"content-length", b"0") or 0)
            if length > self.max_body_bytes:
                raise BodyTooLarge(self.max_body_bytes)
            await self.app(scope, limited_receive, send_with_id)
        except BodyTooLarge:
            if not status["sent"]:
                problem = Problem(413, f"request body larger than {self.max_body_bytes} bytes",
                                  slug="limit-exceeded")
                await problem_response(problem)(scope, receive, send_with_id)
        except (_HeadDone, ClientDisconnect):
            if not status["done"]:
                raise
        except Exception as exc:  # here, not in Starlette's outer handler: the id is still ours
            if status["sent"]:
                raise
            problem = problem_for(exc)
            log_unhandled(error_log, problem, exc, method, scope["path"])
            await problem_response(problem, Request(scope))(scope, receive, send_with_id)
        finally:
            route = scope.get("route")
            route_path = getattr(route, "path", None) or "unmatched"
            elapsed = time.perf_counter() - started
            label = method if method in KNOWN_METHODS else "other"
            self.metrics.requests.labels(label, route_path, str(status["code"])).inc()
            self.metrics.latency.labels(label, route_path).observe(elapsed)
            log.info("%s %s %s", method, scope["path"], status["code"],
                     extra={"status": status["code"], "ms": round(elapsed * 1000, 2), "route": route_path,
                            "request_id": request_id})
            request_id_var.reset(token)
