"""Tile rendering for the API: strong ETags, the LRU, and the call into worker/tiles."""
from __future__ import annotations

import asyncio
import contextvars
import functools
import hashlib
import logging
import math
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from worker.images import write_image
from worker.errors import Busy, LimitExceeded
from worker.tiles import NATIVE_ZOOM, exact_parent, parent_from_children, render_tile, supersample_for

from . import jobs
from .container import Services
from .errors import ClientGone
from .samplers import sampler_inputs, sampling_code
from .settings import Settings
from .tables import Texture
from .tilecache import TileCache

log = logging.getLogger(__name__)

#: bump when tile rendering changes in a way that changes bytes for the same URL
#: (2: box filter as a cascade of exact 2 x 2 means, so parents can be built from children)
TILE_RENDER_VERSION = 2
CACHE_CONTROL = "public, max-age=31536000, immutable"
#: tiles of an upload whose refinement has not ended: caches must revalidate (If-None-Match)
REFINING_CACHE_CONTROL = "public, no-cache"
#: a zoomed-out tile's preview (progressive zoom-out): revalidated, the exact tile replaces it
PREVIEW_CACHE_CONTROL = "public, no-cache"
#: response header naming a preview; clients that can read headers ask again until it is gone
PREVIEW_HEADER = ("X-Texspace-Tile", "preview")


#: the unit of tile cost: the sampler calls of a 256 px tile at native zoom. Queue depths
#: count tiles in these units (``tile_units``): a 512 px tile is 4, a 1024 px one 16.
TILE_UNIT_SAMPLES = 256 ** 2
#: tiles of at most this many sampler calls are small: they never queue behind large ones.
#: One unit: a 512 px tile costs four 256 px ones, and two of them holding both render
#: slots made every 256 px tile behind them wait past the bound (6 of 6 answered 503).
SMALL_TILE_SAMPLES = TILE_UNIT_SAMPLES
#: a large tile renders in bands of about this many sampler calls, and before each band
#: waits while small tiles render, so one costs a small tile at most about one band
BAND_SAMPLES = 1 << 15
#: the longest a large tile's band waits for small tiles to finish
YIELD_SECONDS = 0.25


#: the most exact zoomed-out tiles waiting to render behind their previews; beyond, the
#: oldest is dropped (it renders when next asked for)
MAX_PENDING_EXACT = 64
#: the longest a background band waits for interactive tiles to finish (then one band runs)
BACKGROUND_YIELD_SECONDS = 2.0


def tile_samples(z: int, size: int, zoom_out: str = "supersample") -> int:
    """Sampler calls of one tile: (size x supersampling factor)^2, or size^2 when zoom-out is
    ``bounded`` (one sub-sample per pixel)."""
    return size ** 2 if zoom_out == "bounded" else (size * supersample_for(z)) ** 2


def tile_units(samples: int) -> int:
    """A tile's weight in queue depths: its sampler calls in units of a 256 px native tile,
    rounded up (a smaller tile counts one)."""
    return max(1, math.ceil(samples / TILE_UNIT_SAMPLES))


def final_zoom_out(settings: Settings) -> str:
    """How a tile's final (cacheable) bytes are rendered: ``bounded`` in that mode, else
    ``supersample`` (progressive mode's previews are bounded, its final tiles supersampled)."""
    return "bounded" if settings.tile_zoom_out == "bounded" else "supersample"


def serves_previews(settings: Settings, z: int) -> bool:
    """Whether a cold tile at zoom z is answered with a preview first (progressive mode)."""
    return settings.tile_zoom_out == "progressive" and z < NATIVE_ZOOM


def check_tile_work(settings: Settings, z: int, size: int) -> None:
    """LimitExceeded (413) when a tile costs more sampler calls than ``max_tile_samples``."""
    samples = tile_samples(z, size, final_zoom_out(settings))
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

    def yield_to_small(self, timeout: float = YIELD_SECONDS) -> None:
        """Wait until no small tile renders, at most ``timeout`` s: under a steady stream of
        small tiles a large one still advances a band at a time instead of starving."""
        with self._cond:
            self._cond.wait_for(lambda: self._small == 0, timeout=timeout)


LANES = TileLanes()

#: seconds between two looks at whether a waiting or rendering tile's client is still there
DISCONNECT_POLL_SECONDS = 0.1


