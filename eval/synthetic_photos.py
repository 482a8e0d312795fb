"""Synthetic photos with known structure, for the structure detectors and the fit's tests:
(H, W, 3) float arrays in [0, 1], grey, x right, y down."""
from __future__ import annotations

import numpy as np
from scipy import ndimage


def streaks(size: int = 256, angle_degrees: float = 0.0) -> np.ndarray:
    """Wood-like streaks: bands of many widths whose brightness changes across image x
    (so they run up-down at angle 0), turned by ``angle_degrees``, with a little noise."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    across = x * np.cos(np.radians(angle_degrees)) + y * np.sin(np.radians(angle_degrees))
    value = sum(np.sin(across * f + rng.uniform(0, 6.3)) / f ** 0.5 for f in rng.uniform(0.03, 0.8, 12))
    value = 0.5 + 0.1 * value + 0.01 * rng.standard_normal((size, size))
    return np.repeat(np.clip(value, 0, 1)[..., None], 3, axis=2)


def fibres(along: float, across: float, size: int = 256, seed: int = 0) -> np.ndarray:
    """Noise blurred ``along`` px up-down and ``across`` px left-right (Gaussian sigmas): a
    grain along y whose strength the ratio sets (40 / 4: long fibres, 12 / 4: a weak grain)."""
    noise = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal((size, size)), (along, across),
                                    mode="wrap")
    value = np.clip(0.5 + 0.15 * noise / noise.std(), 0, 1)
    return np.repeat(value[..., None], 3, axis=2)


def running_bond(size: int = 256, brick: int = 32, course: int = 11) -> np.ndarray:
    """Bricks brick x course px in a running bond (every course shifted by half a brick),
    1-px mortar, each brick its own shade: a regular photo with a known lattice."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:size, 0:size]
    row = y // course
    shifted = x + (row % 2) * (brick // 2)
    shade = rng.uniform(0.35, 0.55, (size // course + 2, size // brick + 3))[row, shifted // brick]
    mortar = (y % course == 0) | (shifted % brick == 0)
    image = np.where(mortar, 0.85, shade) + 0.02 * rng.standard_normal((size, size))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def corrugation(period: float = 8.8, size: int = 256, wander_px: float = 1.5, patches: float = 0.12,
                 noise: float = 0.05, seed: int = 7) -> np.ndarray:
    """Corrugated board: sharp ridges every ``period`` px down the photo, running along x
    and wandering by up to ``wander_px`` (as pressed board does), over large tone patches
    (like the validation cardboard's) and fine noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    wander = ndimage.gaussian_filter(rng.standard_normal((size, size)), 12)
    ridges = (0.5 + 0.5 * np.cos(2 * np.pi * (y + wander_px * wander / np.abs(wander).max()) / period)) ** 8
    tone = ndimage.gaussian_filter(rng.standard_normal((size, size)), 24)
    image = 0.55 + 0.12 * ridges + patches * tone / np.abs(tone).max() + noise * rng.standard_normal((size, size))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def boards(width: float = 25.6, size: int = 256, seed: int = 5, uneven: float = 0.0) -> np.ndarray:
    """Boards side by side, ``width`` px across, running up-down: each its own wavy grain
    and tone, dark joints between them (a plank floor seen from above). ``uneven``: each
    board's width drawn from ``width`` times 1 +- uneven (0ad's bridge_wood_a)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    board = np.floor((x + 0.5) / width).astype(int)
    if uneven:
        widths = width * rng.uniform(1 - uneven, 1 + uneven, int(size / width / (1 - uneven)) + 2)
        edges = np.cumsum(widths) - 0.5
        board = np.searchsorted(edges, x)
        gap = np.minimum(np.abs(x - edges[np.maximum(board - 1, 0)]), np.abs(edges[board] - x))
    wander = 200 * ndimage.gaussian_filter(rng.standard_normal((size, size)), 16)
    phase = rng.uniform(0, 2 * np.pi, (board.max() + 1, 6))[board]
    grain = sum(np.sin((x + wander) * f + phase[..., i]) / f ** 0.5 for i, f in enumerate((0.25, 0.4, 0.6, 0.9, 1.3, 1.9)))
    tone = rng.uniform(-0.06, 0.06, board.max() + 1)[board]
    joint = (gap < 1.0) if uneven else np.abs(((x + 0.5) / width + 0.5) % 1 - 0.5) * width < 1.0
    image = 0.55 + 0.03 * grain + tone - 0.3 * joint + 0.01 * rng.standard_normal((size, size))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def ripples(period: float = 48.0, size: int = 256, seed: int = 0, lean: float = 0.0) -> np.ndarray:
    """Wind ripples in sand, ``period`` px apart, running left-right (``lean``: turned that many
    degrees from +x towards +y, as ``model.structure.grain_tilt`` measures) and waving (crests
    bend by a fifth of a period along a photo's width, and wander a little each): a light
    windward slope rising to a sharp crest, a shadowed lee, fine grains over all (0ad's
    savanna_sand_dunes_100 at the working size: 43.6 px apart, leaning -11 degrees)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    wander = ndimage.gaussian_filter(rng.standard_normal((size, size)), 16, mode="wrap")
    turn = np.radians(lean)
    across = y * np.cos(turn) - x * np.sin(turn) + 0.2 * period * np.sin(2 * np.pi * x / size + rng.uniform(0, 2 * np.pi)) \
        + 0.1 * period * wander / wander.std()
    slope = ((across / period) % 1.0) ** 2  # light windward slope rising to the crest, then the lee's drop
    image = 0.45 + 0.2 * slope + 0.015 * rng.standard_normal((size, size))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def banded_motifs(across: float = 60.0, down: float = 110.0, size: int = 256, weave: float = 0.08,
                  seed: int = 3) -> np.ndarray:
    """A woven rug: two bands a repeat of ``down`` px (dark with diamonds, light with bars,
    dark lines between), its motifs every ``across`` px along them, and a weave of
    horizontal streaks (``weave``: their std) that reads as grain along x. Its lattice,
    (across, 0) and (0, down), reaches past a third of a 256-px photo."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    u, v = (x % across) / across - 0.5, (y % down) / down
    image = np.where(v < 0.5, 0.35, 0.65)
    image = np.where((v < 0.02) | (np.abs(v - 0.5) < 0.02), 0.1, image)
    diamond = np.abs(u) / 0.3 + np.abs(v - 0.25) * down / across / 0.25 < 1.0
    bar = (np.abs(u) < 0.4) & (np.abs(v - 0.75) < 0.05)
    image = np.where(diamond | bar, 0.9, image) + 0.03 * ndimage.gaussian_filter(rng.standard_normal((size, size)), 1)
    streaks = ndimage.gaussian_filter(rng.standard_normal((size, size)), (0.7, 12.0))
    image = image + weave * streaks / streaks.std()
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def hexagonal_tiles(radius: float, turn_degrees: float = 0.0, size: int = 256, seed: int = 0
                    ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Hexagonal tiles (centre to corner ``radius`` px) with 2.5-px soft grout over a mottled
    glaze, their lattice turned by ``turn_degrees``: (photo, lattice basis in px)."""
    rng = np.random.default_rng(seed)
    turn = np.radians(turn_degrees)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    basis = rotation @ np.array([[np.sqrt(3) * radius, np.sqrt(3) * radius / 2], [0.0, 1.5 * radius]])  # columns
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    points = np.stack([x.ravel(), y.ravel()])
    cell = np.floor(np.linalg.solve(basis, points))
    nearest, second = np.full(points.shape[1], np.inf), np.full(points.shape[1], np.inf)
    for i in (-1, 0, 1, 2):  # the centres around each point: the two nearest make the grout
        for j in (-1, 0, 1, 2):
            distance = np.hypot(*(points - basis @ (cell + np.array([[i], [j]]))))
            second = np.where(distance < nearest, nearest, np.minimum(second, distance))
            nearest = np.minimum(nearest, distance)
    edge = (second - nearest).reshape(size, size)
    glaze = ndimage.gaussian_filter(rng.standard_normal((size, size)), 2) / 0.14
    image = 0.7 + 0.05 * glaze - 0.35 * np.clip(2.5 - edge, 0, 1)
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2), tuple(float(v) for v in basis.T.ravel())


def parquet(block: int = 32, slats: int = 4, size: int = 256, turn_degrees: float = 0.0, joint: float = 0.12,
            noise: float = 0.02, seed: int = 0) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Parquet seen from above: square blocks of ``block`` px in a checkerboard of slat
    directions (slats up-down, then left-right), ``slats`` slats a block, each slat its own
    tone with fine streaks along it, dark joints ``joint`` deep between slats and blocks,
    the floor turned by ``turn_degrees``, in a light wood colour: (photo, lattice basis in
    px). No two blocks are alike: only the pattern of directions repeats, on (block, block)
    and (block, -block) turned."""
    rng = np.random.default_rng(seed)
    turn = np.radians(turn_degrees)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) - size / 2
    u, v = x * np.cos(turn) + y * np.sin(turn), -x * np.sin(turn) + y * np.cos(turn)  # along the floor's rows
    margin = size // block + 2  # block indices of a turned floor start below 0
    i, j = (np.floor(w / block).astype(int) + margin for w in (u, v))
    up_down = (i + j) % 2 == 0
    across = np.where(up_down, u, v) % block  # across the slats, within the block
    slat_width = block / slats
    tone = rng.uniform(-0.08, 0.08, (2 * margin, 2 * margin, slats))[i, j, (across // slat_width).astype(int)]
    streak = ndimage.gaussian_filter1d(rng.standard_normal((2 * margin, 2 * margin, 2 * block)), 0.7, axis=2)
    streak = streak[i, j, (2 * across).astype(int)]
    slat_joint = np.minimum(across % slat_width, slat_width - across % slat_width) < 0.6
    block_joint = np.minimum(np.minimum(u % block, block - u % block), np.minimum(v % block, block - v % block)) < 0.8
    image = 0.5 + tone + 0.04 * streak - 0.6 * joint * slat_joint - joint * block_joint
    image = image + noise * rng.standard_normal((size, size))
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    lattice = (rotation @ np.array([[block, -block], [block, block]], np.float64)).T.ravel()  # rows: the vectors
    wood = np.clip(image[..., None] * np.array([1.1, 0.85, 0.6]), 0, 1)
    return wood, tuple(float(c) for c in lattice)


def crop_rows(period: float = 10.16, size: int = 256, rows: float = 0.02, lean: float = 0.3, seed: int = 3
              ) -> np.ndarray:
    """Rows of crops seen from above (0ad's farmland_a): a faint brightness wave of ``period``
    px across x under leaves, noise streaked 4 px up-down and sheared by ``lean`` px across
    per px down, so the photo's gradients lean off the rows while its rows run straight."""
    rng = np.random.default_rng(seed)
    x = np.arange(size, dtype=np.float64)[None, :]
    leaves = ndimage.gaussian_filter(rng.standard_normal((size, size)), (4.0, 0.7))
    leaves = ndimage.affine_transform(leaves, [[1.0, 0.0], [lean, 1.0]], mode="wrap")
    image = (0.45 + rows * np.cos(2 * np.pi * x / period) + 0.02 * leaves / leaves.std()
             + 0.03 * rng.standard_normal((size, size)))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def two_by_two(size: int = 256, blend: float = 0.0, seed: int = 4) -> np.ndarray:
    """A game texture made of 2 x 2 copies of one tile of half the photo (0ad's terrains), each
    copy mixed ``blend`` of the way towards its own noise (0: exact copies)."""
    rng = np.random.default_rng(seed)
    half = size // 2
    tile = ndimage.gaussian_filter(rng.standard_normal((half, half)), 3.0, mode="wrap")
    copies = np.tile(tile, (2, 2))
    own = ndimage.gaussian_filter(rng.standard_normal((size, size)), 3.0, mode="wrap")
    image = 0.5 + 0.12 * ((1 - blend) * copies / tile.std() + blend * own / own.std())
    image += 0.01 * rng.standard_normal((size, size))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def wavy_rows(period: float = 9.1, size: int = 256, wave: float = 1.2, seed: int = 6) -> np.ndarray:
    """Rows up-down, ``period`` px apart across x, that wave and break (0ad's temp_farmland:
    rows of crops): each row's phase wanders by ``wave`` radians (std) over tens of px down and
    a few rows across, under streaked leaves, so the photo's 2D correlation fades within a
    few rows while the rows' mean profile across x repeats."""
    rng = np.random.default_rng(seed)
    x = np.arange(size, dtype=np.float64)[None, :]
    drift = ndimage.gaussian_filter(rng.standard_normal((size, size)), (24.0, 2 * period), mode="wrap")
    leaves = ndimage.gaussian_filter(rng.standard_normal((size, size)), (4.0, 0.7), mode="wrap")
    image = (0.45 + 0.05 * np.cos(2 * np.pi * x / period + wave * drift / drift.std())
             + 0.04 * leaves / leaves.std() + 0.03 * rng.standard_normal((size, size)))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)


def module_pavement(module: int = 16, size: int = 256, seed: int = 8, largest: int = 4,
                    joint_depth: float = 0.15, mottling: float = 0.06) -> np.ndarray:
    """Slabs of 1 x 1 to ``largest`` x ``largest`` modules of ``module`` px laid on one grid,
    each its own tone, under ``mottling``, joints ``joint_depth`` darker between slabs only
    (0ad's medit_city_pavement): the joints run along some module lines and not others."""
    rng = np.random.default_rng(seed)
    cells = size // module
    slab = np.full((cells, cells), -1)
    for i in range(cells):
        for j in range(cells):
            if slab[i, j] >= 0:
                continue
            h, w = rng.integers(1, largest + 1, 2)
            while h > 1 and (i + h > cells or (slab[i:i + h, j] >= 0).any()):
                h -= 1
            while w > 1 and (j + w > cells or (slab[i:i + h, j:j + w] >= 0).any()):
                w -= 1
            slab[i:i + h, j:j + w] = i * cells + j
    pixels = np.repeat(np.repeat(slab, module, axis=0), module, axis=1)
    joint = np.zeros((size, size), bool)
    joint[:, :-1] |= pixels[:, :-1] != pixels[:, 1:]
    joint[:-1, :] |= pixels[:-1, :] != pixels[1:, :]
    joint = ndimage.binary_dilation(joint)
    tone = rng.uniform(-0.08, 0.08, cells * cells)[pixels]
    mottle = ndimage.gaussian_filter(rng.standard_normal((size, size)), 3.0)
    image = (0.6 + tone + mottling * mottle / mottle.std() - joint_depth * joint
             + 0.01 * rng.standard_normal((size, size)))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)
