"""Repeats in two directions: a photo's 2D lattice (bricks, tile grids, perforated metal),
refined by least squares and folded where the photo folds sharpest; a far lattice (a rug's
bands of motifs), large cells (close-ups of tiles, 2 x 2 copies of one tile) and the lattice
of the direction streaks run in (parquet). Lattices are two basis vectors (ax, ay, bx, by) in
pixels at the working resolution, x right, y down.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from model.lattice import fold_on_lattice, lattice_cell_sizes
from model.structure.correlation import (LATTICE_MIN_OFFSET, LATTICE_PEAK, LATTICE_REACH, LATTICE_STRONG,
                                         LATTICE_SUPPORT, LATTICE_SUPPORT_PEAK, LATTICE_TIE, autocorrelation,
                                         locate_peaks, luminance_correlation, peak_height, repeat_peaks,
                                         rec709_luminance, strongest_peak, unwrapped_found_wrapped_measured,
                                         within_a_pixel)
from model.structure.grain import detect_grain
from model.structure.stripes import stripe_normal

# Large cells: a photo showing fewer than three repeats across (floor tiles photographed
# close: 2.5 tiles of 102 px at the working resolution) has its peaks beyond LATTICE_REACH.
# Looked for there only where nothing else was found (no lattice, grain, boards or stripes),
# and only lattices whose both vectors are at least LARGE_CELL_MIN of the image: a reach of
# 0.45 for every photo turned the cardboard's stripes into lattices with a far, chance
# second vector, and moved the validation brick wall's measured bond by 0.3 px. Half the
# image is as far as the correlation reaches (offsets of up to half the image each way):
# two whole tiles across is the fewest a lattice is found in (at 0.45, 2.25).
# A cell of half the photo (2 x 2 copies of one tile, as many game terrains are: 0ad's
# tropic_citytile_a and grass_dead read 1.0 there) shows each repeat once: both must be
# LATTICE_STRONG. (Before, such a lattice had no support: only lattice points under half the
# photo were counted, and none are; 42 of the 1,452 photos of data/textures-large got one
# through other points, most a pixel or two off half.) Now 70 do: 54 gained one, 28 with
# weaker repeats lost theirs.
LARGE_CELL_REACH = 0.5
LARGE_CELL_MIN = 0.25
# Long lattices (``detect_long_lattice``): one repeat within LATTICE_REACH, the other up to
# LARGE_CELL_REACH (a rug's bands of motifs, 62.7 px along and 112 px across at 256 px,
# peaks 0.68 / 0.44). Kept only if one peak is LATTICE_STRONG and each basis vector's
# correlation tops its value at half the vector by LONG_HALF_DIP: along grain or stripes
# the correlation is a ridge, high everywhere, and its noise has local maxima (synthetic
# boards: 0.62 at (0, 93) px, 0.63 at (0, 46)); a true repeat's half step falls between
# motifs (the rug: 0.68 -> 0.11, 0.44 -> -0.18; close-ups of floor tiles 0.85 -> 0.41).
LONG_HALF_DIP = 0.1
FINER_TIMES = 3  # how many times _finer_lattice may refine a lattice
# A repeat along stripes (``_repeats_along_stripes``) is a peak: its correlation (the largest
# within a pixel) tops the ridge's RIDGE_STEP px either way along it by LATTICE_TIE. Read
# within a pixel because on a turned photo the ridge leans off the pixel grid: the validation
# brick wall turned 5 degrees has its brick repeat at (32.9, -2.9) px, 0.74 at the nearest
# pixel, 0.86 one pixel over, and it lost its bricks (courses alone) to a single-pixel reading.
RIDGE_STEP = 4.0
# Refinement: every lattice point within a third of the image whose correlation peak is at
# least LATTICE_REFINE_PEAK, located to a fraction of a pixel, fits the basis by least
# squares; a basis read off single integer peaks can be a pixel or two off (the validation
# brick wall's was -14 px instead of about -16 px down, and its bond leaned).
LATTICE_REFINE_PEAK = 0.3
# Parquet (``detect_direction_lattice``): blocks of slats alternating between up-down and
# left-right, each slat its own tone, repeat in the direction of their streaks only. Their
# luminance correlation is the slats': synthetic parquet of 32-px blocks of 8-px slats
# (eval/synthetic_photos.py) peaks 0.49-0.51 at one slat across, both ways, a grid that no block
# repeats (support 0.2 < LATTICE_SUPPORT), and reads 0.42 at the blocks' checkerboard (32,
# 32): no lattice, no grain (as many slats run each way), nothing. Read from the structure
# tensor of DIRECTION_BLUR px derivatives averaged over DIRECTION_WINDOW px
# (``grain_direction_field``): on eight synthetic floors (blocks of 16-64 px, 2-8 slats,
# noise up to 0.06, one turned 4 degrees and saved as JPEG 60) the checkerboard's peaks read
# 0.69-0.92 at 1 / 3 px, 0.65-0.92 at 1 / 2, 0.42-0.85 at 2 / 3; at 1 / 5 the 16- and 20-px
# blocks blur under DIRECTION_SPREAD. On the 21 packaged photos this step is reached on (no
# lattice, grain, boards or stripes) the direction correlation has no peak of LATTICE_PEAK.
DIRECTION_BLUR = 1.0
DIRECTION_WINDOW = 3.0
# Where the gradient energy is under this share of its mean the field fades to 0: flat
# patches would otherwise read as the direction of their noise.
DIRECTION_FLOOR = 0.1
# The field's spread (RMS about its mean) below which the direction is taken as one: the
# packaged wood photos and brushed metal 0.12-0.26, synthetic boards 0.19; parquet 0.43-0.71.
DIRECTION_SPREAD = 0.3
# A checkerboard's equal repeats read up to 0.06 apart on the synthetic floors (64 blocks in
# view: few samples): (32, 32) px read 0.70, two blocks along 0.75, and LATTICE_TIE took the
# lattice of every other block.
DIRECTION_TIE = 0.1
# Both repeats the lattice starts from must reach this on the direction correlation (the
# synthetic parquet's read 0.69-0.92, above). On the 1,452 photos of data/textures-large,
# with LATTICE_PEAK, the step changed what 50 photos got, among them lattices for a glowing
# panel on black (top peak 0.57), a mosaic of wood blocks (0.33), bricks of uneven size and
# the tile grid of black-and-white checkerboards (half their repeat); with LATTICE_STRONG, 11:
# eight tile grids and stone running bonds whose tiles' tones hid them from the luminance
# (0.68-0.94), a plank floor (0.63, whose large cells were already wrong), a riveted metal
# wall and a hazard-striped band.
DIRECTION_PEAK = LATTICE_STRONG
# fold_lattice: how far (px) it moves each coordinate of the detected lattice, in what steps
FOLD_REACH, FOLD_STEP = 3.0, 0.25


def grain_direction_field(image: np.ndarray) -> np.ndarray:
    """(2, H, W) float64: the direction the photo's streaks run at each pixel as a doubled
    angle, (cos 2t, sin 2t) of the gradient's angle t times the local coherence: the
    structure tensor (derivatives of a DIRECTION_BLUR px Gaussian, averaged over a
    DIRECTION_WINDOW px one) as ((xx - yy), 2 xy) / (xx + yy + DIRECTION_FLOOR x its mean).
    Up-down streaks read (+1, 0), left-right ones (-1, 0), whatever their tone; faint
    regions (under the floor) read near 0 rather than as the direction of their noise."""
    luminance = rec709_luminance(image)
    gy, gx = (ndimage.gaussian_filter(luminance, DIRECTION_BLUR, order=order) for order in ((1, 0), (0, 1)))
    xx, xy, yy = (ndimage.gaussian_filter(v, DIRECTION_WINDOW) for v in (gx * gx, gx * gy, gy * gy))
    energy = xx + yy
    return np.stack([xx - yy, 2 * xy]) / (energy + DIRECTION_FLOOR * max(float(energy.mean()), 1e-20))


def direction_correlation(image: np.ndarray, wrap: bool = False, within: float = LATTICE_REACH
                          ) -> tuple[np.ndarray, list[tuple]] | None:
    """As ``luminance_correlation``, of the photo's ``grain_direction_field`` (its two
    components' autocorrelations summed, normalised to 1 at the origin): parquet's blocks
    of slats, alternating between up-down and left-right, repeat there as a checkerboard
    whatever each slat's tone. None where the direction does not vary (less than
    DIRECTION_SPREAD: grain all one way)."""
    field = grain_direction_field(image)
    field -= field.mean(axis=(1, 2), keepdims=True)
    if not np.sqrt(np.mean(np.sum(field ** 2, axis=0))) >= DIRECTION_SPREAD:
        return None
    if wrap:
        spectrum = np.fft.fft2(field)
        correlation = np.fft.ifft2(spectrum * np.conj(spectrum)).real.sum(axis=0)
    else:
        correlation = autocorrelation(field[0]) + autocorrelation(field[1])
    correlation /= correlation[0, 0]
    return correlation, repeat_peaks(correlation, within)


def detect_lattice(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """The 2D lattice a regular photo repeats on, two basis vectors in pixels (ax, ay, bx,
    by; x right, y down) at the image's resolution, or None. ``image``: (H, W, 3) RGB.
    Found on the unwrapped autocorrelation, measured on the wrapped one where that finds
    the same lattice (``unwrapped_found_wrapped_measured``)."""
    return unwrapped_found_wrapped_measured(image, _lattice_on)


def detect_large_cells(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """``detect_lattice`` with repeats looked for up to LARGE_CELL_REACH of the image, kept
    only if both basis vectors are at least LARGE_CELL_MIN of its shorter side (for photos
    where nothing else was found: ``photo_structure``), as its shortest basis
    (``shortest_basis``): with two tiles across, a repeat of half the image is as far one
    way as the other, and the diagonal can come out as a basis vector."""
    found = unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, within=LARGE_CELL_REACH))
    if found is None:
        return None
    found = shortest_basis(found)
    if min(np.hypot(found[0], found[1]), np.hypot(found[2], found[3])) < LARGE_CELL_MIN * min(image.shape[:2]):
        return None
    return None if _weak_half_cell(image, found) else found


def _weak_half_cell(image: np.ndarray, found: tuple[float, float, float, float]) -> bool:
    """Whether ``found`` (px) reaches half the photo, where each repeat is in view once, with a
    repeat under LATTICE_STRONG (``LARGE_CELL_REACH`` says why)."""
    height, width = image.shape[:2]
    if max(abs(found[0]), abs(found[2])) < width / 2 - 1 and max(abs(found[1]), abs(found[3])) < height / 2 - 1:
        return False
    correlation = luminance_correlation(image)[0]
    return min(within_a_pixel(correlation, np.array(found[:2])),
               within_a_pixel(correlation, np.array(found[2:]))) < LATTICE_STRONG


def detect_direction_lattice(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """The lattice the direction of a photo's streaks repeats on (parquet: square blocks of
    slats, up-down and left-right in a checkerboard, each slat its own tone), found as
    ``detect_lattice`` finds one, on ``direction_correlation``: the smallest translations
    that map the pattern of directions onto itself, (n, n) and (n, -n) px for blocks of n
    px. For photos where nothing else was found (``photo_structure``). Folded as a lattice
    of luminance is (``fold_lattice``), on the direction field: the correlation's peaks are
    pyramids a block wide, and a seam, wrapped, tilts them (40-px synthetic blocks: 40.5 px
    wrapped, 40.0 folded)."""
    found = unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, correlate=direction_correlation,
                                                                       tie=DIRECTION_TIE, least=DIRECTION_PEAK))
    if found is None:
        return None
    field = grain_direction_field(image)
    # fold_on_lattice bins three channels: the field's two and a zero one
    return fold_lattice(np.concatenate([field, np.zeros_like(field[:1])]).transpose(1, 2, 0), found)


def detect_long_lattice(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """A lattice with one repeat beyond LATTICE_REACH (a rug's bands of motifs: 62.7 px
    along them, 112 px across, at 256 px), looked for up to LARGE_CELL_REACH (for photos
    where no lattice, boards or stripes were found: ``photo_structure``), as its shortest
    basis, or None. Kept only if one of its two repeats is strong and each dips halfway to
    it (LATTICE_STRONG, LONG_HALF_DIP), with grain or without: a weak far repeat, or one
    on the ridge of grain or stripes, is too often chance. A lattice whose vectors are both
    within LATTICE_REACH is ``detect_lattice``'s to find or refuse; a cell of half the photo
    needs both repeats strong (``_weak_half_cell``)."""
    found = unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, within=LARGE_CELL_REACH,
                                                                       long=True))
    if found is None:
        return None
    found = shortest_basis(found)
    if max(np.hypot(found[0], found[1]), np.hypot(found[2], found[3])) <= LATTICE_REACH * min(image.shape[:2]):
        return None
    return None if _weak_half_cell(image, found) else found


def shortest_basis(lattice: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """The same lattice spanned by its two shortest independent vectors (Lagrange-Gauss
    reduction: take the shorter vector off the longer, as many whole times as brings it
    nearest, until that no longer shortens it), each pointing with non-negative x (y where
    x is near 0), the shorter first; a basis that is already shortest comes back as it was.
    (128, 128), (128, 0) px -> (128, 0), (0, 128)."""
    a, b = np.asarray(lattice, np.float64).reshape(2, 2)
    if abs(a @ b) <= 0.5 * min(a @ a, b @ b):
        return tuple(float(v) for v in lattice)
    if a @ a > b @ b:
        a, b = b, a
    while True:
        b = b - np.round((a @ b) / (a @ a)) * a
        if b @ b >= a @ a:
            break
        a, b = b, a
    a, b = (v if v[0] > 0.5 or (abs(v[0]) <= 0.5 and v[1] >= 0) else -v for v in (a, b))
    return float(a[0]), float(a[1]), float(b[0]), float(b[1])


def _lattice_on(image: np.ndarray, wrap: bool, within: float = LATTICE_REACH, long: bool = False,
                correlate=luminance_correlation, tie: float = LATTICE_TIE, least: float = LATTICE_PEAK  # noqa: ANN001
                ) -> tuple[float, float, float, float] | None:
    """``detect_lattice`` on the wrapped or unwrapped autocorrelation; ``long``: as
    ``detect_long_lattice`` keeps it (one strong repeat is enough, grain or not);
    ``correlate``: of what (``luminance_correlation``, ``direction_correlation``); ``tie``:
    how close to the strongest peak a peak counts as as strong (``_strongest``,
    ``_finer_lattice``); ``least``: how strong the two peaks the basis starts from must be."""
    measured = correlate(image, wrap, within)
    if measured is None or not measured[1]:
        return None
    correlation, found = measured
    # The strongest repeat first, then the strongest one at least 30 degrees from it: for a
    # running bond, one brick along the row and a few courses down (the course height
    # alone is not a repeat, the bricks shift by half a brick from one course to the next).
    value_a, length_a, ax, ay = strongest_peak(found, tie)
    others = [c for c in found if abs(ax * c[3] - ay * c[2]) > 0.5 * length_a * c[1]]
    if not others:
        return None
    value_b, _, bx, by = strongest_peak(others, tie)
    if min(value_a, value_b) < least:
        return None
    basis, across = np.array([[ax, ay], [bx, by]], np.float64), stripe_normal(image)
    for _ in range(FINER_TIMES):  # hexagonal tiles: a lattice of every 4th one, twice as fine twice
        finer = _finer_lattice(correlation, basis, found, across, tie)
        if finer is basis:
            break
        basis = finer
    basis, support = refine_lattice(correlation, basis, within)
    if support < LATTICE_SUPPORT:
        return None
    if long and (max(value_a, value_b) < LATTICE_STRONG or not all(
            within_a_pixel(correlation, v) >= within_a_pixel(correlation, v / 2) + LONG_HALF_DIP for v in basis)):
        return None
    if not long and min(value_a, value_b) < LATTICE_STRONG and detect_grain(image) is not None:
        return None
    if across is not None and not _repeats_along_stripes(correlation, basis, across, unseen=not long):
        return None  # stripes: b was a point on one of their ridges (detect_stripes' case)
    (ax, ay), (bx, by) = basis
    return float(ax), float(ay), float(bx), float(by)


def _finer_lattice(correlation: np.ndarray, basis: np.ndarray, peaks: list[tuple], across: np.ndarray | None,
                   tie: float = LATTICE_TIE) -> np.ndarray:
    """The lattice twice or three times as fine, where a half step of ``basis`` ((a + b) / 2,
    a / 2 or b / 2) or a third ((a +- b) / 3, a / 3, b / 3, and another point of its coset) is
    a repeat too: within 1.5 px of one of ``peaks`` (``luminance_correlation``'s local
    maxima) whose height between pixels (``peak_height``) is at least the basis's less
    ``tie``, and, if it runs along the stripes (``across``), a peak along them, not a
    point of their ridge (``_repeats_along_stripes``); else ``basis`` itself.

    The basis is the shortest of the near-strongest peaks, read at whole pixels, and
    near-ties go either way: the validation brick wall's bond, (-16, 10.7) px, and two
    courses down, (0, 21.3), are within 0.03 (read back from an 8-bit PNG with light falling
    across it, the photo got the stacked lattice of two courses). Hexagonal tiles repeat off
    the pixel grid in every direction but one, where they read up to 0.1 lower: 15-px tiles
    got a rectangular lattice of every other tile (26, 0), (0, 45) px, 17-px tiles one of
    every fourth (twice as fine twice: ``FINER_TIMES``), 20-px tiles one of every third."""
    if not peaks:
        return basis
    a, b = basis
    points = np.array([(dx, dy) for _, _, dx, dy in peaks], np.float64)
    points = points[peak_height(correlation, points) >= peak_height(correlation, basis).min() - tie]
    if not len(points):
        return basis
    halves = [(0.5 * (a + b), (a, 0.5 * (a + b))), (0.5 * a, (0.5 * a, b)), (0.5 * b, (a, 0.5 * b))]
    thirds = [((a + b) / 3, (a, (a + b) / 3)), ((a - b) / 3, (a, (a - b) / 3)), (a / 3, (a / 3, b)), (b / 3, (a, b / 3))]
    for k, (step, finer) in enumerate(halves + thirds):
        if np.hypot(*step) < LATTICE_MIN_OFFSET:
            continue
        # a third: another point of its coset must be a peak too (one can be there by chance)
        checked = [step] if k < len(halves) else [step, min(step - a, step - b, key=np.linalg.norm)]
        if any(np.hypot(*(points - point).T).min() > 1.5 for point in checked):
            continue
        if across is not None and abs(step @ across) < 1.0 \
                and not _repeats_along_stripes(correlation, np.array(finer), across):
            continue
        return np.array(finer)
    return basis


def _repeats_along_stripes(correlation: np.ndarray, basis: np.ndarray, across: np.ndarray, unseen: bool = True) -> bool:
    """Whether a lattice found on a striped photo (``across``: ``stripe_normal``) is a true
    lattice: its shortest vector along the stripes, where one is in view, is a peak of the
    correlation along them. Stripes correlate along whole ridges, one per period, so any
    point on a ridge can pass as a second repeat (8.8-px synthetic stripes gave b = (40.6,
    52.9) px, and b - 6 a = (40, 0) lies on the ridge through the origin, where the
    correlation only falls); a brick wall's courses are stripes too, and its bricks repeat
    along them: (32, 0) px is a peak. ``unseen``: the answer where none is in view (a long
    lattice's far vector on a striped photo is as likely a point of a ridge: no)."""
    height, width = correlation.shape
    i, j = np.meshgrid(np.arange(-12, 13), np.arange(-12, 13), indexing="ij")
    vectors = np.stack([i.ravel(), j.ravel()], axis=1) @ basis
    length = np.hypot(*vectors.T)
    along = (np.abs(vectors @ across) < 1.0) & (length > 0) & (np.abs(vectors[:, 0]) < width / 2) \
        & (np.abs(vectors[:, 1]) < height / 2)
    if not along.any():
        return unseen  # no repeat along the stripes in view (cinder blocks: 128 px): nothing to judge
    vector = vectors[along][np.argmin(length[along])]
    step = np.array([-across[1], across[0]]) * RIDGE_STEP
    crest = max(within_a_pixel(correlation, vector - step), within_a_pixel(correlation, vector + step))
    return bool(within_a_pixel(correlation, vector) >= crest + LATTICE_TIE)  # not a ridge's noise


def refine_lattice(correlation: np.ndarray, basis: np.ndarray, within: float = LATTICE_REACH) -> tuple[np.ndarray, float]:
    """A least-squares basis (2, 2) (rows a, b as x, y) for the lattice points i a + j b
    that ``correlation`` (normalised, origin at [0, 0], wrapping) shows, and the lattice's
    support: the share of its points within ``within`` of the image with a peak of at least
    LATTICE_SUPPORT_PEAK nearby. The fit uses each point's local peak, if at least
    LATTICE_REFINE_PEAK, to a fraction of a pixel (``locate_peaks``). ``basis`` comes back
    as it was when too few points agree or the fit moves a vector by more than a fifth of
    its length."""
    height, width = correlation.shape
    shortest = float(np.hypot(*basis.T).min())
    reach = int(np.ceil(max(height, width) / shortest))
    i, j = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    steps = np.stack([i.ravel(), j.ravel()], axis=1)
    steps = steps[(steps != 0).any(axis=1)]
    predicted = steps @ basis
    # (at most, not under: a photo of 2 x 2 copies of one tile repeats at exactly half of it)
    inside = (np.abs(predicted[:, 0]) <= width * within + 1e-9) & (np.abs(predicted[:, 1]) <= height * within + 1e-9)
    steps, predicted = steps[inside], np.rint(predicted[inside]).astype(int)
    if not len(steps):
        return basis, 0.0
    points, value, interior = locate_peaks(correlation, predicted, max(1, int(0.2 * shortest)))
    support = float(np.mean(value >= LATTICE_SUPPORT_PEAK))
    use = (value >= LATTICE_REFINE_PEAK) & interior
    if use.sum() < 4 or np.linalg.matrix_rank(steps[use]) < 2:
        return basis, support
    weight = np.sqrt(value[use])[:, None]
    fitted, *_ = np.linalg.lstsq(steps[use] * weight, points[use] * weight, rcond=None)
    moved = np.hypot(*(fitted - basis).T)
    if (moved > 0.2 * np.hypot(*basis.T)).any():
        return basis, support
    return fitted, support


def fold_lattice(image: np.ndarray, lattice_px: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """The lattice within ``FOLD_REACH`` px of ``lattice_px`` (each vector's x and y) on which
    the photo folds sharpest: the largest spread of its mean repeat cell (``fold_on_lattice``,
    bins fixed), by coordinate search in ``FOLD_STEP`` px, twice over. Autocorrelation peaks
    put the validation brick wall's bond at -13.8 px per course, where its vertical joints
    average out of the mean cell; folded, it comes out at -16 (half a brick), where they show."""
    sizes = lattice_cell_sizes(lattice_px)

    def spread(lattice: np.ndarray) -> float:
        means, counts = fold_on_lattice(image, tuple(lattice), sizes)
        return float(means[counts > 0].var(axis=0).sum())

    best = np.array(lattice_px, np.float64)
    offsets = np.arange(-FOLD_REACH, FOLD_REACH + FOLD_STEP / 2, FOLD_STEP)
    for _ in range(2):
        for k in range(4):
            trials = np.repeat(best[None], len(offsets), axis=0)
            trials[:, k] += offsets
            if abs(np.linalg.det(trials.reshape(-1, 2, 2))).min() < 1.0:
                continue  # (never near a degenerate basis)
            best = trials[int(np.argmax([spread(t) for t in trials]))]
    return tuple(float(v) for v in best)
