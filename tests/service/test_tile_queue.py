"""Interactive tiles before batch jobs: the bounded tile queue (503 + Retry-After), tiles whose
client has gone, parents built from cached children, bounded zoom-out, worker priority."""
from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import threading

import pytest

from service import tiles as service_tiles
from service.errors import ClientGone
from service.samplers import sampling_code
from worker.errors import Busy
from worker.images import write_image
from worker.tiles import NATIVE_ZOOM, render_tile

from tests.service.helpers import tile_url


def run_async(coroutine) -> None:  # noqa: ANN001
    """asyncio.run on a thread of its own: the browser tests' playwright driver keeps an
    event loop running in the main thread for the rest of the session."""
    errors: list[BaseException] = []

    def target() -> None:
        try:
            asyncio.run(coroutine)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test's thread
            errors.append(exc)

    thread = threading.Thread(target=target)
    thread.start()
    thread.join()
    if errors:
        raise errors[0]

N = NATIVE_ZOOM


class FakeRequest:
    """Stands in for starlette's Request: disconnected after ``after`` looks."""

    def __init__(self, after: int = 0) -> None:
        self.looks = 0
        self.after = after

    async def is_disconnected(self) -> bool:
        self.looks += 1
        return self.looks > self.after


@pytest.fixture
def queue() -> service_tiles.TileQueue:
    return service_tiles.TileQueue()


def test_full_queue_is_503_with_retry_after(client, texture, services) -> None:
    services.settings.tile_workers, services.settings.tile_queue_depth = 1, 0
    service_tiles.QUEUE._running += 1  # the one render slot is taken
    try:
        res = client.get(tile_url(texture, N, 40, 40), params={"size": 64})
    finally:
        service_tiles.QUEUE._running -= 1
    assert res.status_code == 503, res.text
    assert res.headers["content-type"] == "application/problem+json"
    assert res.json()["type"] == "urn:texspace:problem:busy" and int(res.headers["retry-after"]) >= 1
    assert client.get(tile_url(texture, N, 40, 40), params={"size": 64}).status_code == 200  # room again


def test_queue_bounded_by_estimated_wait(services, queue) -> None:
    settings = services.settings
    settings.tile_workers, settings.tile_queue_depth, settings.tile_queue_max_wait_seconds = 1, 100, 1.0
    queue.samples_per_second = 1e5

    async def scenario() -> None:
        await queue.acquire(settings, 40000, None)                       # renders at once
        first = asyncio.ensure_future(queue.acquire(settings, 40000, None))  # 0.4 s of work before it
        second = asyncio.ensure_future(queue.acquire(settings, 40000, None))  # 0.8 s before it
        await asyncio.sleep(0.01)
        with pytest.raises(Busy) as busy:                                   # 1.2 s before it: refused
            await queue.acquire(settings, 40000, None)
        assert busy.value.retry_after == 2
        queue.release(settings, 40000)
        await first                                                          # in order
        assert not second.done()
        queue.release(settings, 40000)
        await second
        queue.release(settings, 40000)

    run_async(scenario())
    assert queue._running == 0 and not queue._waiting and queue._queued_samples == queue._running_samples == 0


def test_waiting_tile_whose_client_left_leaves_the_queue(services, queue) -> None:
    settings = services.settings
    settings.tile_workers, settings.tile_queue_depth = 1, 10

    async def scenario() -> None:
        await queue.acquire(settings, 1000, None)
        with pytest.raises(ClientGone):
            await queue.acquire(settings, 1000, FakeRequest(after=2))
        assert not queue._waiting and queue._queued_samples == 0
        queue.release(settings, 1000)

    run_async(scenario())
    assert queue._running == 0


