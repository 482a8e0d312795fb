"""Tile rendering for the API: strong ETags, the LRU, and the call into worker/tiles."""
from __future__ import annotations

import asyncio
import contextvars
import functools
import hashlib
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from worker.images import write_image
from worker.errors import LimitExceeded
from worker.tiles import render_tile, supersample_for

from .container import Services
from .db import session_scope
from .settings import Settings
from .tables import Job, Texture

#: bump when tile rendering changes in a way that changes bytes for the same URL
TILE_RENDER_VERSION = 1
TILE_MEDIA_TYPES = {"png": "image/png", "webp": "image/webp", "exr": "image/x-exr"}
CACHE_CONTROL = "public, max-age=31536000, immutable"
#: tiles of an upload whose refinement has not ended: caches must revalidate (If-None-Match)
REFINING_CACHE_CONTROL = "public, no-cache"


#: tiles of at most this many sampler calls are small: they never queue behind large ones
SMALL_TILE_SAMPLES = 1 << 18
#: a large tile renders in bands of about this many sampler calls, and before each band
#: waits while small tiles render, so one costs a small tile at most about one band
BAND_SAMPLES = 1 << 15


def tile_samples(z: int, size: int) -> int:
    """Sampler calls of one tile: (size x supersampling factor)^2."""
    return (size * supersample_for(z)) ** 2


def check_tile_work(settings: Settings, z: int, size: int) -> None:
    """LimitExceeded (413) when a tile costs more sampler calls than ``max_tile_samples``."""
    samples = tile_samples(z, size)
    if samples > settings.max_tile_samples:
        raise LimitExceeded(f"a {size} px tile at zoom {z} costs {samples} samples ({supersample_for(z)}^2 "
                            f"per pixel), limit is {settings.max_tile_samples}: use a smaller size "
                            "or a higher zoom")


class TileLanes:
    """Small tiles first: large ones render one at a time on a thread of their own (queued
    ones hold none of the threads small tiles run on), band by band, each band waiting until
    no small tile is rendering (the sampler's pool is first-come-first-served)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._small = 0
        self.large = ThreadPoolExecutor(1, thread_name_prefix="large-tiles")

    @contextmanager
    def small(self):  # noqa: ANN201
        with self._cond:
            self._small += 1
        try:
            yield
        finally:
            with self._cond:
                self._small -= 1
                self._cond.notify_all()

    def yield_to_small(self) -> None:
        with self._cond:
            self._cond.wait_for(lambda: self._small == 0)


LANES = TileLanes()


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


async def render_tile_async(services: Services, texture: Texture, **key) -> bytes:  # noqa: ANN003
    """``render_tile_bytes`` off the event loop: small tiles on the threadpool, large
    ones on their own lane (TileLanes)."""
    if tile_samples(key["z"], key["size"]) <= SMALL_TILE_SAMPLES:
        return await run_in_threadpool(render_tile_bytes, services, texture, **key)
    context = contextvars.copy_context()  # the request id of log lines, as run_in_threadpool does
    render = functools.partial(render_tile_bytes, services, texture, **key)
    return await asyncio.get_running_loop().run_in_executor(LANES.large, context.run, render)


def render_tile_bytes(services: Services, texture: Texture, *, z: int, x: int, y: int, size: int,
                      seed: int, plane: str, offset: float, fmt: str) -> bytes:
    """Render and encode one tile (CPU-bound: call from a worker thread)."""
    started = time.perf_counter()
    args = (services.sampler_for(texture), texture.sampling_code(), seed, z, x, y, size)
    kwargs = dict(pixels_per_unit=services.pixels_per_unit(texture), plane=plane, offset=offset)
    if tile_samples(z, size) <= SMALL_TILE_SAMPLES:
        with LANES.small():
            rgb = render_tile(*args, **kwargs)
    else:
        rgb = render_tile(*args, **kwargs, band_samples=BAND_SAMPLES, before_band=LANES.yield_to_small)
    data = write_image(rgb, fmt)
    services.metrics.tile_render.observe(time.perf_counter() - started)
    return data
