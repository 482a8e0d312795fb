"""UV atlas generation with xatlas, isolated in a child process.

xatlas can run for minutes and segfaults on some inputs (a regular subdivided
icosphere, an open upstream bug), so it never runs in the worker process: a fresh
``python -m worker.atlas`` child gets the mesh through a temporary .npz, runs under
``RLIMIT_AS`` (memory) and ``RLIMIT_CPU`` plus a wall-clock timeout, and writes the
result to another .npz. After a crash, a kill, a timeout or a missing result the atlas is
made of box-projected charts instead (``worker.box_charts``, in-process, numpy). ``should_cancel`` is polled while the child runs:
when it turns true the child is killed and ``Canceled`` raised.

Output UVs follow the OBJ/glTF-in-trimesh convention (v up): xatlas's v points down
the atlas image, so it is flipped to ``1 - v`` here.

Atlases are cached per mesh content: with ``cache_dir`` set, the result is stored under
the sha256 of the float32 vertices, uint32 faces (what xatlas sees) and the options, so
a second bake of the same mesh loads it (milliseconds) instead of running xatlas again
(tens of seconds for 100k faces). The folder is bounded by ``cache_bytes`` (oldest used
entries removed first); a damaged entry is a miss.

Options (``CHART_OPTIONS``, packing resolution) were measured on the 100k-face bench
mesh; see ``atlas_quality`` and bench/jobs.py for what is reported next to the time.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from typing import Callable

import numpy as np

from worker.box_charts import box_charts
from worker.errors import AtlasFailed, Canceled

log = logging.getLogger(__name__)

# The module the child runs (``python -m``): its ``__main__`` reads in.npz, writes out.npz.
# Tests swap in one that crashes or hangs, to check the parent contains it.
CHILD_MODULE = "worker.atlas"
POLL_SECONDS = 0.2   # how often a running child is checked for cancel and timeout
CACHE_FORMAT = 2     # bump when the stored arrays or their meaning change
DEFAULT_CACHE_BYTES = 512 * 2**20
# xatlas options beyond resolution and padding (attribute names of xatlas.ChartOptions /
# PackOptions). Defaults measured best on the 100k-face bench mesh (docs/PERFORMANCE.md).
CHART_OPTIONS: dict = {}
# The share of the atlas budget xatlas gets before the box-projected charts take over: a noisy
# 100k-face scan ran 415 s in xatlas on a busy 2-core machine; its box charts take 0.2 s.
XATLAS_SHARE = 0.5
PACK_OPTIONS: dict = {"bilinear": True, "bruteForce": False}


def atlas_quality(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> dict:
    """How well an atlas spends its texels.

    vertices : (V, 3) float64, faces : (F, 3) int64, uv : (V, 2) float64.
    Returns ``uv_area``: share of the unit square under charts (texel utilisation before
    rasterisation); ``stretch_l2``: Sander et al.'s L2 stretch normalised by the total
    area ratio, 1.0 when every triangle gets the same texel density, larger otherwise;
    ``area_ratio_p5_p95``: 5th and 95th percentiles (by 3D area) of each face's texel
    density relative to the mean; ``uv_degenerate_area``: share of 3D area on faces whose
    UV triangle has no area (they get no texel).
    """
    q = vertices[faces]
    t = uv[faces]
    area3 = 0.5 * np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), axis=1)
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area2 = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    total3 = area3.sum()
    ok = (np.abs(area2) > 1e-15) & (area3 > 0)
    if not ok.any():
        return {"uv_area": float(np.abs(area2).sum()), "stretch_l2": float("inf"),
                "area_ratio_p5_p95": [0.0, 0.0], "uv_degenerate_area": 1.0}
    a = area2[ok, None]
    # partial derivatives of the surface point with respect to s and t (Sander 2001)
    ss = (q[ok, 0] * (t[ok, 1, 1] - t[ok, 2, 1])[:, None] + q[ok, 1] * (t[ok, 2, 1] - t[ok, 0, 1])[:, None]
          + q[ok, 2] * (t[ok, 0, 1] - t[ok, 1, 1])[:, None]) / (2 * a)
    st = (q[ok, 0] * (t[ok, 2, 0] - t[ok, 1, 0])[:, None] + q[ok, 1] * (t[ok, 0, 0] - t[ok, 2, 0])[:, None]
          + q[ok, 2] * (t[ok, 1, 0] - t[ok, 0, 0])[:, None]) / (2 * a)
    w = area3[ok]
    l2 = np.sqrt(np.sum(w * 0.5 * ((ss ** 2).sum(axis=1) + (st ** 2).sum(axis=1))) / w.sum())
    uv_total = np.abs(area2).sum()
    density = (np.abs(area2[ok]) / uv_total) / (w / w.sum())
    order = np.argsort(density)
    cdf = np.cumsum(w[order]) / w.sum()
    p5, p95 = density[order][np.searchsorted(cdf, [0.05, 0.95])]
    return {"uv_area": float(uv_total), "stretch_l2": float(l2 * np.sqrt(uv_total / w.sum())),
            "area_ratio_p5_p95": [float(p5), float(p95)],
            "uv_degenerate_area": float(1.0 - w.sum() / max(total3, 1e-300))}


def _limit_child(memory_bytes: int, cpu_seconds: int):
    def apply() -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
        resource.setrlimit(resource.RLIMIT_CPU, (cpu_seconds, cpu_seconds + 5))
    return apply


def parametrize(vertices: np.ndarray, faces: np.ndarray, *, resolution: int, padding: int,
                timeout: float = 120.0, memory_bytes: int = 2 << 30,
                should_cancel: Callable[[], bool] | None = None,
                cache_dir: str | os.PathLike | None = None,
                cache_bytes: int = DEFAULT_CACHE_BYTES) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Run xatlas in a limited child process, or load its earlier result from ``cache_dir``.

    vertices : (V, 3) float64, faces : (F, 3) int64.
    Returns (vmap (V',) int64 original vertex of each new vertex, faces (F, 3) int64 into
    the new vertices, uv (V', 2) float64 in [0, 1], v up, the method: "xatlas" or "box").

    xatlas gets ``XATLAS_SHARE`` of ``timeout``; when it crashes or runs out of it, the
    atlas is made of box-projected charts (``worker.box_charts``: well under a second for
    200k faces, about half the texel use of xatlas's, stretch as low), so a mesh xatlas
    cannot unwrap in time is still baked.
    """
    key = path = None
    if cache_dir is not None:
        key = cache_key(vertices, faces, resolution=resolution, padding=padding)
        path = os.path.join(cache_dir, f"{key}.npz")
        hit = _cache_load(path, len(vertices), len(faces))
        if hit is not None:
            return hit
    try:
        result = (*_run_child(vertices, faces, resolution=resolution, padding=padding,
                              timeout=timeout * XATLAS_SHARE, memory_bytes=memory_bytes,
                              should_cancel=should_cancel), "xatlas")
    except AtlasFailed as exc:  # (a cancel is not a failure: it propagates)
        log.warning("xatlas gave no atlas (%s); box-projected charts instead", exc.detail)
        result = (*box_charts(vertices, faces, resolution=resolution, padding=padding), "box")
    if path is not None:
        _cache_store(path, result, cache_bytes)
    return result


