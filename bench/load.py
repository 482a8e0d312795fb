"""Load test (``make bench``; not part of ``make test``): N concurrent clients for T seconds
against a real ``texspace serve`` on a free loopback port.

    .venv/bin/python bench/load.py [--clients 32] [--seconds 60] [--base-url URL]

Each client loops over a weighted mix: cached tile GETs (a hot set rendered once before
the clock starts), cold tile GETs (random far-away tiles, rendered on demand), job
submissions (small volumes), job polls and, one request in a hundred, an upload (a 192 px
photo: the encoder and the code's choice, about a second of CPU, ``TEXSPACE_UPLOAD_ENCODES``
at a time). Deliberate back-pressure (503 / 429 with
``Retry-After``) is counted apart, its latency under ``<kind>_503`` (so ``tile_cold`` is
the latency of tiles served); anything else that is not 2xx / 304, and any
transport error, is an error. After the run, every accepted job must finish (nothing
lost). Prints p50 / p95 per kind and requests/s, and merges them into
bench/out/results.json under ``load_<N>_clients`` (other keys are kept).
"""
from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import random
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script (``python bench/load.py``)

from service.spawn import free_port, spawn, stop, wait_ready  # noqa: E402

RESULTS = ROOT / "bench" / "out" / "results.json"
MIX = (("tile_cached", 0.54), ("tile_cold", 0.25), ("job_submit", 0.08), ("job_poll", 0.12), ("upload", 0.01))
UPLOAD_SHARE = dict(MIX)["upload"]  # --upload-share 0: the same mix without uploads (their cost to the rest)
HOT_TILES = 16
BACK_PRESSURE = {429, 503}


