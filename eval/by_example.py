"""By-example noise: Heitz and Neyret, "High-Performance By-Example Noise using a
Histogram-Preserving Blending Operator" (HPG 2018), the by-example baseline of ``make quality``.

The photo is made Gaussian once (``gaussianise``):

1. its colours are decorrelated: projected on the principal axes of their covariance, so
   that each channel can be treated on its own;
2. each decorrelated channel is mapped through its own CDF and the inverse normal CDF
   (by rank), so that it is standard normal; a lookup table of its quantiles undoes that.

The plane is then covered by equilateral triangles (a skewed simplex lattice,
``triangle_grid``). A point reads the Gaussian photo three times, once per vertex of its
triangle, each vertex shifted by its own random offset into the photo (a hash of the
vertex id and the seed), and blends the three with its barycentric weights w_i under the
variance-preserving operator

    G = sum_i w_i (G_i - mean) / sqrt(sum_i w_i^2) + mean,

which keeps a blend of Gaussians Gaussian with the same mean and variance, so that the
inverse lookup table gives back the photo's histogram per decorrelated channel (a plain
linear blend would shrink the variance where patches overlap and wash the colours out).

Everything is a function of the absolute plane position, so tiles drawn at different
origins are parts of one infinite plane. Offsets are whole pixels and keep each vertex's
patch (the hexagon of its six triangles) inside the photo: the photos are not tileable, so
a lookup that wrapped around the photo's edge would draw its seam into the patch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

#: the triangles' edge length in photo pixels at the working size (short side 256; the paper's
#: 2 sqrt 3 scale is 0.29 of the texture, 74 px). Median by-example error over the floor on the 9
#: validation photos (make tune-by-example, docs/eval/quality/by_example_tuning.md), edge 16 ..
#: 96: 7.23, 3.85, 2.68, 2.21, 2.16 (64), 2.14 (80), 2.52. Small triangles blend three patches
#: everywhere and wash structure out (bricks 24.9 at 16); past 80 the offsets have little room
#: left inside the photo and the plane repeats. 64 is within 1% of 80's median, has the lowest
#: geometric mean (3.07; 48: 3.18, 80: 3.10), is below 80 on 5 of 9 photos, and leaves each
#: vertex 126 x 142 offsets to 80's 94 x 114.
TRIANGLE_EDGE = 64.0
#: entries of the inverse histogram lookup table per channel
LUT_SIZE = 4096
SQRT3 = np.sqrt(3.0)


@dataclass(frozen=True)
class GaussianisedExample:
    """A photo prepared for ``by_example_tile`` (``gaussianise``).

    gaussian : (h, w, 3) float64, each decorrelated channel standard normal (by rank)
    colour_mean : (3,) float64, the photo's mean sRGB colour
    axes : (3, 3) float64, columns are the principal axes of the photo's colours
    quantiles : (3, LUT_SIZE) float64, decorrelated value of channel c at quantile
        (k + 0.5) / LUT_SIZE: the inverse of the Gaussianisation
    """

    gaussian: np.ndarray
    colour_mean: np.ndarray
    axes: np.ndarray
    quantiles: np.ndarray


def gaussianise(photo: np.ndarray, lut_size: int = LUT_SIZE) -> GaussianisedExample:
    """photo : (h, w, 3) float sRGB 0..1 -> its Gaussianised form and the way back."""
    photo = np.asarray(photo, np.float64)
    if photo.ndim != 3 or photo.shape[2] != 3:
        raise ValueError(f"photo must be (h, w, 3), got {photo.shape}")
    pixels = photo.reshape(-1, 3)
    colour_mean = pixels.mean(0)
    _, axes = np.linalg.eigh(np.cov(pixels - colour_mean, rowvar=False))
    decorrelated = (pixels - colour_mean) @ axes  # (n, 3)
    n = len(decorrelated)
    # rank -> the normal quantile of its mid-rank: exactly N(0, 1) whatever the photo's histogram
    # (ties get distinct ranks in a stable order, so a flat region stays a narrow band, not a spike)
    ranks = np.argsort(np.argsort(decorrelated, axis=0, kind="stable"), axis=0, kind="stable")
    gaussian = ndtri((ranks + 0.5) / n)
    levels = (np.arange(lut_size) + 0.5) / lut_size
    quantiles = np.quantile(decorrelated, levels, axis=0).T  # (3, lut_size)
    return GaussianisedExample(gaussian.reshape(photo.shape), colour_mean, axes, quantiles)


def degaussianise(example: GaussianisedExample, gaussian: np.ndarray) -> np.ndarray:
    """(..., 3) Gaussian values -> (..., 3) float64 sRGB: the lookup table, then the colour axes back."""
    lut_size = example.quantiles.shape[1]
    # the normal CDF gives the quantile; the table holds the value at quantile (k + 0.5) / lut_size
    position = ndtr(gaussian) * lut_size - 0.5
    index = np.arange(lut_size)
    decorrelated = np.stack([np.interp(position[..., c], index, example.quantiles[c]) for c in range(3)], -1)
    return decorrelated @ example.axes.T + example.colour_mean


def triangle_grid(x: np.ndarray, y: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """The triangle of an equilateral grid (edge length ``edge``) each point lies in.

    x, y : (...) float64 plane coordinates (pixels)
    Returns weights (..., 3) float64 (barycentric, summing to 1) and vertices (..., 3, 2)
    int64, the lattice ids of the triangle's corners, as the paper's TriangleGrid: the
    skew (x - y / sqrt 3, 2 y / sqrt 3) turns the triangles into half unit squares.
    """
    skewed = np.stack([x / edge - y / (edge * SQRT3), 2.0 * y / (edge * SQRT3)], -1)
    base = np.floor(skewed)
    fraction = skewed - base
    base = base.astype(np.int64)
    rest = 1.0 - fraction[..., 0] - fraction[..., 1]
    lower = (rest > 0.0)[..., None]  # the half square under its diagonal, or the upper one
    weights = np.where(lower, np.stack([rest, fraction[..., 1], fraction[..., 0]], -1),
                       np.stack([-rest, 1.0 - fraction[..., 1], 1.0 - fraction[..., 0]], -1))
    corners = np.where(lower[..., None], np.array([[0, 0], [0, 1], [1, 0]]), np.array([[1, 1], [1, 0], [0, 1]]))
    return weights, base[..., None, :] + corners


def vertex_positions(vertices: np.ndarray, edge: float) -> np.ndarray:
    """(..., 2) int64 lattice ids -> (..., 2) float64 plane positions (x, y) in pixels."""
    a, b = vertices[..., 0], vertices[..., 1]
    return np.stack([a + 0.5 * b, 0.5 * SQRT3 * b], -1) * edge


def hash_uniforms(vertices: np.ndarray, seed: int) -> np.ndarray:
    """(..., 2) int64 lattice ids -> (..., 2) float64 uniform in [0, 1), fixed per (vertex, seed).

    A splitmix64 finaliser over the ids and the seed (integer, so exact on every machine and
    at any distance from the origin, unlike the shader hash fract(sin(.) * 43758.5))."""
    ids = np.ascontiguousarray(vertices, np.int64).view(np.uint64)
    key = (ids[..., 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (ids[..., 1] * np.uint64(0xC2B2AE3D27D4EB4F))
    key ^= np.uint64(seed & 0xFFFFFFFFFFFFFFFF) * np.uint64(0x165667B19E3779F9)
    out = []
    for salt in (0x94D049BB133111EB, 0xBF58476D1CE4E5B9):  # two independent draws per vertex
        z = key + np.uint64(salt)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z ^= z >> np.uint64(31)
        out.append((z >> np.uint64(11)).astype(np.float64) / float(1 << 53))  # top 53 bits
    return np.stack(out, -1)


def by_example_tile(photo: np.ndarray | GaussianisedExample, height: int, width: int, origin: tuple[int, int],
                    seed: int, triangle_edge: float = TRIANGLE_EDGE) -> np.ndarray:
    """A tile of the by-example plane of a photo.

    photo : (h, w, 3) float sRGB 0..1 (the working size: one plane pixel is one photo pixel),
        or its ``gaussianise`` result (to prepare a photo once for many tiles)
    height, width : the tile's size in pixels
    origin : (x, y) int, the plane pixel at the tile's top-left corner (column, row); tiles
        at different origins are parts of one plane
    seed : int, picks the plane (every vertex's offset)
    triangle_edge : the triangles' edge length in pixels; a vertex's patch is a hexagon of
        that radius, so it must be under half the photo's short side to fit inside it
    Returns (height, width, 3) float32 sRGB, clipped to 0..1.
    """
    example = photo if isinstance(photo, GaussianisedExample) else gaussianise(photo)
    photo_height, photo_width = example.gaussian.shape[:2]
    rows = np.arange(height, dtype=np.int64) + int(origin[1])
    cols = np.arange(width, dtype=np.int64) + int(origin[0])
    row_grid, col_grid = np.meshgrid(rows, cols, indexing="ij")  # (height, width) plane pixel indices
    weights, vertices = triangle_grid(col_grid + 0.5, row_grid + 0.5, triangle_edge)  # at pixel centres

    # A vertex's patch reaches triangle_edge from it in x and edge * sqrt(3) / 2 in y (+1 for the
    # rounding): offsets drawn inside those margins keep every lookup inside the photo. A photo
    # too small for them gets its centre (the clip below then guards the last pixels).
    margin = np.array([np.ceil(triangle_edge) + 1, np.ceil(0.5 * SQRT3 * triangle_edge) + 1])
    size = np.array([photo_width, photo_height])
    low = np.minimum(margin, size // 2)
    high = np.maximum(size - 1 - margin, low)
    offset = low + np.floor(hash_uniforms(vertices, seed) * (high - low + 1))  # (height, width, 3, 2) photo pixel
    # whole-pixel shift from the plane to the photo per vertex: lookups copy photo pixels exactly
    shift = (offset - np.round(vertex_positions(vertices, triangle_edge))).astype(np.int64)
    photo_col = np.clip(col_grid[..., None] + shift[..., 0], 0, photo_width - 1)
    photo_row = np.clip(row_grid[..., None] + shift[..., 1], 0, photo_height - 1)
    lookups = example.gaussian[photo_row, photo_col]  # (height, width, 3 vertices, 3 channels)

    # variance-preserving blend; the Gaussianised channels have mean 0 (by construction)
    blended = np.einsum("hwv,hwvc->hwc", weights, lookups) / np.sqrt((weights**2).sum(-1, keepdims=True))
    return np.clip(degaussianise(example, blended), 0.0, 1.0).astype(np.float32)
