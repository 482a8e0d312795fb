"""worker.raster.rasterise (scanline spans) against the bounding-box rasteriser it replaced.

The box rasteriser below is the previous implementation, kept as the reference: it tests
every texel centre of each triangle's bounding box. The scanline one must return the same
(texel, face, barycentric) triples, bit for bit and in the same order (so ``last_hits``
picks the same pair on shared edges), on meshes built to stress the span bounds: texel
centres exactly on edges and corners, slivers near the degeneracy threshold, nearly
horizontal and vertical edges, triangles far larger than the atlas or outside it.
"""
import numpy as np
import pytest

from worker.raster import EDGE_EPS, last_hits, rasterise, uv_to_texel


def box_rasterise(tri_uv, resolution, batch_candidates=1 << 16):
    """The bounding-box rasteriser (worker/raster.py before the scanline spans), verbatim."""
    R = int(resolution)
    p = uv_to_texel(np.asarray(tri_uv, dtype=np.float64), R)
    lo = np.clip(np.ceil(p.min(axis=1) - 0.5), 0, R - 1).astype(np.int64)
    hi = np.clip(np.floor(p.max(axis=1) - 0.5), -1, R - 1).astype(np.int64)
    dims = hi - lo + 1
    keep = (dims > 0).all(axis=1)
    (e1, e2), p0 = (p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep &= np.abs(det) > 1e-12
    faces = np.flatnonzero(keep)
    faces = faces[np.argsort(dims[faces].prod(axis=1), kind="stable")]
    batches = []
    start = 0
    while start < len(faces):
        count = max(1, batch_candidates // int(dims[faces[start]].prod()))
        while True:
            stop = min(start + count, len(faces))
            w, h = dims[faces[start:stop]].max(axis=0)
            if count == 1 or (stop - start) * w * h <= batch_candidates:
                break
            count //= 2
        batches.append((faces[start:stop], int(w), int(h)))
        start = stop
    if not batches:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))

    def cover(job):
        batch, w, h = job
        cols = lo[batch, 0, None] + np.arange(w)[None, :]
        rows = lo[batch, 1, None] + np.arange(h)[None, :]
        dx = np.where(cols <= hi[batch, 0, None], cols + 0.5 - p0[batch, 0, None], np.nan)[:, None, :]
        dy = np.where(rows <= hi[batch, 1, None], rows + 0.5 - p0[batch, 1, None], np.nan)[:, :, None]
        inv = 1.0 / det[batch]
        b1 = dx * (e2[batch, 1] * inv)[:, None, None] - dy * (e2[batch, 0] * inv)[:, None, None]
        b2 = dy * (e1[batch, 0] * inv)[:, None, None] - dx * (e1[batch, 1] * inv)[:, None, None]
        inside = b1 >= -EDGE_EPS
        inside &= b2 >= -EDGE_EPS
        inside &= (b1 + b2) <= 1.0 + EDGE_EPS
        bi, yi, xi = np.nonzero(inside)
        c1, c2 = b1[bi, yi, xi], b2[bi, yi, xi]
        return rows[bi, yi] * R + cols[bi, xi], batch[bi], np.stack([1.0 - c1 - c2, c1, c2], axis=1)

    with np.errstate(invalid="ignore"):
        texels, owners, barys = zip(*map(cover, batches))
    return np.concatenate(texels), np.concatenate(owners), np.concatenate(barys)


def centre_uv(cols, rows, R):
    """UVs of texel centres (the points the rasteriser tests)."""
    return np.stack([(np.asarray(cols) + 0.5) / R, 1.0 - (np.asarray(rows) + 0.5) / R], axis=-1)


