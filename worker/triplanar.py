"""Triplanar projection: a texture's xy plane read along the axis a surface faces.

    sample_triplanar(sampler, points, normals, code, seed)  ->  linear RGB (N, 3)

A solid texture fitted on a 2D repeat lattice (bricks, tiles) holds its photo's pattern in
the xy plane only and draws it through z: a surface facing x cuts it into stripes. Reading
the xy plane at the surface point's two other coordinates shows the pattern on every face:
a face facing x reads (z, y), one facing y (x, z), one facing z (x, y), so on a y-up mesh
(glTF's convention) walls keep their rows horizontal. Each projection sits at its own depth
on the plane, so no two faces show the same patch. Bakes use it (``worker/bake.py``,
``projection``) and every emitted shader carries it (``worker/shader.py``, ``<name>_triplanar``),
with these constants.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from worker.runtime import Sampler

PROJECTIONS = ("solid", "triplanar")  # the bake's choices
# Triplanar blend weight of an axis: |n_axis| ** TRIPLANAR_SHARPNESS, renormalised, after
# dropping weights under TRIPLANAR_MIN_WEIGHT: a face turned 35-55 degrees between two axes
# blends their projections, the rest read one, at the sampler cost of one. With 4 and 0.02
# (blends from 21 degrees) the bench mesh's triplanar bake took 2.0x the solid bake, with
# these 1.3-1.4x (bench/run.py --only bake --quick, three runs).
TRIPLANAR_SHARPNESS = 8.0
TRIPLANAR_MIN_WEIGHT = 0.05
# World-unit depth (z) on the texture's xy plane of the x-, y- and z-facing projections
TRIPLANAR_DEPTHS = (0.0, 37.25, 74.5)


def triplanar_weights(normals: np.ndarray) -> np.ndarray:
    """(N, 3) normals (any length) -> (N, 3) float64 weights of the x-, y- and z-facing
    projections, summing to 1 (a zero normal reads the z-facing one)."""
    weights = np.abs(normals) ** TRIPLANAR_SHARPNESS
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)
    weights[weights < TRIPLANAR_MIN_WEIGHT] = 0.0
    weights[weights.sum(axis=1) == 0, 2] = 1.0
    return weights / weights.sum(axis=1, keepdims=True)


def projected_points(points: np.ndarray, axis: int) -> np.ndarray:
    """(N, 3) surface points -> (N, 3) points on the texture's xy plane seen along ``axis``:
    x-facing (0) reads (z, y), y-facing (1) (x, z), z-facing (2) (x, y), at depth
    ``TRIPLANAR_DEPTHS[axis]``."""
    u, v = {0: (2, 1), 1: (0, 2), 2: (0, 1)}[axis]
    out = np.empty_like(points)
    out[:, 0], out[:, 1], out[:, 2] = points[:, u], points[:, v], TRIPLANAR_DEPTHS[axis]
    return out


def sample_triplanar(sampler: Sampler, points: np.ndarray, normals: np.ndarray, code, seed) -> np.ndarray:
    """Linear RGB (N, 3) float32 of the triplanar projection at surface points with these normals;
    each projection is evaluated only where its weight is not zero."""
    weights = triplanar_weights(normals)
    rgb = np.zeros((len(points), 3), np.float32)
    for axis in range(3):
        used = np.flatnonzero(weights[:, axis])
        if len(used) == len(points):
            rgb += weights[:, axis, None].astype(np.float32) * sampler.sample(projected_points(points, axis), code, seed)
        elif len(used):
            rgb[used] += (weights[used, axis, None].astype(np.float32)
                          * sampler.sample(projected_points(points[used], axis), code, seed))
    return rgb