def test_rendering_tile_whose_client_left_stops(services, texture, client) -> None:
    """The render checks before each band; a client gone mid-render frees the thread."""
    from service.routes.textures import load_texture

    tex = load_texture(services, texture["id"])
    cancel = threading.Event()
    cancel.set()
    key = dict(z=N - 2, x=3, y=3, size=64, seed=0, plane="xy", offset=0.0, fmt="png")
    with pytest.raises(ClientGone):
        service_tiles.render_tile_bytes(services, tex, cancel=cancel, **key)

    async def scenario() -> None:
        started = threading.Event()
        release = threading.Event()

        def slow() -> bytes:
            started.set()
            release.wait(5)
            if cancel.is_set():
                raise ClientGone("stopped")
            return b"tile"

        cancel.clear()
        future = asyncio.get_running_loop().run_in_executor(None, slow)
        watching = asyncio.ensure_future(service_tiles._watch(future, cancel, FakeRequest(after=1)))
        await asyncio.sleep(0.3)
        assert cancel.is_set()           # the disconnect was seen and the render told to stop
        release.set()
        with pytest.raises(ClientGone):
            await watching

    run_async(scenario())


@pytest.mark.parametrize("levels", [1, 2])
def test_parent_from_cached_children_same_bytes_no_sampling(client, texture, services, monkeypatch, levels) -> None:
    z, x, y, size = N - levels, 5, -3, 64
    n = 2 ** levels
    for j in range(n):
        for i in range(n):
            assert client.get(tile_url(texture, N, n * x + i, n * y + j), params={"size": size}).status_code == 200
    runtime = services.registry.get(None)
    from service.routes.textures import load_texture

    code = sampling_code(load_texture(services, texture["id"]))
    expected = write_image(render_tile(runtime, code, 0, z, x, y, size), "png")

    def no_sampling(*args, **kwargs):  # noqa: ANN002, ANN003
        raise AssertionError("the parent was rendered, not built from its children")

    monkeypatch.setattr(service_tiles, "render_tile", no_sampling)
    res = client.get(tile_url(texture, z, x, y), params={"size": size})
    assert res.status_code == 200 and res.content == expected
    # a neighbour without cached children is rendered (here: the patched renderer's 500)
    assert client.get(tile_url(texture, z, x + 1, y), params={"size": size}).status_code == 500


def test_bounded_zoom_out_has_its_own_etag_and_native_cost(client, texture, services, monkeypatch) -> None:
    url = tile_url(texture, N - 2, 1, 1)
    monkeypatch.setattr(services.settings, "tile_zoom_out", "supersample")
    exact = client.get(url, params={"size": 64})
    native_exact = client.get(tile_url(texture, N, 1, 1), params={"size": 64})
    services.settings.tile_zoom_out = "bounded"
    bounded = client.get(url, params={"size": 64})
    native = client.get(tile_url(texture, N, 1, 1), params={"size": 64})
    assert bounded.status_code == exact.status_code == 200
    assert bounded.headers["etag"] != exact.headers["etag"] and bounded.content != exact.content
    assert native.headers["etag"] == native_exact.headers["etag"]  # native tiles are the same in both modes
    assert service_tiles.tile_samples(N - 2, 256, "bounded") == service_tiles.tile_samples(N, 256)