class TileQueue:
    """Admission of cold tiles, in arrival order: at most ``tile_workers`` small tiles render
    at once, the rest wait here (on the event loop, holding no thread) while their client is
    connected. A tile that would wait behind ``tile_queue_depth`` units of tiles
    (``tile_units``), or longer than ``tile_queue_max_wait_seconds`` by the measured render
    rate, gets Busy (503 + Retry-After) at once. Large tiles have their own lane (TileLanes)
    and bound (``large``): their work is not counted in a small tile's wait, since their
    bands wait for small tiles."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running = 0
        self._waiting: deque[dict] = deque()
        self._queued_samples = 0
        self._queued_units = 0
        self._running_samples = 0
        self._large_samples = 0
        self._large_units = 0
        self.samples_per_second = 5e5  # rendered samples per second of the whole queue, measured

    def estimated_wait(self) -> float:
        """Seconds until a tile queued now starts rendering, at the measured rate (as if the
        tiles rendering now had just begun)."""
        return (self._queued_samples + self._running_samples) / self.samples_per_second

    def _busy(self, why: str) -> Busy:
        wait = self.estimated_wait()
        return Busy(f"{why}; estimated wait {wait:.1f} s", retry_after=max(1, math.ceil(wait)))

    async def acquire(self, settings: Settings, samples: int, request: Request | None) -> None:
        """Wait for a render slot. Busy when over capacity, ClientGone when the client left."""
        loop = asyncio.get_running_loop()
        with self._lock:
            if self._running < settings.tile_workers and not self._waiting:
                self._running += 1
                self._running_samples += samples
                return
            units = tile_units(samples)
            if self._queued_units + units > settings.tile_queue_depth:
                raise self._busy(f"{len(self._waiting)} tiles ({self._queued_units} units of a 256 px tile) are "
                                 f"waiting to render (limit {settings.tile_queue_depth} units)")
            if self.estimated_wait() > settings.tile_queue_max_wait_seconds:
                raise self._busy(f"the tile queue holds more than {settings.tile_queue_max_wait_seconds:g} s "
                                 "of rendering")
            entry = {"future": loop.create_future(), "samples": samples, "granted": False}
            self._waiting.append(entry)
            self._queued_samples += samples
            self._queued_units += units
        try:
            while not entry["future"].done():
                await asyncio.wait({entry["future"]}, timeout=DISCONNECT_POLL_SECONDS)
                if not entry["future"].done() and request is not None and await request.is_disconnected():
                    raise ClientGone("the client left before its tile started rendering")
        except BaseException:  # gone, or cancelled: leave the queue, or give back the slot just granted
            with self._lock:
                granted = entry["granted"]
                if not granted:
                    self._waiting.remove(entry)
                    self._queued_samples -= samples
                    self._queued_units -= units
            if granted:
                self.release(settings, samples)
            raise

    def release(self, settings: Settings, samples: int, seconds: float = 0.0) -> None:
        """End of a render of ``samples`` (a finished one, in ``seconds``, updates the
        measured rate): the next waiting tiles start."""
        with self._lock:
            if seconds > 0:
                rate = samples / seconds * min(self._running, settings.tile_workers)
                self.samples_per_second = 0.7 * self.samples_per_second + 0.3 * rate
            self._running -= 1
            self._running_samples -= samples
            while self._waiting and self._running < settings.tile_workers:
                entry = self._waiting.popleft()
                self._queued_samples -= entry["samples"]
                self._queued_units -= tile_units(entry["samples"])
                entry["granted"] = True
                self._running += 1
                self._running_samples += entry["samples"]
                future = entry["future"]
                future.get_loop().call_soon_threadsafe(lambda f=future: f.done() or f.set_result(None))

    @contextmanager
    def large(self, settings: Settings, samples: int):  # noqa: ANN201
        """Admission of a large tile: only while no small tile waits (interactive first), and
        one at a time unless the large ones admitted render within ``tile_queue_max_wait_seconds``
        by the measured rate and, with it, weigh at most ``tile_queue_depth`` units; else Busy."""
        units = tile_units(samples)
        with self._lock:
            ahead = self._large_samples / self.samples_per_second
            if self._waiting or (self._large_samples and (ahead > settings.tile_queue_max_wait_seconds or
                                                          self._large_units + units > settings.tile_queue_depth)):
                why = (f"{len(self._waiting)} small tiles are waiting" if self._waiting else
                       f"large tiles admitted before it take {ahead:.1f} s ({self._large_units} units of a "
                       f"256 px tile, limit {settings.tile_queue_depth})")
                raise Busy(why, retry_after=max(1, math.ceil(ahead or samples / self.samples_per_second)))
            self._large_samples += samples
            self._large_units += units
        try:
            yield
        finally:
            with self._lock:
                self._large_samples -= samples
                self._large_units -= units


class ExactRenders:
    """Progressive zoom-out: the exact (supersampled) tiles behind previews, rendered one
    at a time on a thread of their own, newest first (the view the user looks at now),
    each band waiting for interactive tiles, into the tile cache under the exact ETag.
    At most MAX_PENDING_EXACT wait; beyond, the oldest is dropped (asked for again, its
    preview schedules it again)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._waiting: dict[str, tuple] = {}  # exact ETag -> render arguments, oldest first
        self._running: set[str] = set()
        self._thread: threading.Thread | None = None

    def pending(self, etag: str) -> bool:
        with self._cond:
            return etag in self._waiting or etag in self._running

    def submit(self, services: Services, texture: Texture, etag: str, key: dict) -> None:
        with self._cond:
            if etag in self._waiting or etag in self._running:
                return
            self._waiting[etag] = (services, texture, key)
            while len(self._waiting) > MAX_PENDING_EXACT:
                self._waiting.pop(next(iter(self._waiting)))
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="exact-tiles", daemon=True)
                self._thread.start()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._waiting))
                etag = next(reversed(self._waiting))  # newest first
                services, texture, key = self._waiting.pop(etag)
                self._running.add(etag)
            try:
                if services.tile_cache.get(etag) is None:
                    data = render_tile_bytes(services, texture, zoom_out="supersample", background=True, **key)
                    services.tile_cache.put(etag, data)
            except Exception:  # noqa: BLE001 - a background render must not end the thread
                log.exception("exact tile %s failed to render; its preview stays", etag)
            finally:
                with self._cond:
                    self._running.discard(etag)