def cache_key(vertices: np.ndarray, faces: np.ndarray, *, resolution: int, padding: int) -> str:
    """sha256 hex of what xatlas gets (float32 vertices, uint32 faces) and every option."""
    digest = hashlib.sha256()
    options = {"format": CACHE_FORMAT, "xatlas": _xatlas_version(), "resolution": int(resolution), "padding": int(padding),
               "chart": CHART_OPTIONS, "pack": PACK_OPTIONS, "shape": [len(vertices), len(faces)]}
    digest.update(json.dumps(options, sort_keys=True).encode())
    digest.update(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.uint32).tobytes())
    return digest.hexdigest()


def _xatlas_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("xatlas")
    except PackageNotFoundError:
        return "unknown"


def _cache_load(path: str, n_vertices: int, n_faces: int):
    """The cached (vmap, faces, uv, method), or None when absent or not a valid atlas of this mesh."""
    try:
        with np.load(path) as out:
            vmap, faces, uv = (out["vmap"].astype(np.int64), out["faces"].astype(np.int64),
                               out["uv"].astype(np.float64))
            method = str(out["method"])
    except (OSError, KeyError, ValueError, EOFError):
        return None
    ok = (faces.shape == (n_faces, 3) and uv.shape == (len(vmap), 2) and len(vmap) > 0
          and 0 <= vmap.min() and vmap.max() < n_vertices and 0 <= faces.min() and faces.max() < len(vmap)
          and np.isfinite(uv).all())
    if not ok:
        return None
    try:
        os.utime(path)               # most recently used: evicted last
    except OSError:
        pass
    return vmap, faces, uv, method


