"""FastAPI dependencies: the shared services, typed parameter groups, pagination."""
from __future__ import annotations

import base64
import datetime as dt
import json
import unicodedata
from dataclasses import dataclass
from typing import Annotated, Literal

from fastapi import Depends, Header, Path, Query, Request
from pydantic import AfterValidator
from sqlalchemy import Select, and_, or_

from worker.tiles import COORD_LIMIT, MAX_TILE_SIZE, MAX_ZOOM, MIN_TILE_SIZE, MIN_ZOOM, PLANES, TILE_FORMATS

from .container import Services
from .errors import Problem

Plane = Literal[PLANES]
TileFormat = Literal[TILE_FORMATS]


def printable(value: str) -> str:
    """``value`` unchanged, or ValueError (a 422) if it holds a control character (NUL
    included: PostgreSQL text cannot store it) or a lone surrogate (not UTF-8)."""
    for char in value:
        if unicodedata.category(char) in ("Cc", "Cs"):
            raise ValueError(f"control characters are not allowed (found U+{ord(char):04X})")
    return value


#: free text and ids from clients: refused at the edge (422) when they hold control characters
SafeText = Annotated[str, AfterValidator(printable)]
TextureId = Annotated[SafeText, Path(description="texture id")]
JobId = Annotated[SafeText, Path(description="job id")]


def get_services(request: Request) -> Services:
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]


def public_base_url(request: Request, services: Services) -> str:
    """The API's public URL, no trailing slash: TEXSPACE_PUBLIC_BASE_URL where set, never
    the client's Host header then; else the URL the request came to."""
    return (services.settings.public_base_url or str(request.base_url)).rstrip("/")


@dataclass
class TileParams:
    """Where and how to render one tile (docs/ARCHITECTURE.md, Contract 2)."""

    seed: Annotated[int, Query(ge=0, le=2**31 - 1, description="texture instance")] = 0
    size: Annotated[int, Query(ge=MIN_TILE_SIZE, le=MAX_TILE_SIZE, description="tile side in pixels")] = 256
    plane: Annotated[Plane, Query(description="which world plane the tile lies in")] = "xy"
    offset: Annotated[float, Query(ge=-1e9, le=1e9, description="plane position on the third axis (world units)")] = 0.0


@dataclass
class TileAddress:
    z: int
    x: int
    y: int


def tile_address(
    z: Annotated[int, Path(ge=MIN_ZOOM, le=MAX_ZOOM, description="zoom level")],
    x: Annotated[int, Path(ge=-COORD_LIMIT, le=COORD_LIMIT, description="tile column, grows right")],
    y: Annotated[int, Path(ge=-COORD_LIMIT, le=COORD_LIMIT, description="tile row, grows down")],
) -> TileAddress:
    """Path parameters, checked against the zoom range and the coordinate limit."""
    return TileAddress(z, x, y)


def idempotency_key(
    key: Annotated[str | None, Header(alias="Idempotency-Key", max_length=200,
                                      description="repeat a submission safely: the same key returns the same job")] = None,
) -> str | None:
    return key


@dataclass
class PageParams:
    limit: Annotated[int, Query(ge=1, le=200, description="items per page")] = 50
    cursor: Annotated[SafeText | None, Query(max_length=200, description="next_cursor of the previous page")] = None


def encode_cursor(created_at: dt.datetime, ident: str) -> str:
    return base64.urlsafe_b64encode(json.dumps([created_at.isoformat(), ident]).encode()).decode().rstrip("=")


def apply_cursor(query: Select, table, page: PageParams) -> Select:  # noqa: ANN001
    """Newest first; a cursor resumes after the last item of the previous page."""
    query = query.order_by(table.created_at.desc(), table.id.desc()).limit(page.limit + 1)
    if not page.cursor:
        return query
    try:
        padded = page.cursor + "=" * (-len(page.cursor) % 4)
        stamp, ident = json.loads(base64.urlsafe_b64decode(padded))
        if not isinstance(stamp, str) or not isinstance(ident, str):  # a tampered cursor: 422, not 500
            raise TypeError("cursor fields must be strings")
        created = dt.datetime.fromisoformat(printable(stamp))
        printable(ident)
    except (ValueError, TypeError) as exc:
        raise Problem(422, "invalid cursor", slug="validation-error") from exc
    return query.where(or_(table.created_at < created, and_(table.created_at == created, table.id < ident)))


def page_of(rows: list, page: PageParams) -> tuple[list, str | None]:
    """Split the limit+1 rows fetched into this page and the next cursor."""
    if len(rows) > page.limit:
        rows = rows[:page.limit]
        return rows, encode_cursor(rows[-1].created_at, rows[-1].id)
    return rows, None
