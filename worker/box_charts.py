"""A UV atlas in seconds for any mesh: box-projected charts on a shelf.

xatlas grows charts by optimising seams and stretch; on a noisy scanned mesh that costs
minutes (100k faces with vertex noise of 0.3 edge lengths: 415 s and 23,814 charts on a
busy 2-core machine) and it crashes on some regular meshes. This is the fallback
``worker.atlas.parametrize`` takes then: every face goes to the side of a box its
(smoothed) normal faces most, each side's connected pieces are projected flat onto that
side, and the pieces are packed row by row. Texel density is the same on every chart (one
world unit is the same number of texels everywhere); a face tilted from its side's axis by
up to 55 degrees is stretched by up to 1.7x along the tilt.

Functions over arrays: (V, 3) float vertices and (F, 3) int faces in, the same
``(vmap, faces, uv)`` triple as xatlas out (uv in [0, 1], v up).
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

# Smoothing passes of the face normals before a face picks its side: each pass averages
# over one more ring of neighbours, so the noise of a scan does not cut its surface into
# one chart per few faces (the noisy 100k-face mesh: 8 passes, 1.0k charts instead of 60k).
SMOOTHING_PASSES = 8
# A face keeps the side its neighbourhood faces while its own normal is within 70 degrees
# of that side's axis (it is stretched at most 1 / cos(70) = 2.9x), else it takes its own.
MAX_TILT_COS = 0.34
# Per side of the box: the two axes its charts are projected onto, ordered so that a face
# wound counter-clockwise seen from outside stays counter-clockwise in UV.
SIDE_AXES = {(0, 1): (1, 2), (1, 1): (2, 0), (2, 1): (0, 1), (0, -1): (2, 1), (1, -1): (0, 2), (2, -1): (1, 0)}


def area_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) face normals, each as long as twice its face's area."""
    tri = vertices[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def smoothed_face_normals(normals: np.ndarray, faces: np.ndarray, n_vertices: int,
                          passes: int = SMOOTHING_PASSES) -> np.ndarray:
    """(F, 3) unit normals of ``normals`` (``area_normals``) averaged ``passes`` times through
    the shared vertices (area-weighted)."""
    corners = faces.reshape(-1)
    for _ in range(passes):
        at_vertex = np.zeros((n_vertices, 3))
        for axis in range(3):
            at_vertex[:, axis] = np.bincount(corners, np.repeat(normals[:, axis], 3), minlength=n_vertices)
        normals = at_vertex[faces].sum(axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def _side_of(normals: np.ndarray) -> np.ndarray:
    axis = np.abs(normals).argmax(axis=1)
    return 2 * axis + (normals[np.arange(len(normals)), axis] < 0)


def box_sides(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) side of the box each face is projected onto: 2 * axis + (1 if the normal points
    down that axis), by its smoothed normal; a face whose own normal leans more than
    ``MAX_TILT_COS`` off that side's axis takes its own side instead (else it would be a
    sliver in UV, with almost no texels)."""
    normals = area_normals(vertices, faces)
    own = smoothed_face_normals(normals, faces, len(vertices), passes=0)
    side = _side_of(smoothed_face_normals(normals, faces, len(vertices)))
    axis, sign = side // 2, np.where(side % 2, -1.0, 1.0)
    facing = own[np.arange(len(faces)), axis] * sign
    return np.where(facing >= MAX_TILT_COS, side, _side_of(own))


def box_charts(vertices: np.ndarray, faces: np.ndarray, *, resolution: int,
               padding: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The atlas: (vmap (V',) original vertex of each new vertex, faces (F, 3) into the new
    vertices, uv (V', 2) in [0, 1], v up), charts ``padding`` texels apart at ``resolution``."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    side = box_sides(vertices, faces)
    # one new vertex per (vertex, side) a face uses: charts on different sides share no vertex
    keys = faces * 6 + side[:, None]
    unique_keys, new_faces = np.unique(keys.reshape(-1), return_inverse=True)
    new_faces = new_faces.reshape(-1, 3)
    vmap, vertex_side = unique_keys // 6, unique_keys % 6
    points = vertices[vmap]
    uv = np.empty((len(vmap), 2))
    for code in range(6):
        on = vertex_side == code
        u_axis, v_axis = SIDE_AXES[(code // 2, -1 if code % 2 else 1)]
        uv[on, 0], uv[on, 1] = points[on, u_axis], points[on, v_axis]
    chart = _charts(new_faces, len(vmap))
    return vmap, new_faces, _pack(uv, new_faces, chart, resolution=resolution, padding=padding)


def _charts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V',) chart of each vertex: the connected pieces of the faces."""
    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].reshape(-1)
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1]


def _pack(uv: np.ndarray, faces: np.ndarray, chart: np.ndarray, *, resolution: int, padding: int) -> np.ndarray:
    """Charts moved onto shelves (tallest first) and scaled, as one, into the unit square."""
    n = int(chart.max()) + 1
    low, high = _bounds(uv, chart, n)
    # a chart taller than wide turns a quarter (orientation kept): flat shelves waste less
    tall = (high - low)[:, 1] > (high - low)[:, 0]
    turn = tall[chart]
    uv = uv.copy()
    uv[turn] = np.stack([uv[turn, 1], -uv[turn, 0]], axis=1)
    low, high = _bounds(uv, chart, n)
    size = high - low
    # texels are not known before the scale: pack, then pack again with the gap the scale implies
    gap = 0.0
    for _ in range(3):
        offsets, side = _shelves(size + gap)
        scale = (1.0 - 1e-9) / side
        gap_new = (padding + 1) / (resolution * scale)  # +1: a texel's centre on each chart's edge
        if abs(gap_new - gap) <= 0.01 * gap_new:
            break
        gap = gap_new
    offsets, side = _shelves(size + gap)
    placed = (uv - low[chart] + offsets[chart] + gap / 2) / side
    return np.clip(placed, 0.0, 1.0)


def _bounds(uv: np.ndarray, chart: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) lower and upper corners of each chart's UV box."""
    low = np.full((n, 2), np.inf)
    high = np.full((n, 2), -np.inf)
    np.minimum.at(low, chart, uv)
    np.maximum.at(high, chart, uv)
    return low, high


def _shelves(size: np.ndarray) -> tuple[np.ndarray, float]:
    """Shelf packing of boxes ``size`` (N, 2): tallest first, left to right, rows of a width
    that makes the result about square. Returns (N, 2) lower-left corners and the side of
    the square that holds them all."""
    order = np.argsort(-size[:, 1], kind="stable")
    width = max(float(np.sqrt((size[:, 0] * size[:, 1]).sum()) * 1.1), float(size[:, 0].max()))
    offsets = np.zeros_like(size)
    x = y = row_height = 0.0
    for k in order:  # one step per chart (hundreds to a few thousand), not per face
        w, h = size[k]
        if x + w > width and x > 0:
            x, y, row_height = 0.0, y + row_height, 0.0
        offsets[k] = (x, y)
        x += w
        row_height = max(row_height, h)
    side = max(width, y + row_height, float((offsets + size).max()))
    return offsets, side