EXACT = ExactRenders()


async def final_tile(services: Services, texture: Texture, request: Request, if_none_match: str | None,
                     key: dict) -> tuple[str, bytes | None]:
    """A tile's final bytes: (ETag, bytes or None for 304), from the LRU or rendered (503
    when over capacity)."""
    etag = tile_etag(texture, **key, zoom_out=final_zoom_out(services.settings))
    if etag_matches(if_none_match, etag):
        return etag, None
    data = services.tile_cache.get(etag)
    if data is None:
        services.metrics.tile_cache_misses.inc()
        data = await render_tile_async(services, texture, request, **key)
        services.tile_cache.put(etag, data)
    else:
        services.metrics.tile_cache_hits.inc()
    return etag, data


async def progressive_tile(services: Services, texture: Texture, request: Request, if_none_match: str | None,
                           key: dict) -> tuple[str, bytes | None, bool]:
    """A zoomed-out tile in progressive mode: (ETag, bytes or None for 304, is_preview).

    The exact tile when it is cached or can be built from cached children; else the
    bounded render as a preview (a native tile's cost) and the exact one queued behind it
    (ExactRenders). A client revalidating its preview gets 304 until the exact tile is
    ready, then the exact tile."""
    exact = tile_etag(texture, **key, zoom_out="supersample")
    if etag_matches(if_none_match, exact):
        return exact, None, False
    data = services.tile_cache.get(exact)
    (services.metrics.tile_cache_misses if data is None else services.metrics.tile_cache_hits).inc()
    if data is None:
        data = await built_from_cached(services, texture, key)
        if data is not None:
            services.tile_cache.put(exact, data)
    if data is not None:
        return exact, data, False
    preview = tile_etag(texture, **key, zoom_out="bounded")
    if etag_matches(if_none_match, preview):
        EXACT.submit(services, texture, exact, key)  # (again, if it was dropped meanwhile)
        return preview, None, True
    data = services.tile_cache.get(preview)
    if data is None:
        data = await render_tile_async(services, texture, request, zoom_out="bounded", **key)
        services.tile_cache.put(preview, data)
        services.metrics.tile_previews.inc()
    EXACT.submit(services, texture, exact, key)  # after the preview: it must not wait for a band
    return preview, data, True


