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
# Candidate (triangle, texel) pairs per batch. Small batches keep each float64
# temporary (512 KB) in cache: 2048^2 atlas of the 100k-face bench mesh, best of 3:
# 2^22 0.69 s, 2^20 0.46, 2^18 0.33, 2^16 0.29 (same output). Two threads over the
# batches gained nothing measurable, so it stays one loop.
BATCH_CANDIDATES = 1 << 16


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
    batches = []
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
        batches.append((faces[start:stop], int(w), int(h)))
        start = stop
    if not batches:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))

    def cover(job):
        batch, w, h = job
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
        return (rows[bi, yi] * R + cols[bi, xi], batch[bi],
                np.stack([b0[bi, yi, xi], b1[bi, yi, xi], b2[bi, yi, xi]], axis=1))

    texels, owners, barys = zip(*map(cover, batches))
    return np.concatenate(texels), np.concatenate(owners), np.concatenate(barys)


def last_hits(texel: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Covered texels and, for each, its last (texel, triangle) pair.

    texel : (K,) int64 flat indices from ``rasterise``. Returns (texels (T,) unique flat
    indices in increasing order, pick (T,) int64 index into the K pairs).
    """
    # A scatter-max over an atlas-sized table: 0.03-0.09 s for 2.5M texels against
    # 0.7 s for the np.unique sort it replaced (same result).
    last = np.full(int(resolution) ** 2, -1, dtype=np.int64)
    np.maximum.at(last, texel, np.arange(len(texel), dtype=np.int64))
    uniq = np.flatnonzero(last >= 0)
    return uniq, last[uniq]


def barycentric_points(face: np.ndarray, bary: np.ndarray, tri_xyz: np.ndarray) -> np.ndarray:
    """face (T,) int64, bary (T, 3) float64, tri_xyz (F, 3, 3) float64 -> points (T, 3) float64.

    Corner by corner: three (T, 3) gathers instead of one (T, 3, 3) temporary.
    """
    pts = bary[:, 0, None] * tri_xyz[face, 0]
    pts += bary[:, 1, None] * tri_xyz[face, 1]
    pts += bary[:, 2, None] * tri_xyz[face, 2]
    return pts


def surface_points(texel: np.ndarray, face: np.ndarray, bary: np.ndarray, tri_xyz: np.ndarray,
                   resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """One 3D point per covered texel.

    tri_xyz : (F, 3, 3) float64 triangle corners. Returns (texels (T,) unique flat
    indices in increasing order, points (T, 3) float64); where a texel lies on several
    triangles the last wins.
    """
    uniq, pick = last_hits(texel, resolution)
    return uniq, barycentric_points(face[pick], bary[pick], tri_xyz)


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
