"""The one table from domain errors to RFC 9457 ``application/problem+json`` responses.

``worker/`` and ``model/`` raise plain exceptions (``worker/errors.py``); routes raise
:class:`Problem` for HTTP-level cases (not found, conflict). Everything leaves the API
as a problem document with a useful ``detail``.
"""
from __future__ import annotations

import errno
import logging
import sqlite3
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy import exc as database
from starlette.exceptions import HTTPException as StarletteHTTPException

from worker import errors as domain

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:texspace:problem:"
BODY_PARSE_ERROR = "There was an error parsing the body"  # FastAPI's 400 for bodies it cannot decode


#: Retry-After of a request the database failed: PostgreSQL restarts in seconds, and the
#: pool's pre-ping replaces the dropped connections on the next checkout
DATABASE_RETRY_AFTER_SECONDS = 5
#: what a client is told instead of the driver's message, which names hosts, files and SQL
DATABASE_DETAIL = f"the database did not answer; retry in {DATABASE_RETRY_AFTER_SECONDS} s"


class ClientGone(domain.TexspaceError):
    """The client closed the connection before its response was ready; its work was dropped."""


#: domain exception class -> (HTTP status, problem type slug, title)
ERROR_TABLE: dict[type[Exception], tuple[int, str, str]] = {
    ClientGone: (499, "client-closed-request", "The client closed the request"),
    domain.InvalidImage: (422, "invalid-image", "The image cannot be used"),
    domain.InvalidMesh: (422, "invalid-mesh", "The mesh cannot be used"),
    domain.InvalidParameter: (422, "invalid-parameter", "A parameter is out of range"),
    domain.LimitExceeded: (413, "limit-exceeded", "A size limit was exceeded"),
    domain.AtlasFailed: (422, "atlas-failed", "The mesh could not be UV-unwrapped"),
    domain.Canceled: (409, "canceled", "The job was canceled"),
    domain.ModelNotFound: (503, "model-unavailable", "The texture's model is not loaded"),
    domain.Busy: (503, "busy", "The service is busy; retry later"),
    domain.InsufficientStorage: (507, "insufficient-storage", "The server's storage is full"),
    domain.ModelInvalid: (500, "model-invalid", "A model export is broken"),
    domain.FeatureUnavailable: (501, "feature-unavailable", "This feature is not installed"),
    domain.TexspaceError: (400, "bad-request", "The request cannot be processed"),
    # The database did not answer: down, restarting, out of connections (the pool's wait),
    # or SQLite locked past its busy timeout. Not the request's fault, nor the service's.
    database.OperationalError: (503, "database-unavailable", "The database is unavailable"),
    database.InterfaceError: (503, "database-unavailable", "The database is unavailable"),
    database.DisconnectionError: (503, "database-unavailable", "The database is unavailable"),
    database.TimeoutError: (503, "database-unavailable", "The database is unavailable"),
}


class Problem(Exception):
    """An HTTP-level problem raised by routes (not found, conflict, ...)."""

    def __init__(self, status: int, detail: str, *, slug: str | None = None,
                 title: str | None = None, headers: dict[str, str] | None = None,
                 **extra: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.slug = slug or HTTPStatus(status).phrase.lower().replace(" ", "-")
        self.title = title or HTTPStatus(status).phrase
        self.headers = headers
        self.extra = extra

    def to_dict(self, instance: str | None = None) -> dict[str, Any]:
        body = {"type": TYPE_PREFIX + self.slug, "title": self.title, "status": self.status,
                "detail": self.detail}
        if instance:
            body["instance"] = instance
        body.update(self.extra)
        return body


def not_found(what: str, ident: str) -> Problem:
    return Problem(404, f"{what} {ident!r} does not exist", slug="not-found")


STORAGE_FULL_DETAIL = ("the server's storage is full, so nothing was stored; deleting textures frees "
                       "space, or retry once an operator has added some")
_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}
_NO_SPACE = "No space left on device"  # strerror(ENOSPC), in the messages of writers that drop the errno
_SQLITE_FULL = "database or disk is full"  # SQLITE_FULL's message
_POSTGRES_DISK_FULL = "53100"  # SQLSTATE disk_full


