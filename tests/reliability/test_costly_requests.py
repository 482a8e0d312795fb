"""Requests that cost far more than they look (issue 19), against a real ``texspace api``:
the worst upload shapes stay under 1.5 GB of API memory, a maximal tile does not hold
up small ones, and slow or lying clients lose their connection."""
from __future__ import annotations

import io
import socket
import statistics
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.service.conftest import brick_png

from .procs import Cluster, base_env

RSS_LIMIT = int(1.5 * 2**30)


def png(width: int, height: int, channels: int = 3) -> bytes:
    mode = {1: "L", 3: "RGB", 4: "RGBA"}[channels]
    shape = (height, width) if channels == 1 else (height, width, channels)
    pixels = np.zeros(shape, np.uint8)
    pixels[::7] = 200                       # some structure; still compresses to little
    buf = io.BytesIO()
    Image.fromarray(pixels, mode).save(buf, "PNG", compress_level=1)
    return buf.getvalue()


def peak_rss(pid: int) -> int:
    """The process's peak resident memory (VmHWM), bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Cluster:
    root = tmp_path_factory.mktemp("costly")
    cluster = Cluster(root, base_env(root / "data", TEXSPACE_HTTP_READ_TIMEOUT_SECONDS="1.5"))
    cluster.start_api()
    yield cluster
    cluster.stop()


@pytest.mark.slow
def test_worst_upload_shapes_stay_under_1_5_gb(cluster: Cluster) -> None:
    """A 16 x 1,000,000 PNG (46 kB, under the pixel limit) once tried to allocate 45.8 GiB;
    an 8192^2 RGBA PNG (the pixel limit) cost 2.8 GB. Two of the latter at once share the
    decode budget instead of doubling the peak."""
    with cluster.client() as http:
        thin = http.post("/v1/textures", files={"image": ("thin.png", png(16, 1_000_000, 1), "image/png")})
        assert thin.status_code == 422 and "16 times" in thin.json()["detail"], thin.text
        big = png(8192, 8192, 4)
        with http.stream("GET", "/healthz"):
            pass
        results: list[int] = []

        def upload() -> None:
            with cluster.client() as own:
                own.timeout = 120
                results.append(own.post("/v1/textures", files={"image": ("big.png", big, "image/png")}).status_code)

        threads = [threading.Thread(target=upload) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(180)
        assert results == [201, 201], cluster.log_tail()
        assert http.get("/healthz").status_code == 200
    peak = peak_rss(cluster.api.pid)
    print(f"API peak RSS {peak / 2**30:.2f} GiB")
    assert peak < RSS_LIMIT, f"API peak RSS {peak / 2**30:.2f} GiB"


@pytest.mark.slow
def test_small_tiles_do_not_wait_behind_a_maximal_tile(cluster: Cluster) -> None:
    """A cold 256 px tile while a maximal allowed tile (512 px at zoom 2: 4 M samples)
    renders answers within 2x its idle time (it took 17.7 s instead of 0.09 s)."""
    with cluster.client() as http:
        http.timeout = 120
        res = http.post("/v1/textures", files={"image": ("b.png", brick_png(), "image/png")})
        assert res.status_code == 201, res.text
        base = f"/v1/textures/{res.json()['id']}/tiles"
        http.get(f"{base}/6/100/0.png")             # warm the sampler
        cold = iter(range(1000, 2000))

        def small() -> float:
            started = time.perf_counter()
            assert http.get(f"{base}/6/{next(cold)}/0.png").status_code == 200
            return time.perf_counter() - started

        idle = statistics.median(small() for _ in range(7))
        done: list[float] = []

        def heavy() -> None:
            with cluster.client() as own:
                own.timeout = 120
                started = time.perf_counter()
                assert own.get(f"{base}/2/0/0.png", params={"size": 512}).status_code == 200
                done.append(time.perf_counter() - started)

        thread = threading.Thread(target=heavy)
        thread.start()
        time.sleep(0.5)
        busy = statistics.median(small() for _ in range(5))
        assert not done, "the maximal tile ended before the small ones were measured"
        thread.join(120)
        assert done, "the maximal tile did not render"
        print(f"small cold tile: {idle:.3f} s idle, {busy:.3f} s beside a maximal tile ({done[0]:.1f} s)")
        assert busy <= 2 * idle + 0.02, f"small tile {busy:.3f} s while busy, {idle:.3f} s idle"


def test_slow_and_lying_clients_are_disconnected(cluster: Cluster) -> None:
    """Headers that never end (slowloris) and a body shorter than its Content-Length are
    cut off after TEXSPACE_HTTP_READ_TIMEOUT_SECONDS (1.5 here)."""
    requests = [b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ",
                b"POST /v1/textures HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                b"Content-Length: 100000\r\n\r\n--b\r\n",
                b""]                                           # connect and say nothing
    for request in requests:
        with socket.create_connection(("127.0.0.1", cluster.port), timeout=10) as sock:
            started = time.monotonic()
            sock.sendall(request)
            try:
                data = sock.recv(4096)
            except ConnectionResetError:
                data = b""
            assert time.monotonic() - started < 8, request
            assert not data or data.startswith(b"HTTP/1.1 "), data  # closed, perhaps after a status line
    with cluster.client() as http:
        assert http.get("/healthz").status_code == 200