def percentile(values: list[float], q: float) -> float:
    """q-th percentile (0..100), linear interpolation; NaN for no values."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    pos = (len(ordered) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


@contextmanager
def serve(extra_env: dict[str, str]):
    """``texspace serve`` with a throw-away data folder; yields its base URL."""
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="texspace-load-") as data:
        env = {k: v for k, v in os.environ.items() if not k.startswith("TEXSPACE_")}
        env |= {"TEXSPACE_DATA_DIR": data, "TEXSPACE_PORT": str(port), "TEXSPACE_LOG_LEVEL": "WARNING",
                "TEXSPACE_AUTO_FIT": "false"} | extra_env  # measures serving, not fits behind the uploads
        log_path = Path(data) / "serve.log"
        proc = spawn(["serve"], env, log_path)
        base = f"http://127.0.0.1:{port}"
        try:
            wait_ready(base, [proc], 120, output=lambda: log_path.read_text(errors="replace"), name="texspace serve")
            yield base
        finally:
            stop([proc], grace=20)


def exemplar_png(seed: int) -> bytes:
    """A small real texture photo (scikit-image's CC0 brick), shifted per seed."""
    import numpy as np
    from PIL import Image
    from skimage import data

    grey = np.roll(data.brick(), 37 * seed, axis=1)[:192, :192]
    buf = io.BytesIO()
    Image.fromarray(np.stack([grey, grey, (grey * 0.7).astype(np.uint8)], axis=-1)).save(buf, "PNG")
    return buf.getvalue()


class Recorder:
    def __init__(self) -> None:
        self.latency: dict[str, list[float]] = defaultdict(list)
        self.errors: list[str] = []
        self.back_pressure = 0
        self.accepted_jobs: list[str] = []
        self.cold_by_zoom: dict[int, list[float]] = defaultdict(list)  # tiles served (2xx), by zoom

    def record(self, kind: str, seconds: float, res: httpx.Response | None, error: str | None = None) -> None:
        """Latency under ``kind``; back-pressure answers under ``<kind>_503`` (how fast they come)."""
        if error is not None:
            self.latency[kind].append(seconds)
            self.errors.append(f"{kind}: {error}")
        elif res.status_code in BACK_PRESSURE and "retry-after" in res.headers:
            self.latency[f"{kind}_{res.status_code}"].append(seconds)
            self.back_pressure += 1
        else:
            self.latency[kind].append(seconds)
        if error is None and not (200 <= res.status_code < 300 or res.status_code == 304
                                  or (res.status_code in BACK_PRESSURE and "retry-after" in res.headers)):
            self.errors.append(f"{kind}: HTTP {res.status_code} {res.text[:200]}")


def mix(upload_share: float) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """The kinds and weights of ``MIX`` with uploads taking ``upload_share`` of the requests
    (the tile_cached share gives or takes the difference)."""
    weights = dict(MIX) | {"upload": upload_share}
    weights["tile_cached"] += UPLOAD_SHARE - upload_share
    return tuple(weights), tuple(weights.values())


async def client_loop(i: int, http: httpx.AsyncClient, setup: dict, stop_at: float, rec: Recorder) -> None:
    rng = random.Random(1000 + i)
    kinds, weights = setup["mix"]
    while time.monotonic() < stop_at:
        kind = rng.choices(kinds, weights)[0]
        if kind == "tile_cached":
            request = ("GET", rng.choice(setup["hot"]), {})
        elif kind == "tile_cold":
            texture = rng.choice(setup["textures"])
            z, x, y = rng.randint(4, 8), rng.randint(-10**6, 10**6), rng.randint(-10**6, 10**6)
            request = ("GET", f"/v1/textures/{texture}/tiles/{z}/{x}/{y}.png", {"params": {"seed": rng.randint(0, 99)}})
        elif kind == "job_submit":
            texture = rng.choice(setup["textures"])
            request = ("POST", f"/v1/textures/{texture}/volumes",
                       {"json": {"resolution": 8, "seed": rng.randint(0, 10**6), "format": "npy"}})
        elif kind == "upload":
            request = ("POST", "/v1/textures", {"files": {"image": ("load.png", setup["photo"], "image/png")}})
        else:
            if not rec.accepted_jobs:
                continue
            request = ("GET", f"/v1/jobs/{rng.choice(rec.accepted_jobs)}", {})
        method, url, kwargs = request
        started = time.perf_counter()
        try:
            res = await http.request(method, url, **kwargs)
        except httpx.HTTPError as exc:
            rec.record(kind, time.perf_counter() - started, None, f"{type(exc).__name__}: {exc}")
            continue
        rec.record(kind, time.perf_counter() - started, res)
        if kind == "tile_cold" and res.status_code == 200:
            rec.cold_by_zoom[z].append(time.perf_counter() - started)
        if kind == "job_submit" and res.status_code == 202:
            rec.accepted_jobs.append(res.json()["id"])


async def run_load(base: str, clients: int, seconds: float, upload_share: float = UPLOAD_SHARE
                   ) -> tuple[Recorder, float]:
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base, timeout=120.0, limits=limits) as http:
        textures = []
        for seed in range(2):
            res = await http.post("/v1/textures", files={"image": (f"load-{seed}.png", exemplar_png(seed))})
            res.raise_for_status()
            textures.append(res.json()["id"])
        hot = [f"/v1/textures/{textures[k % 2]}/tiles/6/{k}/{-k}.png" for k in range(HOT_TILES)]
        for url in hot:  # rendered once: from here on these are cache hits
            (await http.get(url)).raise_for_status()
        setup = {"textures": textures, "hot": hot, "photo": exemplar_png(2), "mix": mix(upload_share)}
        rec = Recorder()
        started = time.monotonic()
        await asyncio.gather(*(client_loop(i, http, setup, started + seconds, rec) for i in range(clients)))
        return rec, time.monotonic() - started


def wait_jobs(base: str, job_ids: list[str], timeout: float) -> dict[str, int]:
    """States of the accepted jobs once all are finished (or the timeout passed)."""
    deadline = time.monotonic() + timeout
    states: dict[str, str] = {}
    with httpx.Client(base_url=base, timeout=30) as http:
        pending = list(job_ids)
        while pending and time.monotonic() < deadline:
            still = []
            for job_id in pending:
                state = http.get(f"/v1/jobs/{job_id}").json()["state"]
                states[job_id] = state
                if state in ("queued", "running"):
                    still.append(job_id)
            pending = still
            if pending:
                time.sleep(0.5)
    counts: dict[str, int] = defaultdict(int)
    for state in states.values():
        counts[state] += 1
    return dict(counts)


