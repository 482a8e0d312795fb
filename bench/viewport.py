"""Viewport benchmark (``make bench``): what a map view costs a user, on a real embedded
``texspace serve``.

    .venv/bin/python bench/viewport.py          # or bench/run.py --only viewport

A viewport is 16 cold 256^2 tiles (a 4 x 4 block never asked for before) requested at
once, as a map asks for them. Measured: per-tile latency from the common start (p50,
p95) and the time to the last tile, at native zoom idle (on a settled server:
``settle``), at native zoom while 4 volume jobs of 128^3 run (2 at a time on the worker,
2 queued), two zoom levels out cold with the default progressive zoom-out (the previews,
then each tile asked again as the page does until it is exact), and one zoom level out
over native tiles viewed before (parents built from cached children). Then two levels
out on a server with ``TEXSPACE_TILE_ZOOM_OUT=supersample`` (every tile exact at once),
and in process the previews' (bounded render's) difference against the supersampled
tiles.
"""
from __future__ import annotations

import json
import sys
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.common import median, percentile  # noqa: E402
from bench.serving import embedded_server, get, post_image, upload_image_1024  # noqa: E402

N = 6  # worker.tiles.NATIVE_ZOOM
VOLUMES = 4
VOLUME_RESOLUTION = 128
#: the viewport measures rendering, not admission: a shared machine's slow moments would
#: otherwise turn some of its 16 tiles into 503s (bench/load.py measures those)
ENV = {"TEXSPACE_TILE_QUEUE_MAX_WAIT_SECONDS": "120"}


def viewport(tiles: str, z: int, x0: int, y0: int, n: int = 4, seed: int = 3) -> dict:
    """n x n tiles from (x0, y0) requested at once; seconds from the common start to each."""
    urls = [f"{tiles}/{z}/{x0 + i}/{y0 + j}.png?seed={seed}" for j in range(n) for i in range(n)]
    statuses: list[int] = []

    def fetch(url: str) -> float:
        for _ in range(10):  # a 503 is retried after its Retry-After, as a patient map would
            try:
                get(url)
                statuses.append(200)
                break
            except urllib.error.HTTPError as exc:
                statuses.append(exc.code)
                if exc.code != 503:
                    break
                time.sleep(float(exc.headers.get("Retry-After", "1")))
        return time.perf_counter() - started

    with ThreadPoolExecutor(len(urls)) as pool:
        started = time.perf_counter()
        done = list(pool.map(fetch, urls))
    return {"p50_s": median(done), "p95_s": percentile(done, 95), "last_s": max(done),
            "all_s": [round(t, 4) for t in sorted(done)], "non_200": [c for c in statuses if c != 200]}


def progressive_viewport(tiles: str, z: int, x0: int, y0: int, n: int = 4, seed: int = 3,
                         poll_s: float = 0.25) -> dict:
    """``viewport`` on a progressive server: seconds to each tile's first answer (a preview
    or already exact) and to its exact tile, asking again with If-None-Match as the page does."""
    urls = [f"{tiles}/{z}/{x0 + i}/{y0 + j}.png?seed={seed}" for j in range(n) for i in range(n)]
    previews: list[bool] = []

    def fetch(url: str) -> tuple[float, float]:
        etag, first = None, None
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            req = urllib.request.Request(url, headers={"If-None-Match": etag} if etag else {})
            try:
                with urllib.request.urlopen(req, timeout=120) as r:
                    r.read()
                    etag, preview = r.headers["ETag"], r.headers.get("X-Texspace-Tile") == "preview"
            except urllib.error.HTTPError as exc:
                if exc.code == 503:  # over capacity: after its Retry-After, as a patient map would
                    time.sleep(float(exc.headers.get("Retry-After", "1")))
                    continue
                if exc.code != 304:
                    raise
                preview = True  # 304 on the preview's ETag: the exact tile is not ready yet
            now = time.perf_counter() - started
            if first is None:
                first = now
                previews.append(preview)
            if not preview:
                return first, now
            time.sleep(poll_s)
        raise RuntimeError(f"{url}: no exact tile within 600 s")

    with ThreadPoolExecutor(len(urls)) as pool:
        started = time.perf_counter()
        firsts, exacts = zip(*pool.map(fetch, urls))
    return {"p50_s": median(firsts), "p95_s": percentile(firsts, 95), "last_s": max(firsts),
            "exact_p50_s": median(exacts), "exact_last_s": max(exacts), "previews": sum(previews),
            "all_s": [round(t, 4) for t in sorted(firsts)], "non_200": []}


