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


def mean_cell_share(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> float:
    """How much of the photo's spread its mean repeat cell explains (0..1): the spread of
    each pixel's cell colour about the photo's mean, over the photo's own spread."""
    cell, counts = fold_on_lattice(image, lattice_px, lattice_cell_sizes(lattice_px))
    pixels = image.reshape(-1, 3)
    explained = (counts[:, None] * np.square(cell - pixels.mean(axis=0))).sum() / counts.sum()
    return float(np.sqrt(explained / max(pixels.var(axis=0).sum(), 1e-12)))
