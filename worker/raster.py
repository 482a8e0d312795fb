"""UV-space rasterisation of triangles into a texture atlas, and gutter filling.

Texel (row r, column c) of an R x R atlas has its centre at uv
``((c + 0.5) / R, 1 - (r + 0.5) / R)`` (v up, row 0 at the top of the image, as OBJ
and trimesh's glTF exporter expect). A texel is *covered* when its centre lies inside
(or on the edge of) a triangle's UV image; its 3D surface point is the barycentric
blend of that triangle's vertex positions.

Vectorised: triangles are sorted by bounding-box size and processed in batches; each
batch forms a (triangles x bbox-texels) candidate grid, computes barycentrics for all
candidates at once and keeps the inside ones. No per-texel Python.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

EDGE_EPS = 1e-9           # barycentric tolerance: texel centres on an edge count as inside
BATCH_CANDIDATES = 1 << 22  # candidate (triangle, texel) pairs per batch (~100 MB of temporaries)


def uv_to_texel(uv: np.ndarray, resolution: int) -> np.ndarray:
    """uv (..., 2) in [0, 1], v up -> continuous texel coords (..., 2) as (x = column, y = row)."""
    return np.stack([uv[..., 0] * resolution, (1.0 - uv[..., 1]) * resolution], axis=-1)


def rasterise(tri_uv: np.ndarray, resolution: int):
    """Cover an atlas with triangles.

    tri_uv : (F, 3, 2) float64 UVs of each triangle's corners.
    Returns (texel (K,) int64 flat index r*R + c, face (K,) int64, bary (K, 3) float64)
    for every (texel, triangle) pair whose texel centre is inside the triangle
    (a texel on a shared edge may appear twice: same surface point either way).
    """
    R = int(resolution)
    p = uv_to_texel(np.asarray(tri_uv, dtype=np.float64), R)             # (F, 3, 2)
    lo = np.clip(np.ceil(p.min(axis=1) - 0.5), 0, R - 1).astype(np.int64)   # first texel centre >= min
    hi = np.clip(np.floor(p.max(axis=1) - 0.5), -1, R - 1).astype(np.int64)
    dims = hi - lo + 1                                                   # (F, 2) bbox width, height
    keep = (dims > 0).all(axis=1)
    (e1, e2), p0 = (p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep &= np.abs(det) > 1e-12                                          # UV-degenerate triangles cover nothing
    faces = np.flatnonzero(keep)
    faces = faces[np.argsort(dims[faces].prod(axis=1), kind="stable")]
    texels, owners, barys = [], [], []
    start = 0
    while start < len(faces):
        # As many triangles as fit the candidate budget once padded to the batch's
        # largest bounding box (sorted by size, so padding wastes little).
        count = max(1, BATCH_CANDIDATES // int(dims[faces[start]].prod()))
        while True:
            stop = min(start + count, len(faces))
            w, h = dims[faces[start:stop]].max(axis=0)
            if count == 1 or (stop - start) * w * h <= BATCH_CANDIDATES:
                break
            count //= 2
        batch = faces[start:stop]
        start = stop
        cols = lo[batch, 0, None] + np.arange(w)[None, :]                # (B, w)
        rows = lo[batch, 1, None] + np.arange(h)[None, :]                # (B, h)
        dx = (cols + 0.5 - p0[batch, 0, None])[:, None, :]               # (B, 1, w)
        dy = (rows + 0.5 - p0[batch, 1, None])[:, :, None]               # (B, h, 1)
        inv = 1.0 / det[batch]
        b1 = (dx * e2[batch, 1, None, None] - dy * e2[batch, 0, None, None]) * inv[:, None, None]
        b2 = (dy * e1[batch, 0, None, None] - dx * e1[batch, 1, None, None]) * inv[:, None, None]
        b0 = 1.0 - b1 - b2
        inside = (b0 >= -EDGE_EPS) & (b1 >= -EDGE_EPS) & (b2 >= -EDGE_EPS)
        inside &= (cols < R)[:, None, :] & (rows < R)[:, :, None]
        inside &= (cols <= hi[batch, 0, None])[:, None, :] & (rows <= hi[batch, 1, None])[:, :, None]
        bi, yi, xi = np.nonzero(inside)
        texels.append(rows[bi, yi] * R + cols[bi, xi])
        owners.append(batch[bi])
        barys.append(np.stack([b0[bi, yi, xi], b1[bi, yi, xi], b2[bi, yi, xi]], axis=1))
    if not texels:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(texels), np.concatenate(owners), np.concatenate(barys)


def surface_points(texel: np.ndarray, face: np.ndarray, bary: np.ndarray, tri_xyz: np.ndarray,
                   resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """One 3D point per covered texel.

    tri_xyz : (F, 3, 3) float64 triangle corners. Returns (texels (T,) unique flat
    indices, points (T, 3) float64); where a texel lies on several triangles the last wins.
    """
    # np.unique on the reversed arrays keeps the last occurrence of each texel.
    uniq, first_rev = np.unique(texel[::-1], return_index=True)
    pick = len(texel) - 1 - first_rev
    pts = np.einsum("kc,kcd->kd", bary[pick], tri_xyz[face[pick]])
    return uniq, pts


def overlap_fraction(texel: np.ndarray, resolution: int) -> float:
    """Share of covered texels hit by more than one triangle (strictly overlapping UVs
    hit interiors twice; shared edges only hit a thin line, which stays small)."""
    if len(texel) == 0:
        return 0.0
    hits = np.bincount(texel, minlength=resolution * resolution)
    return float((hits > 1).sum() / max(1, (hits > 0).sum()))


def fill_gutter(image: np.ndarray, covered: np.ndarray, padding: int) -> np.ndarray:
    """Copy the nearest covered texel into every uncovered texel within ``padding`` texels.

    image : (R, R, C) float32, covered : (R, R) bool. Returns a new (R, R, C) array;
    texels farther than ``padding`` from any chart keep their value. Uses one exact
    Euclidean distance transform (scipy), so texture filtering and mipmaps near chart
    borders read chart colours instead of background.
    """
    if covered.all() or not covered.any():
        return image.copy()
    dist, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
    out = image.copy()
    near = (dist <= padding) & ~covered
    out[near] = image[ri[near], ci[near]]
    return out