def _post_json(url: str, body: dict) -> dict:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read())


def _job_states(base: str, ids: list[str]) -> list[str]:
    states = []
    for job_id in ids:
        with urllib.request.urlopen(f"{base}/v1/jobs/{job_id}", timeout=30) as r:
            states.append(json.loads(r.read())["state"])
    return states


def under_volumes(base: str, texture: str, tiles: str, x0: int, y0: int, log=print) -> dict:
    """The viewport while VOLUMES volume jobs run: submitted first, tiles once one runs."""
    ids = [_post_json(f"{base}/v1/textures/{texture}/volumes",
                      {"resolution": VOLUME_RESOLUTION, "seed": k, "format": "npy"})["id"] for k in range(VOLUMES)]
    deadline = time.monotonic() + 60
    while "running" not in _job_states(base, ids) and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.3)  # the jobs' samplers at full speed
    before = _job_states(base, ids)
    result = viewport(tiles, N, x0, y0)
    after = _job_states(base, ids)
    deadline = time.monotonic() + 600
    while any(s in ("queued", "running") for s in _job_states(base, ids)) and time.monotonic() < deadline:
        time.sleep(0.5)
    final = _job_states(base, ids)
    log(f"  jobs at the viewport's start {before}, end {after}, final {final}")
    return result | {"jobs_at_start": before, "jobs_at_end": after, "jobs_final": final}


def settle(base: str, texture: str, tiles: str) -> None:
    """Bring a just-started server to the state a viewer meets: its worker process has
    finished starting (a tiny volume job has run) and one viewport has been rendered away
    from the measured ones. Measured without this, the first viewport of a fresh server
    came last at 1.46-1.48 s, the next ones at 1.15-1.20 s (two servers, same minute)."""
    job = _post_json(f"{base}/v1/textures/{texture}/volumes", {"resolution": 8, "seed": 0, "format": "npy"})["id"]
    deadline = time.monotonic() + 120
    while _job_states(base, [job])[0] in ("queued", "running") and time.monotonic() < deadline:
        time.sleep(0.05)
    viewport(tiles, N, -100, -100)


def _show(log, name: str, r: dict) -> None:
    log(f"  {name}: p50 {r['p50_s']:.3f} s, p95 {r['p95_s']:.3f} s, last {r['last_s']:.3f} s"
        + (f", non-200 {r['non_200']}" if r["non_200"] else ""))


