"""HTTP benchmarks on a real embedded ``texspace serve``: uploads (encode) and tiles."""
from __future__ import annotations

import io
import json
import os
import signal
import tempfile
import time
import urllib.request
import uuid
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from bench.common import median, percentile
from service.spawn import free_port, spawn, stop, wait_ready


@contextmanager
def embedded_server(model_dir: Path, log=print, env: dict[str, str] | None = None):
    """``texspace serve`` (API + worker) on a free loopback port with a throwaway data dir,
    ``env`` added to its environment (``TEXSPACE_*`` settings).

    Yields the base URL; the server is stopped (SIGINT, then SIGKILL) on exit.
    """
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="texspace-bench-") as data:
        env = dict(os.environ, TEXSPACE_DATA_DIR=data, TEXSPACE_PORT=str(port), TEXSPACE_HOST="127.0.0.1",
                   TEXSPACE_MODEL_DIRS=str(model_dir), TEXSPACE_LOG_LEVEL="WARNING",
                   TEXSPACE_AUTO_FIT="false", **(env or {}))  # measures serving, not fits behind the uploads
        log_path = Path(data) / "serve.log"  # a file, not a pipe: nobody reads it while the server runs
        proc = spawn(["serve"], env, log_path)
        base = f"http://127.0.0.1:{port}"
        try:
            wait_ready(base, [proc], 120, output=lambda: log_path.read_text(errors="replace"), name="texspace serve")
            yield base
        finally:
            stop([proc], sig=signal.SIGINT)


def upload_image_1024() -> bytes:
    """A 1024 x 1024 RGB PNG made from scikit-image's bundled brick photo (offline)."""
    import skimage.data
    from PIL import Image

    grey = Image.fromarray(skimage.data.brick()).resize((1024, 1024), Image.BICUBIC)
    rgb = Image.merge("RGB", (grey, grey.point(lambda v: int(v * 0.9)), grey.point(lambda v: int(v * 0.8))))
    buf = io.BytesIO()
    rgb.save(buf, "PNG")
    return buf.getvalue()


def post_image(base: str, png: bytes, name: str, lighting: str = "as-is") -> dict:
    boundary = uuid.uuid4().hex
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"name\"\r\n\r\n{name}\r\n"
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"lighting\"\r\n\r\n{lighting}\r\n"
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"image\"; filename=\"bench.png\"\r\n"
            f"Content-Type: image/png\r\n\r\n").encode() + png + f"\r\n--{boundary}--\r\n".encode()
    req = urllib.request.Request(f"{base}/v1/textures", data=body, method="POST",
                                 headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.loads(r.read())


def get(url: str) -> tuple[float, bytes]:
    t = time.perf_counter()
    with urllib.request.urlopen(url, timeout=120) as r:
        data = r.read()
    return time.perf_counter() - t, data


def bench_http(model_dir: Path, *, uploads: int = 7, cold_tiles: int = 24, cached_tiles: int = 50,
               log=print) -> dict:
    """encode p50 of 1024^2 uploads, as they are and with lighting=even (taken in turns);
    cold 256^2 tiles (distinct addresses, zoom 6 = one sample per pixel, 65,536 sampler
    points) p50/p95; cached tile p50 (same URL again)."""
    png = upload_image_1024()
    with embedded_server(model_dir, log) as base:
        encode_s, even_s, texture = [], [], None
        for i in range(uploads):
            for lighting, times in (("as-is", encode_s), ("even", even_s)):
                t = time.perf_counter()
                texture = post_image(base, png, f"bench-{i}", lighting)
                times.append(time.perf_counter() - t)
        tiles = f"{base}/v1/textures/{texture['id']}/tiles"
        get(f"{tiles}/6/-1/-1.png?seed=3")  # first request warms the route and the session
        cold = [get(f"{tiles}/6/{i}/{-2 * i + 5}.png?seed=3")[0] for i in range(cold_tiles)]
        url = f"{tiles}/6/0/5.png?seed=3"
        cached = [get(url)[0] for _ in range(cached_tiles)]
    log(f"  encode 1024^2 upload: p50 {median(encode_s):.3f} s over {uploads}; lighting=even {median(even_s):.3f} s")
    log(f"  tile 256^2 cold: p50 {median(cold):.3f} s, p95 {percentile(cold, 95):.3f} s over {cold_tiles}")
    log(f"  tile cached: p50 {median(cached) * 1000:.2f} ms over {cached_tiles}")
    return {"encode_p50_s": median(encode_s), "encode_even_p50_s": median(even_s), "tile_256_cold_p50_s": median(cold),
            "tile_256_cold_p95_s": percentile(cold, 95), "tile_cached_p50_s": median(cached),
            "tile_256_cold_all_s": [round(x, 4) for x in cold], "encode_all_s": [round(x, 4) for x in encode_s]}


def tile_in_process(model_dir: Path, repeats: int = 5) -> float:
    """Best time of one 256^2 zoom-6 tile rendered (not encoded) in this process: the
    sampler part of a cold tile, for the breakdown."""
    from worker.runtime import ModelRuntime
    from worker.tiles import render_tile

    runtime = ModelRuntime(model_dir)
    code = np.zeros(runtime.code_size, np.float32)
    from bench.common import best_of

    render_tile(runtime, code, 3, 6, 0, 0, 256)
    return best_of(lambda: render_tile(runtime, code, 3, 6, 1, 2, 256), repeats)