def summarise(rec: Recorder, elapsed: float, clients: int, seconds: float, job_states: dict[str, int]) -> dict:
    all_latency = [v for values in rec.latency.values() for v in values]
    ms = lambda v: round(v * 1000, 1)  # noqa: E731
    by_kind = {kind: {"requests": len(v), "p50_ms": ms(percentile(v, 50)), "p95_ms": ms(percentile(v, 95))}
               for kind, v in sorted(rec.latency.items())}
    return {
        "clients": clients, "seconds": round(elapsed, 1), "requested_seconds": seconds,
        "requests": len(all_latency), "requests_per_second": round(len(all_latency) / elapsed, 1),
        "p50_ms": ms(percentile(all_latency, 50)), "p95_ms": ms(percentile(all_latency, 95)),
        "errors": len(rec.errors), "error_samples": rec.errors[:10], "back_pressure_responses": rec.back_pressure,
        "by_kind": by_kind, "jobs_accepted": len(rec.accepted_jobs), "jobs_final_states": job_states,
        "tile_cold_by_zoom": {z: {"served": len(v), "p50_ms": ms(percentile(v, 50)), "p95_ms": ms(percentile(v, 95))}
                              for z, v in sorted(rec.cold_by_zoom.items())},
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
    }


def merge_into(path: Path, key: str, value: dict) -> None:
    """Read-modify-write the results file, keeping every other key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        current = json.loads(path.read_text())
    except (OSError, ValueError):
        current = {}
    current[key] = value
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(current, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--base-url", help="an already running server on loopback (default: start one)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--env", action="append", default=[], metavar="TEXSPACE_X=VALUE",
                        help="a setting for the server started here (repeatable); the results key gets "
                             "the values appended")
    parser.add_argument("--max-queued-jobs", type=int, default=32, help="server back-pressure threshold")
    parser.add_argument("--upload-share", type=float, default=UPLOAD_SHARE,
                        help=f"share of requests that upload a photo (default {UPLOAD_SHARE:g}; 0: none, the "
                             "reference for what uploads cost the tiles); the results key gets it appended")
    args = parser.parse_args(argv)
    if not 0 <= args.upload_share <= dict(MIX)["tile_cached"] + UPLOAD_SHARE:
        parser.error("upload share must be 0..0.55")
    if not 1 <= args.clients <= 256 or not 0 < args.seconds <= 600:
        parser.error("clients must be 1..256 and seconds 0..600 (bounded)")
    if args.base_url and not args.base_url.startswith(("http://127.0.0.1", "http://localhost", "http://[::1]")):
        parser.error("loopback only")

    def measure(base: str) -> dict:
        print(f"load: {args.clients} clients for {args.seconds:g} s against {base}", flush=True)
        rec, elapsed = asyncio.run(run_load(base, args.clients, args.seconds, args.upload_share))
        job_states = wait_jobs(base, rec.accepted_jobs, timeout=120)
        return summarise(rec, elapsed, args.clients, args.seconds, job_states)

    extra = dict(item.split("=", 1) for item in args.env)
    if any(not k.startswith("TEXSPACE_") for k in extra):
        parser.error("--env takes TEXSPACE_* settings")
    if args.base_url:
        summary = measure(args.base_url)
    else:
        with serve({"TEXSPACE_MAX_QUEUED_JOBS": str(args.max_queued_jobs)} | extra) as base:
            summary = measure(base)
    summary["settings"], summary["upload_share"] = extra, args.upload_share
    key = (f"load_{args.clients}_clients" + "".join(f"_{v}" for v in extra.values())
           + (f"_uploads_{args.upload_share:g}" if args.upload_share != UPLOAD_SHARE else ""))
    merge_into(args.out, key, summary)
    print(f"{'kind':<12} {'requests':>9} {'p50 ms':>9} {'p95 ms':>9}")
    for kind, row in summary["by_kind"].items():
        print(f"{kind:<12} {row['requests']:>9} {row['p50_ms']:>9} {row['p95_ms']:>9}")
    print(f"{'all':<12} {summary['requests']:>9} {summary['p50_ms']:>9} {summary['p95_ms']:>9}")
    print("cold tiles served, by zoom: " + ", ".join(f"z{z} {row['served']} p50 {row['p50_ms']} p95 {row['p95_ms']} ms"
                                                   for z, row in summary["tile_cold_by_zoom"].items()))
    print(f"{summary['requests_per_second']} requests/s; errors {summary['errors']}; back-pressure "
          f"{summary['back_pressure_responses']}; jobs {summary['jobs_final_states']} of {summary['jobs_accepted']}")
    print(f"written to {args.out} under {key!r}")
    lost = sum(n for state, n in summary["jobs_final_states"].items() if state != "succeeded")
    return 1 if summary["errors"] or lost else 0


if __name__ == "__main__":
    sys.exit(main())
