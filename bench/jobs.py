"""Job benchmarks: a 256^3 volume in a child process (peak RSS) and a 2048^2 bake of a
~100k-face mesh without UVs (xatlas timed apart).

    python -m bench.jobs volume MODEL_DIR RESOLUTION   # child: prints {"seconds", "peak_rss_mb"}
"""
from __future__ import annotations

import io
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT


def bench_volume(model_dir: Path, resolution: int = 256, log=print) -> dict:
    """render_volume to .npy in a fresh child process; its wall time and peak RSS."""
    proc = subprocess.run([sys.executable, "-m", "bench.jobs", "volume", str(model_dir), str(resolution)],
                          cwd=ROOT, capture_output=True, text=True, timeout=900, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"volume child failed: {proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    log(f"  volume {resolution}^3: {result['seconds']:.2f} s, peak RSS {result['peak_rss_mb']:.0f} MB")
    return result


def _volume_child(model_dir: str, resolution: int) -> None:
    from worker.runtime import ModelRuntime
    from worker.volumes import render_volume

    runtime = ModelRuntime(model_dir)
    code = np.random.default_rng(1).standard_normal(runtime.code_size).astype(np.float32)
    runtime.sample(np.zeros((4096, 3)), code, 0)  # session warm-up, as in a running worker
    with tempfile.TemporaryDirectory(prefix="texspace-bench-vol-") as tmp:
        t = time.perf_counter()
        render_volume(runtime, code, 5, resolution=resolution, fmt="npy", out_path=Path(tmp) / "v.npy",
                      max_voxels=resolution ** 3)
        seconds = time.perf_counter() - t
    print(json.dumps({"seconds": seconds, "peak_rss_mb": peak_rss_kb() / 1024.0}))


def peak_rss_kb() -> int:
    """Peak RSS of this process image (VmHWM). Not ru_maxrss: Linux carries a forked
    parent's RSS over into the child's ru_maxrss across exec (the bench parent holds
    torch, ~1 GB, which a first run reported as the volume's peak)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux


def bench_mesh(target_faces: int = 100_000) -> tuple[bytes, int]:
    """OBJ bytes of a ~100k-face mesh without UVs, and its face count.

    The repo's bunny (902 faces, pybullet_data) subdivided three times (57.7k faces),
    then the faces of one side (centroid x below a quantile) once more, so the face
    count lands near ``target_faces``; vertices are displaced along their normals by a
    smooth pseudo-random field. Irregular on purpose: xatlas segfaults on a perfectly
    regular subdivided icosphere (ASSETS.md).
    """
    import trimesh
    from trimesh import remesh

    mesh = trimesh.load(ROOT / "tests" / "data" / "meshes" / "bunny.obj", process=False, force="mesh")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    for _ in range(3):
        v, f = remesh.subdivide(v, f)
    extra = max(0, target_faces - len(f)) // 3
    centroid_x = v[f].mean(axis=1)[:, 0]
    pick = np.argsort(centroid_x)[:extra]
    v, f = remesh.subdivide(v, f, face_index=pick)
    m = trimesh.Trimesh(v, f, process=False)
    scale = float(np.ptp(v, axis=0).max())
    p = v / scale
    field = (np.sin(17 * p[:, 0] + 3 * np.cos(11 * p[:, 1])) * np.cos(13 * p[:, 2] + 2 * p[:, 0])
             + 0.5 * np.sin(41 * p[:, 1] + 29 * p[:, 2]))
    m.vertices = v + m.vertex_normals * (0.004 * scale * field)[:, None]
    buf = io.StringIO()
    np.savetxt(buf, m.vertices, fmt="v %.7f %.7f %.7f")
    np.savetxt(buf, m.faces + 1, fmt="f %d %d %d")
    return buf.getvalue().encode(), len(m.faces)


def bench_bake(model_dir: Path, resolution: int = 2048, log=print) -> dict:
    """bake_mesh (GLB) of the bench mesh at resolution^2 with xatlas UVs; stage timings."""
    from worker.bake import BakeLimits, bake_mesh
    from worker.runtime import ModelRuntime

    runtime = ModelRuntime(model_dir)
    code = np.random.default_rng(1).standard_normal(runtime.code_size).astype(np.float32)
    runtime.sample(np.zeros((4096, 3)), code, 0)
    mesh, faces = bench_mesh()
    with tempfile.TemporaryDirectory(prefix="texspace-bench-bake-") as tmp:
        t = time.perf_counter()
        result = bake_mesh(runtime, code, 5, mesh_bytes=mesh, filename="bench.obj", resolution=resolution,
                           fmt="glb", out_path=Path(tmp) / "bake.glb", limits=BakeLimits(atlas_timeout=600))
        seconds = time.perf_counter() - t
    texels = int(result.covered.sum())
    stages = {k: round(v, 3) for k, v in result.timings.items()}
    log(f"  bake {resolution}^2, {faces} faces, {texels} texels: {seconds:.2f} s "
        f"(xatlas {result.timings['atlas']:.2f} s; stages {stages})")
    return {"bake_2048_s": seconds, "bake_2048_xatlas_s": result.timings["atlas"],
            "bake_2048_excl_xatlas_s": seconds - result.timings["atlas"], "bake_2048_texels": texels,
            "bake_2048_faces": faces, "bake_2048_stages_s": stages, "bake_2048_uv_source": result.uv_source}


if __name__ == "__main__":
    if sys.argv[1] == "volume":
        _volume_child(sys.argv[2], int(sys.argv[3]))
    else:
        sys.exit(f"unknown child command {sys.argv[1]!r}")