def sixteen_in_process(model_dir: Path, z: int = N) -> float:
    """Seconds to render 16 256^2 tiles one after another in this process (no HTTP, no PNG):
    the sampler's floor for a viewport at this moment of the shared machine."""
    from worker.runtime import ModelRuntime
    from worker.tiles import render_tile

    runtime = ModelRuntime(model_dir)
    code = np.random.default_rng(1).standard_normal(runtime.code_size).astype(np.float32)
    render_tile(runtime, code, 3, z, -50, -50, 256)
    started = time.perf_counter()
    for k in range(16):
        render_tile(runtime, code, 3, z, 500 + k % 4, 500 + k // 4, 256)
    return time.perf_counter() - started


def bench_viewport(model_dir: Path, log=print) -> dict:
    png = upload_image_1024()
    out: dict = {"sampler_16_tiles_before_s": sixteen_in_process(model_dir)}
    log(f"  reference: 16 native 256^2 tiles rendered in process, one after another: "
        f"{out['sampler_16_tiles_before_s']:.3f} s")
    with embedded_server(model_dir, log, env=ENV) as base:
        texture = post_image(base, png, "viewport")["id"]
        tiles = f"{base}/v1/textures/{texture}/tiles"
        settle(base, texture, tiles)
        out["native_idle"] = viewport(tiles, N, 100, 100)
        _show(log, "16 cold tiles, native, idle", out["native_idle"])
        out["native_4_volumes"] = under_volumes(base, texture, tiles, 200, 200, log=log)
        _show(log, f"16 cold tiles, native, {VOLUMES} volume jobs of {VOLUME_RESOLUTION}^3", out["native_4_volumes"])
        out["native_idle_again"] = viewport(tiles, N, 300, 300)
        _show(log, "16 cold tiles, native, idle again", out["native_idle_again"])
        out["out2_progressive_cold"] = progressive_viewport(tiles, N - 2, 1000, 1000)
        r = out["out2_progressive_cold"]
        _show(log, f"16 cold tiles, two zoom levels out, progressive ({r['previews']} previews)", r)
        log(f"    exact tiles: p50 {r['exact_p50_s']:.3f} s, last {r['exact_last_s']:.3f} s")
        # one level out over 8 x 8 native tiles viewed before: parents from cached children
        viewport(tiles, N, 800, 800, n=8)
        out["out1_from_children"] = viewport(tiles, N - 1, 400, 400)
        _show(log, "16 tiles one level out over viewed native tiles (from children)", out["out1_from_children"])
        out["out2_one_tile_from_children"] = viewport(tiles, N - 2, 200, 200, n=1)  # native 800..803
        log(f"  one tile two levels out over 16 viewed native tiles: {out['out2_one_tile_from_children']['last_s']:.3f} s")
    with embedded_server(model_dir, log, env=ENV | {"TEXSPACE_TILE_ZOOM_OUT": "supersample"}) as base:
        texture = post_image(base, png, "viewport-supersample")["id"]
        tiles = f"{base}/v1/textures/{texture}/tiles"
        settle(base, texture, tiles)
        out["supersample_native_idle"] = viewport(tiles, N, 100, 100)
        _show(log, "supersample server: 16 cold tiles, native", out["supersample_native_idle"])
        out["out2_supersample_cold"] = viewport(tiles, N - 2, 1000, 1000)
        _show(log, "supersample server: 16 cold tiles, two zoom levels out", out["out2_supersample_cold"])
    out["sampler_16_tiles_after_s"] = sixteen_in_process(model_dir)
    log(f"  reference again: {out['sampler_16_tiles_after_s']:.3f} s")
    out["bounded_difference"] = bounded_difference(model_dir, log=log)
    return out


def bounded_difference(model_dir: Path, tiles: int = 6, size: int = 128, log=print) -> dict:
    """Bounded zoom-out tiles against the supersampled reference, in process: RMS and max
    |difference| of 8-bit sRGB values and the difference of mean colour (linear), per zoom."""
    from worker.colour import linear_to_srgb
    from worker.runtime import ModelRuntime
    from worker.tiles import render_tile

    runtime = ModelRuntime(model_dir)
    code = np.random.default_rng(1).standard_normal(runtime.code_size).astype(np.float32)
    result = {}
    for z in (N - 1, N - 2, N - 3):
        diffs, means, spread = [], [], []
        for k in range(tiles):
            ref = render_tile(runtime, code, 3, z, 7 * k - 9, 3 - 5 * k, size)
            fast = render_tile(runtime, code, 3, z, 7 * k - 9, 3 - 5 * k, size, zoom_out="bounded")
            to8 = lambda a: np.round(np.asarray(linear_to_srgb(a), np.float64) * 255)  # noqa: E731
            diffs.append(to8(fast) - to8(ref))
            means.append(np.abs(fast.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))).max())
            spread.append(to8(ref).std())
        d = np.concatenate([x.ravel() for x in diffs])
        result[f"z{z}"] = {"rms_srgb8": float(np.sqrt((d ** 2).mean())), "p99_abs_srgb8": float(np.percentile(np.abs(d), 99)),
                           "max_abs_srgb8": float(np.abs(d).max()), "mean_colour_abs_diff_linear": float(max(means)),
                           "reference_std_srgb8": float(np.mean(spread))}
        r = result[f"z{z}"]
        log(f"  bounded vs supersampled, zoom {z} ({tiles} tiles of {size}^2): RMS {r['rms_srgb8']:.1f} / 255 "
            f"(reference pixel std {r['reference_std_srgb8']:.1f}), p99 {r['p99_abs_srgb8']:.0f}, "
            f"max {r['max_abs_srgb8']:.0f}; mean colour within {r['mean_colour_abs_diff_linear']:.4f} (linear)")
    return result


if __name__ == "__main__":
    from bench.common import SHIPPED_MODEL

    print(json.dumps(bench_viewport(Path(sys.argv[1]) if len(sys.argv) > 1 else SHIPPED_MODEL), indent=1))
