"""Solid 3D textures: an N^3 grid of the sampler, written slab by slab.

The volume covers the world box ``bounds = (min_xyz, max_xyz)``; voxel (i, j, k) has
its centre at ``min + (index + 0.5) * (max - min) / N`` per axis, with array order
[z, y, x, channel]. The grid is evaluated ``slab`` z-slices at a time and each slab is
handed to a streaming writer (formats and file layouts: ``worker/volume_writers.py``),
so memory is O(slab * N^2) whatever N is (a VDB is spooled to disk and encoded once the
last slab is in, one 128^3 block at a time; the encode counts as the last 10% of
progress). Progress is reported after every slab and ``should_cancel()`` is asked before
every slab (Canceled is raised, the partial file is removed). The file is written under a temporary name in the target folder and renamed
into place, so readers never see half a volume and a re-run simply overwrites.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from worker.contract import MAX_VOLUME_RESOLUTION, MIN_VOLUME_RESOLUTION
from worker.errors import Canceled, InvalidParameter, LimitExceeded
from worker.files import atomic_output, extension
from worker.runtime import Sampler
from worker.volume_writers import VOLUME_FORMATS, WRITERS

SLAB_POINTS = 2 ** 18          # default points per slab (~6 MB of positions)
MAX_FLIPBOOK_SIDE = 16384      # PNG width/height a texture importer can take
DEFAULT_BOUNDS = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

ProgressFn = Callable[[float], None] | None
CancelFn = Callable[[], bool] | None


def voxel_centres(lo: float, hi: float, n: int) -> np.ndarray:
    """(n,) float64 centres of n equal cells between lo and hi."""
    return lo + (np.arange(n, dtype=np.float64) + 0.5) * ((hi - lo) / n)


def slab_points(axes: tuple[np.ndarray, np.ndarray, np.ndarray], z0: int, z1: int) -> np.ndarray:
    """Points of slices [z0, z1): (nz * Ny * Nx, 3) float64, order [z][y][x], by broadcasting."""
    xs, ys, zs = axes
    pts = np.empty((z1 - z0, len(ys), len(xs), 3), dtype=np.float64)
    pts[..., 0] = xs[None, None, :]
    pts[..., 1] = ys[None, :, None]
    pts[..., 2] = zs[z0:z1, None, None]
    return pts.reshape(-1, 3)


def render_volume(sampler: Sampler, code: np.ndarray, seed: int, *, resolution: int,
                  bounds=DEFAULT_BOUNDS, fmt: str = "npy", out_path: str | os.PathLike,
                  slab: int | None = None, max_voxels: int = 512 ** 3,
                  progress: ProgressFn = None, should_cancel: CancelFn = None) -> Path:
    """Evaluate the texture on an N^3 grid and write it to ``out_path`` in ``fmt``.

    code : (8,) float32. bounds : ((x0, y0, z0), (x1, y1, z1)) world box.
    slab : z-slices per sampler call (default: about SLAB_POINTS points).
    Returns the final path.
    """
    n = int(resolution)
    if fmt not in VOLUME_FORMATS:
        raise InvalidParameter(f"volume format must be one of {VOLUME_FORMATS}, got {fmt!r}")
    if not MIN_VOLUME_RESOLUTION <= n <= MAX_VOLUME_RESOLUTION:
        raise InvalidParameter(f"resolution must be in [{MIN_VOLUME_RESOLUTION}, {MAX_VOLUME_RESOLUTION}], got {n}")
    if n ** 3 > max_voxels:
        raise LimitExceeded(f"{n}^3 = {n ** 3} voxels exceeds the limit of {max_voxels}")
    box = np.asarray(bounds, dtype=np.float64)
    if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[1] > box[0]).all():
        raise InvalidParameter("bounds must be ((x0, y0, z0), (x1, y1, z1)) with max > min")
    out_path = Path(out_path)
    with atomic_output(out_path, suffix=extension(fmt)) as tmp:
        writer = WRITERS[fmt](tmp, n, box)
        if fmt == "flipbook" and max(writer.cols, writer.rows) * n > MAX_FLIPBOOK_SIDE:
            writer.close()
            raise LimitExceeded(f"flipbook of {n} slices would exceed {MAX_FLIPBOOK_SIDE} px per side")
        step = int(slab or max(1, SLAB_POINTS // (n * n)))
        share = 0.9 if fmt == "vdb" else 1.0     # a VDB is encoded in close(), after the last slab
        axes = tuple(voxel_centres(box[0, a], box[1, a], n) for a in range(3))
        try:
            for z0 in range(0, n, step):
                if should_cancel is not None and should_cancel():
                    raise Canceled("volume job canceled")
                z1 = min(z0 + step, n)
                rgb = sampler.sample(slab_points(axes, z0, z1), code, seed)
                writer.write(rgb.reshape(z1 - z0, n, n, 3))
                if progress is not None:
                    progress(share * z1 / n)
        except BaseException:
            try:  # atomic_output deletes the partial file; keep the original error
                writer.close()
            except Exception:
                pass
            raise
        writer.close()
        if progress is not None and share < 1.0:
            progress(1.0)
    return out_path
