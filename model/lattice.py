"""A photo on its repeat lattice (bricks, tile grids, perforated metal): numpy geometry
that photo analysis (model/structure/) and training (model/train.py) both read.
Lattices are two basis vectors (ax, ay, bx, by) in pixels of the exemplar at its working
resolution, x along columns, y along rows, unless a name says world units; images are
(H, W, 3) float arrays.
"""

from __future__ import annotations

import math

import numpy as np

from model.config import ModelConfig


def lattice_pixels(lattice: tuple[float, float, float, float] | None) -> tuple[float, float, float, float] | None:
    """A lattice in world units (``--lattice``) in the exemplar's working-resolution pixels,
    where the photo is measured (model.fit divides the detected one by the same factor)."""
    ppu = ModelConfig().pixels_per_unit
    return tuple(v * ppu for v in lattice) if lattice else None


def lattice_contrast(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> float:
    """How much a photo's repeats differ: the mean squared sRGB distance between the photo
    and itself shifted by each lattice vector (pixels, x along columns, y along rows), the
    mean over the two vectors. Each shift is the best whole-pixel one within a pixel of the
    vector, so a grid drawn a fraction of a pixel off does not count as difference."""
    height, width = image.shape[:2]
    per_vector = []
    for vx, vy in (lattice_px[:2], lattice_px[2:]):
        best = math.inf
        for dx in range(math.floor(vx) - 1, math.ceil(vx) + 2):
            for dy in range(math.floor(vy) - 1, math.ceil(vy) + 2):
                if abs(dx) >= width // 2 or abs(dy) >= height // 2 or dx == dy == 0:
                    continue
                a = image[max(0, dy):height + min(0, dy), max(0, dx):width + min(0, dx)]
                b = image[max(0, -dy):height + min(0, -dy), max(0, -dx):width + min(0, -dx)]
                best = min(best, float(np.square(a - b).sum(axis=2).mean()))
        per_vector.append(best)
    return float(np.mean(per_vector))


def fold_on_lattice(image: np.ndarray, lattice_px: tuple[float, float, float, float],
                    sizes: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel of the photo binned by its phase on the lattice, ``sizes`` bins along the
    two lattice vectors (pixels, x along columns, y along rows, as ``lattice_phases`` reads
    world points): the mean colour float64 [n_a * n_b, 3] and the pixel count [n_a * n_b]
    of each bin (row i_a * n_b + i_b)."""
    height, width = image.shape[:2]
    rows, cols = np.mgrid[0:height, 0:width]
    points = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1)
    u = points @ np.linalg.inv(np.array(lattice_px, np.float64).reshape(2, 2).T).T
    bins = np.floor((u - np.floor(u)) * sizes).astype(int) % sizes
    index = bins[:, 0] * sizes[1] + bins[:, 1]
    n = int(np.prod(sizes))
    counts = np.bincount(index, minlength=n)
    colours = image.reshape(-1, 3)
    sums = np.stack([np.bincount(index, colours[:, c], minlength=n) for c in range(3)], axis=1)
    return sums / np.maximum(counts, 1)[:, None], counts


def lattice_cell_sizes(lattice_px: tuple[float, float, float, float]) -> tuple[int, int]:
    """Bins of a mean repeat cell: about one per pixel along each lattice vector."""
    return tuple(int(max(2, round(float(np.hypot(*v))))) for v in (lattice_px[:2], lattice_px[2:]))


def lattice_mean_cell(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> np.ndarray:
    """The photo's mean repeat cell: float32 [n_a, n_b, 3] (``fold_on_lattice`` at
    ``lattice_cell_sizes``), standardised: zero mean, unit spread over the cell."""
    sizes = lattice_cell_sizes(lattice_px)
    cell, counts = fold_on_lattice(image, lattice_px, sizes)
    cell[counts == 0] = image.reshape(-1, 3).mean(axis=0)  # (a bin no pixel fell in: a lattice longer than the photo)
    cell = (cell - cell.mean(axis=0)) / (cell.std() + 1e-6)
    return cell.reshape(*sizes, 3).astype(np.float32)


# Cell shades need this many whole cells, each with its four neighbours whole, to be measured
# (the savanna dunes' 10 gave a spread their fit drew as blotches: 2.91 -> 3.15x the floor).
SHADE_MIN_CELLS = 24
# ... and a shade variance at least this many of its sampling errors above zero: on 0ad's
# validation photos, floor tiles, planks and farm rows 6.5-6.7, bricks 1.95, where 70-s CPU fits
# gained from shades; farmland_a 1.1, its road tiles 0.1 and temp_farmland -1.3 are noise.
SHADE_MIN_ERRORS = 1.5
# A cell's mean less its four neighbours' has 1 + 4 / 16 = 1.25 times the variance of
# independent per-cell shades; on cells shifted half a period each way, each the mean of four
# shades, 0.09375 times (the sum of squares of that residual kernel convolved with a 2 x 2 box).
_SHADE_ALIGNED, _SHADE_SHIFTED = 1.25, 0.09375


def _cell_residuals(image: np.ndarray, lattice_px: tuple[float, float, float, float], shift: float) -> np.ndarray:
    """Mean colour of each whole lattice cell (cells shifted by ``shift`` of a period along both
    vectors) less the mean of its four neighbours, for cells whose neighbours are whole too:
    float64 [n, 3]. Whole: at least 80% of the fullest cell's pixels."""
    height, width = image.shape[:2]
    rows, cols = np.mgrid[0:height, 0:width]
    points = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1)
    cell = np.floor(points @ np.linalg.inv(np.array(lattice_px, np.float64).reshape(2, 2).T).T + shift)
    cell = (cell - cell.min(axis=0)).astype(np.int64)
    shape = tuple(cell.max(axis=0) + 1)
    index = cell[:, 0] * shape[1] + cell[:, 1]
    n = int(np.prod(shape))
    counts = np.bincount(index, minlength=n)
    colours = image.reshape(-1, 3).astype(np.float64)
    means = np.stack([np.bincount(index, colours[:, c], minlength=n) for c in range(3)], axis=1)
    means = (means / np.maximum(counts, 1)[:, None]).reshape(*shape, 3)
    whole = (counts >= 0.8 * counts.max()).reshape(shape)
    centre = (slice(1, -1), slice(1, -1))
    around = [(slice(2, None), slice(1, -1)), (slice(None, -2), slice(1, -1)),
              (slice(1, -1), slice(2, None)), (slice(1, -1), slice(None, -2))]
    residual = means[centre] - sum(means[a] for a in around) / 4.0
    ok = whole[centre] & np.logical_and.reduce([whole[a] for a in around])
    return residual[ok]