QUEUE = TileQueue()
#: linear-light float32 copies of recent tiles at NATIVE_ZOOM and one out (tile_from_cache)
LINEAR = TileCache(0)


def tile_etag(texture: Texture, *, z: int, x: int, y: int, size: int, seed: int, plane: str,
              offset: float, fmt: str, zoom_out: str = "supersample") -> str:
    """Strong ETag: every input that changes the bytes, including the model version, the
    texture's code and colour table (``texspace recolour`` changes a table in place) and,
    below native zoom, how zoomed-out tiles are rendered."""
    mode = zoom_out if z < NATIVE_ZOOM and zoom_out != "supersample" else ""
    parts = (TILE_RENDER_VERSION, texture.model_version, texture.id, texture.sampler_key or "",
             seed, z, x, y, size, plane, repr(float(offset)), fmt) + ((mode,) if mode else ())
    digest = hashlib.sha256("|".join(map(str, parts)).encode() + sampling_code(texture).tobytes())
    return '"' + digest.hexdigest()[:32] + '"'


def tiles_final(services: Services, texture: Texture) -> bool:
    """False while the texture's in-place refinement may still replace its sampler (the
    encoder's, or the refinement's own interim), so that its tile URLs will serve new bytes
    (under new ETags) once the job succeeds."""
    return not jobs.refinement_pending(services, texture)


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """RFC 9110 If-None-Match (weak comparison): '*' or any listed tag equal to ours."""
    if not if_none_match:
        return False
    tags = [t.strip() for t in if_none_match.split(",")]
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)


def _linear_key(texture: Texture, key: dict, z: int, x: int, y: int) -> str:
    return tile_etag(texture, **{**key, "z": z, "x": x, "y": y, "fmt": "linear"})


def _keeps_linear(services: Services, z: int) -> bool:
    return (final_zoom_out(services.settings) == "supersample" and services.settings.tile_linear_cache_bytes > 0
            and NATIVE_ZOOM - 1 <= z <= NATIVE_ZOOM)


def cached_linear(services: Services, texture: Texture, key: dict, z: int, x: int, y: int,
                  depth: int = 2) -> np.ndarray | None:
    """Linear pixels of tile (z, x, y) without sampling: its own cached copy, or (when
    ``exact_parent(z)``) its four children's, downsampled: the same bits as a render.
    None when some are missing. (size, size, 3) float32."""
    size = key["size"]
    if final_zoom_out(services.settings) != "supersample":
        return None
    data = LINEAR.get(_linear_key(texture, key, z, x, y))
    if data is not None:
        return np.frombuffer(data, np.float32).reshape(size, size, 3)
    if depth == 0 or not exact_parent(z):
        return None
    children = []
    for j in (0, 1):
        row = []
        for i in (0, 1):
            child = cached_linear(services, texture, key, z + 1, 2 * x + i, 2 * y + j, depth - 1)
            if child is None:
                return None
            row.append(child)
        children.append(row)
    return parent_from_children(children)


def tile_from_cache(services: Services, texture: Texture, *, z: int, x: int, y: int, size: int, seed: int,
                    plane: str, offset: float, fmt: str) -> bytes | None:
    """Encoded tile built from cached linear pixels (its own, or its children's), else None."""
    services.registry.get(texture.model_version)  # a retired model's textures: 503, even from the cache
    key = dict(size=size, seed=seed, plane=plane, offset=offset, zoom_out=final_zoom_out(services.settings))
    LINEAR.max_bytes = services.settings.tile_linear_cache_bytes
    rgb = cached_linear(services, texture, key, z, x, y)
    if rgb is None:
        return None
    if _keeps_linear(services, z):
        LINEAR.put(_linear_key(texture, key, z, x, y), np.ascontiguousarray(rgb).tobytes())
    return write_image(rgb, fmt)


async def built_from_cached(services: Services, texture: Texture, key: dict) -> bytes | None:
    """``tile_from_cache`` off the event loop for the zooms the linear cache can serve
    (native and up to two out), else None without a thread hop."""
    if not NATIVE_ZOOM - 2 <= key["z"] <= NATIVE_ZOOM:
        return None
    return await run_in_threadpool(tile_from_cache, services, texture, **key)