def stress_meshes(rng, R):
    """(name, tri_uv (F, 3, 2)) meshes that put texel centres on, or within rounding of, edges."""
    n = 400
    yield "random", rng.random((n, 3, 2))
    yield "small", rng.random((n, 1, 2)) + rng.normal(0, 2.0 / R, (n, 3, 2))
    yield "subtexel", rng.random((n, 1, 2)) + rng.normal(0, 0.3 / R, (n, 3, 2))
    # Corners exactly on texel centres: horizontal, vertical and diagonal edges through
    # rows of centres, shared edges of a regular grid split both ways.
    yield "centre_corners", centre_uv(rng.integers(-2, R + 2, (n, 3)), rng.integers(-2, R + 2, (n, 3)), R)
    g = np.arange(0, R + 1, max(1, R // 8))
    cc, rr = np.meshgrid(g[:-1], g[:-1])
    a = centre_uv(cc, rr, R).reshape(-1, 2)
    b = centre_uv(cc + (g[1] - g[0]), rr, R).reshape(-1, 2)
    c = centre_uv(cc, rr + (g[1] - g[0]), R).reshape(-1, 2)
    d = centre_uv(cc + (g[1] - g[0]), rr + (g[1] - g[0]), R).reshape(-1, 2)
    yield "grid", np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1),
                                  np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    # Edges through texel centres at odd slopes (1:2, 2:3, ...) and fans around one centre.
    start = rng.integers(0, R, (n, 2))
    step = rng.integers(-5, 6, (n, 2, 2))
    reach = rng.integers(1, max(2, R // 6), (n, 1, 1))
    ends = start[:, None, :] + step * reach
    yield "lattice_edges", centre_uv(np.concatenate([start[:, None, 0], ends[..., 0]], 1),
                                     np.concatenate([start[:, None, 1], ends[..., 1]], 1), R)
    # Slivers: third corner off the segment by 1e-16..1e-3 texels, some right at the
    # |det| > 1e-12 threshold, some with both ends on texel centres.
    p = centre_uv(rng.integers(0, R, (n, 2)), rng.integers(0, R, (n, 2)), R)
    t = rng.random((n, 1))
    mid = p[:, 0] * (1 - t) + p[:, 1] * t
    normal = (p[:, 1] - p[:, 0])[:, ::-1] * [1, -1]
    off = 10.0 ** rng.uniform(-16, -3, (n, 1)) / R * rng.choice([-1, 1], (n, 1))
    yield "slivers", np.stack([p[:, 0], p[:, 1], mid + normal * off], 1)
    length = np.linalg.norm((p[:, 1] - p[:, 0]) * R, axis=1)[:, None]
    threshold = 1e-12 * 10.0 ** rng.uniform(-0.3, 0.3, (n, 1)) / np.maximum(length, 1e-9) ** 2 / R
    yield "threshold_slivers", np.stack([p[:, 0], p[:, 1], mid + normal * threshold], 1)
    # Nearly horizontal / vertical edges: corners a few ulps to 1e-6 texels apart in v or u.
    q = rng.random((n, 3, 2))
    k = rng.integers(0, 2, n)
    q[np.arange(n), 1, k] = q[np.arange(n), 0, k] + 10.0 ** rng.uniform(-17, -6, n) * rng.choice([-1, 1], n)
    yield "axis_edges", q
    # Flat slivers along a row (or column) of centres: corners 1e-14..1e-5 texels off it,
    # where the test is worst conditioned (its rounding exceeds 1e-9 texels).
    q = centre_uv(rng.integers(0, R, (n, 3)), np.repeat(rng.integers(0, R, (n, 1)), 3, axis=1), R)
    q[..., 1] += 10.0 ** rng.uniform(-14, -5, (n, 3)) / R * rng.choice([-1, 1], (n, 3))
    yield "flat_rows", q
    yield "flat_columns", q[..., ::-1]
    q = centre_uv(rng.integers(0, R, (n, 3)), rng.integers(0, R, (n, 3)), R)
    q[:, 1, 1] = np.nextafter(q[:, 0, 1], q[:, 0, 1] + rng.choice([-1, 1], n))  # one ulp off a row of centres
    yield "ulp_off_row", q
    # The same for the edge opposite corner 0 (corners 1 and 2 on a row, 1e-12..1e-6 texels
    # apart in v, corner 0 far off it): b1 and b2 are O(1) there while b1 + b2 changes by
    # only ~1e-12 per texel along the row, so rounding moves where b1 + b2 <= 1 + eps
    # stops holding by many ulps of a texel (the case the span's rounding margin is for).
    q = centre_uv(rng.integers(0, R, (n, 3)), np.repeat(rng.integers(0, R, (n, 1)), 3, axis=1), R)
    q[:, 0, 1] = rng.random(n)
    q[:, 2, 1] += 10.0 ** rng.uniform(-12, -6, n) / R * rng.choice([-1, 1], n)
    yield "flat_far_edge", q
    yield "flat_far_edge_columns", q[..., ::-1]
    # Large: across the whole atlas and beyond it, and entirely outside it.
    yield "large", rng.uniform(-1.5, 2.5, (40, 3, 2))
    yield "outside", rng.uniform(1.01, 3.0, (n, 3, 2)) * rng.choice([-1, 1], (n, 1, 2))
    # Degenerate: repeated corners, collinear corners, zero-area.
    z = rng.random((n, 3, 2))
    z[: n // 3, 2] = z[: n // 3, 0]
    z[n // 3:, 2] = z[n // 3:, 0] + 0.37 * (z[n // 3:, 1] - z[n // 3:, 0])
    yield "degenerate", z


def assert_same(tri_uv, R):
    got, want = rasterise(tri_uv, R), box_rasterise(tri_uv, R)
    for name, g, w in zip(("texel", "face", "bary"), got, want):
        assert g.dtype == w.dtype and g.shape == w.shape, (name, g.shape, w.shape)
        # Bit-identical and in the same order (np.array_equal would let -0.0 == 0.0 pass).
        assert g.tobytes() == w.tobytes(), name
    return got


@pytest.mark.parametrize("R", [16, 37, 64, 256])
def test_scanline_rasteriser_matches_the_box_rasteriser(R):
    rng = np.random.default_rng(R)
    total = 0
    for name, tri_uv in stress_meshes(rng, R):
        texel, face, _ = assert_same(tri_uv, R)
        total += len(texel)
        uniq, pick = last_hits(texel, R)
        assert len(uniq) == 0 or (np.diff(uniq) > 0).all()
    assert total > 0
    # All of them at once (chunks then span several kinds of triangle).
    assert_same(np.concatenate([m for _, m in stress_meshes(np.random.default_rng(R + 1), R)]), R)


def test_scanline_rasteriser_edge_cases():
    empty = np.zeros((0, 3, 2))
    for R in (1, 2, 16):
        assert_same(empty, R)
        assert_same(np.array([[[0, 0], [1, 0], [0, 1]], [[1, 1], [0, 1], [1, 0]]], float), R)   # full atlas
        assert_same(np.array([[[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]]]), R)                         # a point
    texel, face, bary = assert_same(np.array([[[0, 0], [1, 0], [0, 1]], [[1, 1], [0, 1], [1, 0]]], float), 16)
    assert len(np.unique(texel)) == 256                                  # two halves cover every texel
    assert np.allclose(bary.sum(axis=1), 1.0)


def test_scanline_rasteriser_chunk_boundaries(monkeypatch):
    """Tiny chunks: spans and candidate runs cut mid-triangle and mid-row give the same output."""
    from worker import raster

    rng = np.random.default_rng(7)
    tri_uv = np.concatenate([m for _, m in stress_meshes(rng, 64)])
    want = box_rasterise(tri_uv, 64)
    for pairs, candidates in ((1, 1), (3, 7), (64, 50), (1 << 15, 1 << 17)):
        monkeypatch.setattr(raster, "CHUNK_PAIRS", pairs)
        monkeypatch.setattr(raster, "CHUNK_CANDIDATES", candidates)
        got = rasterise(tri_uv, 64)
        assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want))