def storage_full(exc: BaseException) -> domain.InsufficientStorage | None:
    """The domain error ``exc`` stands for when a write failed for lack of space, else None.

    Space errors come from everywhere a byte is written, so they are recognised here, on
    the way out, through the chain of causes (SQLAlchemy keeps the driver's error as
    ``orig``): an OSError with ENOSPC or EDQUOT (or its message, from writers such as
    OpenImageIO that drop the errno), SQLite's "database or disk is full" (the database
    and the SQLite queue) and PostgreSQL's disk_full. Their messages name server paths;
    the problem says what happened instead.
    """
    seen, pending = set(), [exc]
    while pending:
        error = pending.pop()
        if error is None or id(error) in seen:
            continue
        seen.add(id(error))
        if isinstance(error, domain.InsufficientStorage):
            return error
        if (isinstance(error, OSError) and (error.errno in _FULL_ERRNOS or _NO_SPACE in str(error))
                or isinstance(error, sqlite3.OperationalError) and _SQLITE_FULL in str(error)
                or getattr(error, "sqlstate", None) == _POSTGRES_DISK_FULL):
            return domain.InsufficientStorage(STORAGE_FULL_DETAIL)
        pending += [getattr(error, "orig", None), error.__cause__, error.__context__]
    return None


def problem_for(exc: BaseException) -> Problem:
    """The problem a domain (or unexpected) exception stands for."""
    if isinstance(exc, Problem):
        return exc
    if not isinstance(exc, domain.TexspaceError):
        exc = storage_full(exc) or exc
    for cls in type(exc).__mro__:
        if cls in ERROR_TABLE:
            status, slug, title = ERROR_TABLE[cls]
            if isinstance(exc, domain.TexspaceError):
                detail, retry = exc.detail, getattr(exc, "retry_after", None)
            else:       # the database's errors, the table's only others
                detail, retry = DATABASE_DETAIL, DATABASE_RETRY_AFTER_SECONDS
            return Problem(status, detail, slug=slug, title=title,
                           headers={"Retry-After": str(retry)} if retry else None)
    return Problem(500, "internal error; the request id in the logs tells more", slug="internal-error")


def problem_response(problem: Problem, request: Request | None = None) -> JSONResponse:
    instance = str(request.url.path) if request is not None else None
    return JSONResponse(problem.to_dict(instance), status_code=problem.status,
                        media_type=PROBLEM_MEDIA_TYPE, headers=problem.headers)


def install_error_handlers(app: FastAPI) -> None:
    """Make every error leave the app as problem+json."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return problem_response(exc, request)

    @app.exception_handler(domain.TexspaceError)
    async def _domain(request: Request, exc: domain.TexspaceError) -> JSONResponse:
        return problem_response(problem_for(exc), request)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")}
                  for e in exc.errors()]
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors) or "invalid request"
        return problem_response(Problem(422, detail, slug="validation-error",
                                        title="Request validation failed", errors=errors), request)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        if exc.status_code == 400:  # FastAPI / Starlette could not parse the body: a validation error
            if detail == BODY_PARSE_ERROR:
                detail = "the request body cannot be decoded (expected UTF-8 JSON)"
            return problem_response(Problem(422, f"invalid request body: {detail}", slug="validation-error",
                                            title="Request validation failed"), request)
        slug = "limit-exceeded" if exc.status_code == 413 else None  # same type as LimitExceeded
        return problem_response(Problem(exc.status_code, detail, slug=slug, headers=getattr(exc, "headers", None)),
                                request)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        problem = problem_for(exc)
        log_unhandled(log, problem, exc, request.method, request.url.path)
        return problem_response(problem, request)


def log_unhandled(logger: logging.Logger, problem: Problem, exc: BaseException, method: str, path: str) -> None:
    """A bug's traceback; one line for a known outage (a database that is down fails every
    request while it is: a traceback each would bury the log)."""
    if problem.slug == "internal-error":
        logger.error("unhandled error on %s %s", method, path, exc_info=exc)
    else:
        logger.warning("%s on %s %s: %s", problem.slug, method, path, type(exc).__name__)


class ProblemDetails(BaseModel):
    """RFC 9457 problem document."""

    type: str = Field(description="URI naming the kind of problem")
    title: str
    status: int
    detail: str = Field(description="what went wrong, for a person")
    instance: str | None = None


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries for problem documents (media type fixed in main)."""
    return {code: {"description": HTTPStatus(code).phrase, "model": ProblemDetails} for code in codes}