def test_worker_lowers_its_own_priority() -> None:
    code = ("import os; from service.processes import lower_priority; before = os.nice(0); "
            "lower_priority(7); print(os.nice(0) - before)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert int(out.stdout) == min(7, 19 - os.nice(0))


def test_large_tiles_only_while_no_small_tile_waits(services, queue) -> None:
    settings = services.settings
    settings.tile_workers, settings.tile_queue_depth, settings.tile_queue_max_wait_seconds = 1, 64, 2.0
    queue.samples_per_second = 1e6
    with queue.large(settings, 4_000_000):          # alone: admitted whatever its size
        with pytest.raises(Busy):                   # 4 s of large work ahead: refused
            with queue.large(settings, 1_000_000):
                pass
    with queue.large(settings, 1_000_000), queue.large(settings, 1_000_000):  # 1 s ahead: both admitted
        pass

    async def scenario() -> None:
        await queue.acquire(settings, 1000, None)
        waiting = asyncio.ensure_future(queue.acquire(settings, 1000, None))
        await asyncio.sleep(0.01)
        with pytest.raises(Busy) as busy:            # a small tile waits: interactive first
            with queue.large(settings, 1_000_000):
                pass
        assert "small tiles are waiting" in busy.value.detail
        queue.release(settings, 1000)
        await waiting
        queue.release(settings, 1000)

    run_async(scenario())
    assert queue._large_samples == 0


def test_tiles_weigh_their_samples_in_units_of_a_256_px_tile() -> None:
    units = service_tiles.tile_units
    assert units(service_tiles.tile_samples(N, 256)) == 1 and units(service_tiles.tile_samples(N, 64)) == 1
    assert units(service_tiles.tile_samples(N, 512)) == 4 and units(service_tiles.tile_samples(N, 1024)) == 16
    assert units(service_tiles.tile_samples(N - 1, 256)) == 4              # 2 x 2 sub-samples per pixel
    assert units(service_tiles.tile_samples(N - 1, 256, "bounded")) == 1
    assert service_tiles.tile_samples(N, 512) > service_tiles.SMALL_TILE_SAMPLES >= service_tiles.tile_samples(N, 256)


def test_512_px_tiles_do_not_make_256_px_tiles_busy(services, queue) -> None:
    """Two cold 512 px tiles, then six 256 px ones, on a machine rendering 200k samples/s:
    the 512 px tiles (4 units each) go to the large lane, whose bands wait for small tiles,
    and every 256 px tile is admitted. (They once took both render slots: 2.6 s of work
    ahead of each 256 px tile, and 6 of 6 answered 503.)"""
    settings = services.settings
    settings.tile_workers, settings.tile_queue_depth, settings.tile_queue_max_wait_seconds = 2, 64, 2.0
    queue.samples_per_second = 2e5
    large, small = service_tiles.tile_samples(N, 512), service_tiles.tile_samples(N, 256)

    async def scenario() -> None:
        with queue.large(settings, large), queue.large(settings, large):
            for _ in range(2):
                await queue.acquire(settings, small, None)                  # the two render slots
            waiting = [asyncio.ensure_future(queue.acquire(settings, small, None)) for _ in range(4)]
            await asyncio.sleep(0.01)
            assert not any(w.done() for w in waiting) and queue._queued_units == 4   # queued, none refused
            with pytest.raises(Busy, match="small tiles are waiting"):       # a third 512 px tile: later
                with queue.large(settings, large):
                    pass
            for _ in range(6):
                queue.release(settings, small)
                await asyncio.sleep(0)
            await asyncio.gather(*waiting)

    run_async(scenario())
    assert queue._running == 0 and queue._queued_units == 0 and queue._large_units == 0


def test_queue_depth_counts_units(services, queue) -> None:
    """Large tiles admitted weigh their units against ``tile_queue_depth``: 512 px tiles
    count four each, whatever the measured rate says of their time."""
    settings = services.settings
    settings.tile_workers, settings.tile_queue_depth, settings.tile_queue_max_wait_seconds = 1, 8, 2.0
    queue.samples_per_second = 1e9
    large = service_tiles.tile_samples(N, 512)
    with queue.large(settings, large), queue.large(settings, large):
        with pytest.raises(Busy, match="8 units of a 256 px tile, limit 8"):
            with queue.large(settings, large):
                pass
    with queue.large(settings, service_tiles.tile_samples(N, 1024)):        # alone: admitted whatever its weight
        pass


def test_a_512_px_tile_renders_on_the_large_lane(client, texture, services, monkeypatch) -> None:
    threads = []
    render = service_tiles.render_tile_bytes

    def recording(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        threads.append(threading.current_thread().name)
        return render(*args, **kwargs)

    monkeypatch.setattr(service_tiles, "render_tile_bytes", recording)
    assert client.get(tile_url(texture, N, 7, 9), params={"size": 512}).status_code == 200
    assert client.get(tile_url(texture, N, 7, 9), params={"size": 256}).status_code == 200
    assert threads[0].startswith("large-tiles") and not threads[1].startswith("large-tiles"), threads