def cell_shade_covariance(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> np.ndarray | None:
    """How much each repeat cell's own shade varies (bricks, tiles, planks of different
    shades): float64 [3, 3], the covariance of per-cell colour offsets in units of the photo's
    mean channel variance, or None where fewer than ``SHADE_MIN_CELLS`` cells can be compared
    or the shades' variance is not ``SHADE_MIN_ERRORS`` sampling errors above zero.

    A cell's mean less its neighbours' also varies with the texture inside the cells (noise
    averaged over a cell is not constant); that part is the same on cells shifted half a period,
    where every cell straddles four shades, so the difference of the two, over the difference
    of their responses to per-cell shades, leaves the shades alone (clipped to be positive
    semi-definite). Floor tiles: 0.38 -> 0.33 of the photo's spread; farmland rows 0.10 -> 0.07."""
    aligned, shifted = _cell_residuals(image, lattice_px, 0.0), _cell_residuals(image, lattice_px, 0.5)
    if min(len(aligned), len(shifted)) < SHADE_MIN_CELLS:
        return None
    c_aligned, c_shifted = np.cov(aligned.T), np.cov(shifted.T)
    # a variance estimated from n samples has a sampling error of about sqrt(2 / n) of itself
    v_aligned, v_shifted = float(np.trace(c_aligned)), float(np.trace(c_shifted))
    error = math.sqrt(2.0 * v_aligned**2 / len(aligned) + 2.0 * v_shifted**2 / len(shifted))
    if v_aligned - v_shifted < SHADE_MIN_ERRORS * error:
        return None
    values, vectors = np.linalg.eigh((c_aligned - c_shifted) / (_SHADE_ALIGNED - _SHADE_SHIFTED))
    covariance = (vectors * np.clip(values, 0.0, None)) @ vectors.T
    return covariance / max(float(image.reshape(-1, 3).var(axis=0).mean()), 1e-12)


def mean_cell_share(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> float:
    """How much of the photo's spread its mean repeat cell explains (0..1): the spread of
    each pixel's cell colour about the photo's mean, over the photo's own spread."""
    cell, counts = fold_on_lattice(image, lattice_px, lattice_cell_sizes(lattice_px))
    pixels = image.reshape(-1, 3)
    explained = (counts[:, None] * np.square(cell - pixels.mean(axis=0))).sum() / counts.sum()
    return float(np.sqrt(explained / max(pixels.var(axis=0).sum(), 1e-12)))
