"""Tile rendering for the API: strong ETags, the LRU, and the call into worker/tiles."""
from __future__ import annotations

import hashlib
import time

import numpy as np
from sqlalchemy import select

from worker.images import write_image
from worker.tiles import render_tile

from .context import Services
from .db import session_scope
from .tables import Job, Texture

#: bump when tile rendering changes in a way that changes bytes for the same URL
TILE_RENDER_VERSION = 1
TILE_MEDIA_TYPES = {"png": "image/png", "webp": "image/webp", "exr": "image/x-exr"}
CACHE_CONTROL = "public, max-age=31536000, immutable"
#: tiles of an upload whose refinement has not ended: caches must revalidate (If-None-Match)
REFINING_CACHE_CONTROL = "public, no-cache"


def tile_etag(texture: Texture, *, z: int, x: int, y: int, size: int, seed: int, plane: str,
              offset: float, fmt: str) -> str:
    """Strong ETag: every input that changes the bytes, including the model version."""
    parts = (TILE_RENDER_VERSION, texture.model_version, texture.id, texture.sampler_key or "",
             seed, z, x, y, size, plane, repr(float(offset)), fmt)
    return '"' + hashlib.sha256("|".join(map(str, parts)).encode()).hexdigest()[:32] + '"'


def tiles_final(services: Services, texture: Texture) -> bool:
    """False while the texture's in-place refinement may still replace its sampler, so
    that its tile URLs will serve new bytes (under new ETags) once the job succeeds."""
    if texture.sampler_key or not texture.refinement_job_id:
        return True
    with session_scope(services.sessions) as session:
        state = session.scalar(select(Job.state).where(Job.id == texture.refinement_job_id))
    return state is None or state in ("failed", "canceled")  # succeeded: this row was read before


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """RFC 9110 If-None-Match (weak comparison): '*' or any listed tag equal to ours."""
    if not if_none_match:
        return False
    tags = [t.strip() for t in if_none_match.split(",")]
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)


def render_tile_bytes(services: Services, texture: Texture, *, z: int, x: int, y: int, size: int,
                      seed: int, plane: str, offset: float, fmt: str) -> bytes:
    """Render and encode one tile (CPU-bound: call from a worker thread)."""
    started = time.perf_counter()
    rgb = render_tile(services.sampler_for(texture), texture.sampling_code(), seed, z, x, y,
                      size, pixels_per_unit=services.pixels_per_unit(texture), plane=plane, offset=offset)
    data = write_image(rgb, fmt)
    services.metrics.tile_render.observe(time.perf_counter() - started)
    return data
