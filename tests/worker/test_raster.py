"""worker/raster.py pieces of a bake that must be exact: the sRGB table, the gutter."""
import numpy as np
from scipy import ndimage

from worker.colour import linear_to_srgb8
from worker.raster import _srgb8_table, encode_srgb8, face_affine, fill_gutter, gutter_sources, rasterise, texel_points


def test_srgb_table_is_bit_identical_to_the_curve():
    rng = np.random.default_rng(0)
    thresholds = []
    _, step = _srgb8_table()
    edges = step[step < 2.0]
    for k in range(-3, 4):                                  # every step and its float32 neighbours
        x = edges.copy()
        for _ in range(abs(k)):
            x = np.nextafter(x, np.float32(np.sign(k) * 2.0), dtype=np.float32)
        thresholds.append(x)
    values = np.concatenate([
        rng.random(2_000_000, dtype=np.float32), rng.random(200_000, dtype=np.float32) * 0.01,
        np.linspace(0, 1, 1_000_001, dtype=np.float32), *thresholds,
        np.array([0.0, 1.0, -0.0, -1e-30, 1e-45, 1.0000001, 7.5, -3.0, np.inf, -np.inf], np.float32)])
    with np.errstate(invalid="ignore"):
        assert np.array_equal(encode_srgb8(values), linear_to_srgb8(values))
    assert len(edges) == 255 and (encode_srgb8(edges) - encode_srgb8(np.nextafter(edges, np.float32(0))) == 1).all()
    assert encode_srgb8(np.array([np.nan], np.float32))[0] == 0
    shaped = rng.random((7, 5, 3), dtype=np.float32)
    assert encode_srgb8(shaped).shape == (7, 5, 3) and encode_srgb8(shaped).dtype == np.uint8


def test_gutter_copies_a_nearest_covered_texel_within_the_padding():
    """Against scipy's exact distance transform, on masks sparse and dense, charts at the
    borders, and paddings up to beyond the mask's size."""
    rng = np.random.default_rng(1)
    masks = [ndimage.binary_opening(rng.random((96, 80)) > density, iterations=1) for density in (0.5, 0.7, 0.8)]
    masks.append(np.zeros((40, 70), bool))
    masks[-1][0, 69] = masks[-1][39, 0] = masks[-1][20, 30:33] = True    # single texels at corners
    for covered in masks:
        covered[:5] = False
        assert covered.any()
        width = covered.shape[1]
        dist = ndimage.distance_transform_edt(~covered)
        for padding in (0, 1, 3, 8, 20, 100):
            dst, src = gutter_sources(covered, padding)
            want = np.flatnonzero((dist <= padding) & ~covered)
            assert np.array_equal(np.sort(dst), want)                # exactly the texels within the padding
            assert covered.ravel()[src].all()
            r, c = np.divmod(dst, width)
            sr, sc = np.divmod(src, width)
            assert np.allclose(np.hypot(r - sr, c - sc), dist.ravel()[dst])   # a nearest one, Euclidean
    covered = masks[0]
    image = rng.random((96, 80, 3)).astype(np.float32)
    filled = fill_gutter(image, covered, 2)
    assert np.array_equal(filled[covered], image[covered])
    assert gutter_sources(np.zeros((8, 8), bool), 4)[0].size == 0
    assert gutter_sources(np.ones((8, 8), bool), 4)[0].size == 0


def test_texel_points_are_the_barycentric_blend_of_the_corners():
    """A bake's surface points come from each texel's face alone (an affine map per face);
    they must be the points the rasteriser's barycentric coordinates give, on every texel,
    and rasterise without barycentrics must cover the same (texel, face) pairs."""
    rng = np.random.default_rng(4)
    R = 96
    tri_uv = rng.random((300, 3, 2)) * 0.3 + rng.random((300, 1, 2)) * 0.7   # small, overlapping, any winding
    tri_uv[:5] = tri_uv[:5, :1]                                               # UV-degenerate: cover nothing
    tri_xyz = rng.normal(size=(300, 3, 3)) * 10 + 100
    texel, face, bary = rasterise(tri_uv, R)
    texel32, face32 = rasterise(tri_uv, R, barycentric=False)
    assert texel32.dtype == face32.dtype == np.int32
    assert np.array_equal(texel32, texel) and np.array_equal(face32, face) and len(texel) > 1000
    want = np.einsum("kc,kcd->kd", bary, tri_xyz[face])
    got = texel_points(texel32, face32, face_affine(tri_uv, tri_xyz, R), R)
    assert got.shape == want.shape and np.abs(got - want).max() < 1e-9