def _cache_store(path: str, result, cache_bytes: int) -> None:
    """Write one entry atomically, then drop the least recently used beyond ``cache_bytes``.
    A cache that cannot be written only costs the next bake its atlas time."""
    folder = os.path.dirname(path)
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            vmap, faces, uv, method = result
            np.savez(f, vmap=vmap.astype(np.int32), faces=faces.astype(np.int32), uv=uv, method=method)
        os.replace(tmp, path)
        entries = []
        for name in os.listdir(folder):
            if name.endswith(".npz"):
                st = os.stat(os.path.join(folder, name))
                entries.append((st.st_mtime, st.st_size, name))
        total = sum(size for _, size, _ in entries)
        for _, size, name in sorted(entries):
            if total <= cache_bytes:
                break
            os.remove(os.path.join(folder, name))
            total -= size
    except OSError:
        pass


def _run_child(vertices, faces, *, resolution, padding, timeout, memory_bytes, should_cancel):
    with tempfile.TemporaryDirectory(prefix="texspace-atlas-") as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(src, vertices=vertices.astype(np.float32), faces=faces.astype(np.uint32),
                 resolution=resolution, padding=padding,
                 options=json.dumps({"chart": CHART_OPTIONS, "pack": PACK_OPTIONS}))
        env = dict(os.environ)
        env["OMP_NUM_THREADS"] = env["OPENBLAS_NUM_THREADS"] = "1"   # small VM footprint under RLIMIT_AS
        err_path = os.path.join(tmp, "stderr.txt")
        with open(err_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-m", CHILD_MODULE, src, dst], env=env,
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                    preexec_fn=_limit_child(memory_bytes, int(timeout) + 1),
                                    cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
            _wait_child(proc, timeout, should_cancel)
        if proc.returncode != 0:
            cause = (f"killed by signal {-proc.returncode}" if proc.returncode < 0
                     else f"exit status {proc.returncode}")
            with open(err_path, "rb") as err:
                stderr = err.read()
            tail = stderr.decode(errors="replace").strip().splitlines()[-1:] or [""]
            raise AtlasFailed(f"UV atlas generation failed ({cause}) {tail[0]}".strip())
        try:
            with np.load(dst) as out:
                return (out["vmap"].astype(np.int64), out["faces"].astype(np.int64),
                        out["uv"].astype(np.float64))
        except (OSError, KeyError, ValueError) as exc:
            raise AtlasFailed(f"UV atlas generation produced no result: {exc}") from None


def _wait_child(proc: subprocess.Popen, timeout: float, should_cancel: Callable[[], bool] | None) -> None:
    """Wait for the child; kill it (and raise) on timeout or cancel."""
    deadline = time.monotonic() + timeout
    try:
        while True:
            try:
                proc.wait(min(POLL_SECONDS, max(0.0, deadline - time.monotonic())))
                return
            except subprocess.TimeoutExpired:
                pass
            if should_cancel is not None and should_cancel():
                raise Canceled("bake job canceled during UV atlas generation")
            if time.monotonic() >= deadline:
                raise AtlasFailed(f"UV atlas generation took longer than {timeout:.0f} s")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _child_main(src: str, dst: str) -> None:
    import xatlas
    with np.load(src) as inp:
        vertices, faces = inp["vertices"], inp["faces"]
        resolution, padding = int(inp["resolution"]), int(inp["padding"])
        options = json.loads(str(inp["options"]))
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices, faces)
    chart, pack = xatlas.ChartOptions(), xatlas.PackOptions()
    for target, values in ((chart, options["chart"]), (pack, options["pack"])):
        for name, value in values.items():
            setattr(target, name, value)
    pack.resolution = resolution
    pack.padding = padding
    atlas.generate(chart, pack)
    vmap, new_faces, uv = atlas[0]
    uv = uv.astype(np.float64)
    uv[:, 1] = 1.0 - uv[:, 1]
    np.savez(dst, vmap=vmap, faces=new_faces, uv=uv)


if __name__ == "__main__":
    _child_main(sys.argv[1], sys.argv[2])
