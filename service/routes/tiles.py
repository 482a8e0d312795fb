"""Tiles of the infinite plane (docs/ARCHITECTURE.md, Contract 2) and their TileJSON."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request, Response
from starlette.concurrency import run_in_threadpool

from worker.errors import LimitExceeded
from worker.files import media_type
from worker.tiles import MAX_ZOOM, MIN_ZOOM, NATIVE_ZOOM, TILE_FORMATS

from .. import auth
from ..deps import ServicesDep, TileAddress, TileFormat, TileParams, public_base_url, tile_address
from ..errors import problem_responses
from ..schemas import TileJSON
from ..tiles import (CACHE_CONTROL, PREVIEW_CACHE_CONTROL, PREVIEW_HEADER, REFINING_CACHE_CONTROL,
                     check_tile_work, final_tile, progressive_tile, serves_previews, tiles_final)
from .textures import load_texture

router = APIRouter(prefix="/v1/textures", tags=["tiles"])


@router.get(
    "/{texture_id}/tiles/{z}/{x}/{y}.{fmt}",
    response_class=Response,
    description=(f"Tile (z, x, y) of the texture's infinite plane; x and y may be negative. At zoom "
                 f"{NATIVE_ZOOM} one tile pixel is one exemplar pixel; each zoom step doubles the pixels "
                 f"per world unit (zoom {MIN_ZOOM}..{MAX_ZOOM}). Same URL, same bytes: strong ETag, "
                 "immutable caching, 304 on If-None-Match; a zoomed-out tile may first come as a preview "
                 "(X-Texspace-Tile: preview, no-cache) until its exact render is ready."),
    responses={200: {"description": "the tile image", "content": {media_type(f): {} for f in TILE_FORMATS}},
               304: {"description": "unchanged (If-None-Match)"}, **problem_responses(404, 413, 422, 503)},
)
async def get_tile(
    services: ServicesDep,
    request: Request,
    texture_id: str,
    fmt: TileFormat,
    address: Annotated[TileAddress, Depends(tile_address)],
    params: Annotated[TileParams, Depends()],
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    if params.size > services.settings.max_tile_size:
        raise LimitExceeded(f"tile size {params.size} exceeds the limit of {services.settings.max_tile_size}")
    check_tile_work(services.settings, address.z, params.size)
    texture = await run_in_threadpool(load_texture, services, texture_id)
    key = dict(z=address.z, x=address.x, y=address.y, size=params.size, seed=params.seed,
               plane=params.plane, offset=params.offset, fmt=fmt)
    cache_control = CACHE_CONTROL
    refining = texture.refinement_may_replace_sampler()  # else final: no query
    if refining and not await run_in_threadpool(tiles_final, services, texture):
        cache_control = REFINING_CACHE_CONTROL  # same ETag, same bytes; the URL's bytes will change
    if serves_previews(services.settings, address.z):
        etag, data, preview = await progressive_tile(services, texture, request, if_none_match, key)
    else:
        (etag, data), preview = await final_tile(services, texture, request, if_none_match, key), False
    headers = {"ETag": etag, "Cache-Control": PREVIEW_CACHE_CONTROL if preview else cache_control}
    if preview:
        headers[PREVIEW_HEADER[0]] = PREVIEW_HEADER[1]
    # with API keys, a tenant's tiles must not be served to others by a shared cache
    if auth.current_owner() is not None:
        headers["Cache-Control"] = headers["Cache-Control"].replace("public", "private")
    if data is None:
        services.metrics.tile_not_modified.inc()
        return Response(status_code=304, headers=headers)
    return Response(content=data, media_type=media_type(fmt), headers=headers)


@router.get("/{texture_id}/tilejson.json", response_model=TileJSON, responses=problem_responses(404, 422))
def get_tilejson(services: ServicesDep, request: Request, texture_id: str,
                 params: Annotated[TileParams, Depends()]) -> TileJSON:
    """TileJSON 3.0 for map viewers (Leaflet, OpenLayers, MapLibre) with a simple CRS."""
    texture = load_texture(services, texture_id)
    base = public_base_url(request, services)  # TEXSPACE_PUBLIC_BASE_URL, else the request's own
    query = f"seed={params.seed}&size={params.size}"
    if params.plane != "xy" or params.offset:
        query += f"&plane={params.plane}&offset={params.offset:g}"
    return TileJSON(name=texture.name or texture.id,
                    tiles=[f"{base}/v1/textures/{texture.id}/tiles/{{z}}/{{x}}/{{y}}.png?{query}"],
                    minzoom=MIN_ZOOM, maxzoom=MAX_ZOOM, tileSize=params.size,
                    bounds=[-180.0, -85.0511287798066, 180.0, 85.0511287798066],
                    center=[0.0, 0.0, float(NATIVE_ZOOM)])