async def render_tile_async(services: Services, texture: Texture, request: Request | None = None,
                            zoom_out: str | None = None, **key) -> bytes:  # noqa: ANN003
    """``render_tile_bytes`` off the event loop, first built from cached children where it
    can be; small tiles through the TileQueue onto the threadpool, large ones on their own
    lane (TileLanes). While the tile waits or renders, a client that disconnects stops it
    (ClientGone); over capacity, Busy (503 + Retry-After). ``zoom_out``: the render
    (default: the final tiles', ``final_zoom_out``; ``bounded`` for a preview)."""
    settings = services.settings
    zoom_out = zoom_out or final_zoom_out(settings)
    if zoom_out == "supersample" and (data := await built_from_cached(services, texture, key)) is not None:
        return data
    samples = tile_samples(key["z"], key["size"], zoom_out)
    cancel = threading.Event()
    render = functools.partial(render_tile_bytes, services, texture, cancel=cancel, zoom_out=zoom_out, **key)
    if samples > SMALL_TILE_SAMPLES:
        with QUEUE.large(settings, samples):
            context = contextvars.copy_context()  # the request id of log lines, as run_in_threadpool does
            future = asyncio.get_running_loop().run_in_executor(LANES.large, context.run, render)
            return await _watch(future, cancel, request)
    await QUEUE.acquire(settings, samples, request)
    started = time.perf_counter()
    done = False
    try:
        data = await _watch(asyncio.ensure_future(run_in_threadpool(render)), cancel, request)
        done = True
        return data
    finally:
        QUEUE.release(settings, samples, time.perf_counter() - started if done else 0.0)


async def _watch(future: asyncio.Future, cancel: threading.Event, request: Request | None) -> bytes:
    """The render's result; if the client disconnects first, stop the render at its next
    band and raise ClientGone once it has stopped (its thread is free again)."""
    while True:
        done, _ = await asyncio.wait({future}, timeout=DISCONNECT_POLL_SECONDS)
        if done:
            return future.result()
        if request is not None and await request.is_disconnected():
            cancel.set()
            try:
                await future
            except ClientGone:
                pass
            raise ClientGone("the client left while its tile rendered; rendering stopped")


def render_tile_bytes(services: Services, texture: Texture, *, z: int, x: int, y: int, size: int,
                      seed: int, plane: str, offset: float, fmt: str,
                      cancel: threading.Event | None = None, zoom_out: str | None = None,
                      background: bool = False) -> bytes:
    """Render and encode one tile (CPU-bound: call from a worker thread). Renders in bands;
    ``cancel`` set stops it before the next band (ClientGone). Tiles at and one zoom out from
    native leave a linear copy for parents built from children (tile_from_cache).
    ``background``: each band first waits for interactive tiles (BACKGROUND_YIELD_SECONDS)."""
    started = time.perf_counter()
    zoom_out = zoom_out or final_zoom_out(services.settings)
    inputs = sampler_inputs(services, texture, zoom=z)
    args = (inputs.sampler, inputs.code, seed, z, x, y, size)
    kwargs = dict(pixels_per_unit=inputs.pixels_per_unit, plane=plane, offset=offset,
                  zoom_out=zoom_out, band_samples=BAND_SAMPLES)

    def check_cancel() -> None:
        if cancel is not None and cancel.is_set():
            raise ClientGone("the client left; rendering stopped")

    if background or tile_samples(z, size, zoom_out) > SMALL_TILE_SAMPLES:
        def before_band() -> None:
            LANES.yield_to_small(BACKGROUND_YIELD_SECONDS if background else YIELD_SECONDS)
            check_cancel()

        rgb = render_tile(*args, **kwargs, before_band=before_band)
    else:
        with LANES.small():
            rgb = render_tile(*args, **kwargs, before_band=check_cancel)
    if _keeps_linear(services, z) and zoom_out == "supersample":
        LINEAR.max_bytes = services.settings.tile_linear_cache_bytes
        key = dict(size=size, seed=seed, plane=plane, offset=offset, zoom_out=zoom_out)
        LINEAR.put(_linear_key(texture, key, z, x, y), rgb.tobytes())
    data = write_image(rgb, fmt)
    services.metrics.tile_render.observe(time.perf_counter() - started)
    return data
