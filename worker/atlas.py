"""UV atlas generation with xatlas, isolated in a child process.

xatlas can run for minutes and segfaults on some inputs (a regular subdivided
icosphere, an open upstream bug), so it never runs in the worker process: a fresh
``python -m worker.atlas`` child gets the mesh through a temporary .npz, runs under
``RLIMIT_AS`` (memory) and ``RLIMIT_CPU`` plus a wall-clock timeout, and writes the
result to another .npz. A crash, a kill, a timeout or a missing result raises
``AtlasFailed``; the caller lives on. ``should_cancel`` is polled while the child runs:
when it turns true the child is killed and ``Canceled`` raised.

Output UVs follow the OBJ/glTF-in-trimesh convention (v up): xatlas's v points down
the atlas image, so it is flipped to ``1 - v`` here.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from typing import Callable

import numpy as np

from worker.errors import AtlasFailed, Canceled

TEST_CRASH_ENV = "TEXSPACE_ATLAS_TEST_CRASH"   # test hook: "segfault" | "abort" | "hang"
POLL_SECONDS = 0.2   # how often a running child is checked for cancel and timeout


def _limit_child(memory_bytes: int, cpu_seconds: int):
    def apply() -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
        resource.setrlimit(resource.RLIMIT_CPU, (cpu_seconds, cpu_seconds + 5))
    return apply


def parametrize(vertices: np.ndarray, faces: np.ndarray, *, resolution: int, padding: int,
                timeout: float = 120.0, memory_bytes: int = 2 << 30,
                crash_for_test: str | None = None,
                should_cancel: Callable[[], bool] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run xatlas in a limited child process.

    vertices : (V, 3) float64, faces : (F, 3) int64.
    Returns (vmap (V',) int64 original vertex of each new vertex, faces (F, 3) int64 into
    the new vertices, uv (V', 2) float64 in [0, 1], v up).
    """
    with tempfile.TemporaryDirectory(prefix="texspace-atlas-") as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(src, vertices=vertices.astype(np.float32), faces=faces.astype(np.uint32),
                 resolution=resolution, padding=padding)
        env = dict(os.environ)
        env.pop(TEST_CRASH_ENV, None)
        if crash_for_test:
            env[TEST_CRASH_ENV] = crash_for_test
        env["OMP_NUM_THREADS"] = env["OPENBLAS_NUM_THREADS"] = "1"   # small VM footprint under RLIMIT_AS
        err_path = os.path.join(tmp, "stderr.txt")
        with open(err_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-m", "worker.atlas", src, dst], env=env,
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
    hook = os.environ.get(TEST_CRASH_ENV)
    if hook == "segfault":
        import ctypes
        ctypes.string_at(0)          # dereference NULL: SIGSEGV, like the xatlas bug
    elif hook == "abort":
        os.abort()
    elif hook == "hang":
        import time
        time.sleep(3600)
    import xatlas
    with np.load(src) as inp:
        vertices, faces = inp["vertices"], inp["faces"]
        resolution, padding = int(inp["resolution"]), int(inp["padding"])
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices, faces)
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.padding = padding
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmap, new_faces, uv = atlas[0]
    uv = uv.astype(np.float64)
    uv[:, 1] = 1.0 - uv[:, 1]
    np.savez(dst, vmap=vmap, faces=new_faces, uv=uv)


if __name__ == "__main__":
    _child_main(sys.argv[1], sys.argv[2])
