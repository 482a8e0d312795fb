"""Repeats read along one direction at a time: stripes (corrugated board), boards across a
grain (plank floors), wide boards and ripples (along their lean), rows seen in their profile
(crop rows), each as a lattice (ax, ay, bx, by) in pixels whose a is the repeat and b a
turned a quarter turn, along the stripes, where the photo does not repeat
(``stripe_lattice``); and a module grid (slabs of several sizes), the rows' period along x
and along y as one lattice.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from model.structure.correlation import (LATTICE_MIN_OFFSET, LATTICE_STRONG, LATTICE_SUPPORT, autocorrelation,
                                         locate_peaks, luminance_correlation, parabola_top, rec709_luminance,
                                         strongest_peak, unwrapped_found_wrapped_measured)
from model.structure.grain import detect_grain

# Stripes (``detect_stripes``): a repeat along one direction only, seen at its multiples.
# The validation corrugated cardboard: period 8.8 px down, peaks 0.44, 0.37, 0.30, 0.28,
# 0.26, 0.25, 0.23, 0.20, 0.19 at 1..9 periods (its large tone patches decorrelate
# slowly).
STRIPE_SUPPORT_PEAK = 0.15
# The stripes' repeat itself need only reach STRIPE_PEAK (a lattice's, LATTICE_PEAK): rows of
# crops seen from above (0ad's farmland_a) repeat every 10 px across at 0.29, 0.27, 0.24 and
# 0.28 for one to four rows, while their correlation along the rows is a ridge of 0.45.
STRIPE_PEAK = 0.2
# correlation_normal: the photo's stripe normal is kept where the correlation's is within
# NORMAL_KEEP_DEGREES of it, and replaced by it up to NORMAL_AGREE_DEGREES
NORMAL_KEEP_DEGREES, NORMAL_AGREE_DEGREES = 2.0, 20.0
# Gradient energy across the stripes over that along them (1-px blur): both corrugated
# cardboards 4.0, the other packaged photos with one repeat direction are grain (wood,
# brushed metal) or have a second repeat.
STRIPE_ANISOTROPY = 2.0
STRIPE_MIN_REPEATS = 6  # multiples within a third of the image, both signs: |a| <= 1/9 of it
# Boards (``detect_boards``): a grain photo made of boards (plank floors, decking,
# panelling) repeats across its grain at the boards' width, but its luminance
# autocorrelation hides that under the grain's own streaks (the training wood planks: 0.21
# at one board, 0.47 at five). Averaged along the grain first, the joints show: 0.60,
# 0.64, 0.69 at one, two, three boards of 25.6 px.
BOARD_PEAK = 0.4
BOARD_MIN_REPEATS = 2  # multiples within a third of the image: boards at most 1/6 of it
# Rows (``detect_rows``): stripes that wave or break, whose 2D correlation fades before
# enough multiples reach STRIPE_SUPPORT_PEAK. 0ad's temp_farmland (rows of crops, 9.1 px
# apart at the working size) reads 0.22, 0.15, 0.11, 0.11 at two to eight rows in 2D; its
# profile along the rows 0.52, 0.57, 0.32, 0.42, 0.20, 0.28 at one to six. Of the 1,452
# corpus photos, 7 get rows: 6 with nothing else found (farmland, brick courses, a
# corrugated roof), and tropic_farmland, whose rows a long lattice (105 px) carried before.
ROW_PEAK = 0.3
ROW_SUPPORT_PEAK = 0.25
ROW_MIN_REPEATS = 3  # multiples within a third of the image: rows at most 1/9 of it
FLAT_PROFILE = 1e-10  # a profile's mean square (luminance 0-1) under which it is flat
# Boards of uneven width (0ad's bridge_wood_a: planks) repeat only on average, the profile
# 0.38, 0.26, 0.22, 0.22, 0.29 at one to five of their mean width, 10.7 px. Where no board
# reaches BOARD_PEAK, a first peak of ROW_PEAK with ROW_MIN_REPEATS multiples at
# UNEVEN_BOARD_PEAK: on the corpus's grain photos without boards, 3 of 1,452 (the planks; two
# metal panels whose slots repeat every 16 px); with two multiples, also the packaged wood_2's
# broad bands (33.5 px), one piece of wood. The planks' 70-s fit: 5.0x -> 1.7x the floor.
UNEVEN_BOARD_PEAK = 0.2
# Wide boards and ripples (``wide_period``, ``detect_wide_boards``): a repeat across the grain
# too wide for two multiples within a third of the photo (over a sixth of it, up to a
# quarter). The wind ripples on 0ad's savanna_sand_dunes_100 run left-right and wave, 43.5 px
# apart at the working size: the profile across them reads 0.46 at one ripple after swinging
# to -0.64 at half of one. The dark woods and the bark of the corpus have a first local
# maximum below zero (-0.21, -0.5): no repeat. Their grain is dropped, as a long lattice drops
# it: paired 70-s fits (seed 0) over the photo's floor, grain -> stripes: savanna dunes 6.20 ->
# 4.46, desert dunes 5.71 -> 4.46, ufoai roof panels 31.8 -> 4.14 (stripes keeping the grain:
# 6.73, 4.42, 4.68).
WIDE_PEAK = 0.4
WIDE_DIP = 0.3
# Ripples lean as a whole: the savanna dunes' crests run 10.7 degrees off x (their gradients;
# 10.5 in their autocorrelation) while their repeat down the photo stays sharp (0.53 at 45 px;
# profiles turned 4-14 degrees smear it to 0.31-0.46). Stripes turned to the lean, as far
# apart down the photo: paired 70-s fits over the floor, seeds 0 and 1, 3.91 and 3.78 -> 2.58
# and 2.43. Waving ripples that run along x read up to 5.8 degrees off it (synthetic ripples,
# 40-56 px, four seeds): a lean under WIDE_LEAN_MIN is the crests' own wave.
WIDE_LEAN_MIN, WIDE_LEAN_MAX = 7.0, 20.0


def detect_stripes(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """A photo that repeats along one direction only (corrugated cardboard, ribbed or
    fluted surfaces): its period vector a in pixels, as a lattice (ax, ay, bx, by) whose b
    is a turned a quarter turn (along the stripes), or None. Where ``detect_lattice`` finds
    no second repeat.

    The repeat is the strongest autocorrelation peak; it counts when the peaks come back at
    its multiples k a within a third of the image (a share of at least LATTICE_SUPPORT
    reach STRIPE_SUPPORT_PEAK), and a is their least-squares period. b carries no repeat of
    the photo: the fit's phase inputs along it start at zero weight, and the photo's mean
    cell, folded on a square cell of side |a|, is flat along it. Meant for photos where
    ``detect_lattice`` finds no lattice: peaks in other directions are not looked at.
    Found and measured as ``detect_lattice`` is (``unwrapped_found_wrapped_measured``)."""
    return unwrapped_found_wrapped_measured(image, _stripes_on)


def _stripes_on(image: np.ndarray, wrap: bool) -> tuple[float, float, float, float] | None:
    """``detect_stripes`` on the wrapped or unwrapped autocorrelation."""
    measured, across = luminance_correlation(image, wrap, least=STRIPE_PEAK), stripe_normal(image)
    if measured is None or across is None:
        return None
    correlation, found = measured
    across = correlation_normal(correlation, across)
    # Any repeat a + t s (s along the stripes) shows the same stripes, and the peak found can
    # be any of them (the validation cardboard's is (2, 9) px, not (0, 9)): the period is
    # the repeat's part across the stripes. Peaks along the stripes (a brick wall's bricks
    # along their courses; bumps on the ridge through the origin) are no period across them.
    found = [c for c in found if abs(c[2] * across[0] + c[3] * across[1]) >= LATTICE_MIN_OFFSET]
    if not found:
        return None
    value, length, ax, ay = strongest_peak(found)
    height, width = correlation.shape
    reach = int(np.ceil(max(height, width) / length))
    steps = np.array([k for k in range(-reach, reach + 1) if k], np.float64)
    predicted = steps[:, None] * np.array([ax, ay], np.float64)
    inside = (np.abs(predicted[:, 0]) < width / 3) & (np.abs(predicted[:, 1]) < height / 3)
    steps, predicted = steps[inside], np.rint(predicted[inside]).astype(int)
    if len(steps) < STRIPE_MIN_REPEATS:
        return None
    points, values, interior = locate_peaks(correlation, predicted, max(1, int(0.2 * length)))
    if np.mean(values >= STRIPE_SUPPORT_PEAK) < LATTICE_SUPPORT:
        return None
    if value < LATTICE_STRONG and detect_grain(image) is not None:
        return None
    use = interior & (values >= STRIPE_SUPPORT_PEAK)
    if not use.any():
        return None  # every supporting peak at its window's edge: no period to measure (was NaN)
    weight = np.sqrt(values[use])
    # least squares of k a = p_k over the located peaks: a = sum w k p / sum w k^2
    repeat = (weight[:, None] * steps[use, None] * points[use]).sum(axis=0) / (weight * steps[use] ** 2).sum()
    return stripe_lattice(float(repeat @ across) * across)


def detect_boards(image: np.ndarray, grain: str) -> tuple[float, float, float, float] | None:
    """The boards of a photo with grain along ``grain`` ("x" or "y"): their width as a
    stripe lattice (ax, ay, bx, by) in pixels, a across the grain and b along it (a turned
    a quarter turn, as ``detect_stripes``), or None.

    The luminance is averaged along the grain (``across_grain_correlation``); the profile's
    autocorrelation must peak at BOARD_PEAK or more near a share of at least LATTICE_SUPPORT
    of the multiples of the width within a third of the image, at least BOARD_MIN_REPEATS of
    them (a width between two pixels splits its peaks), and the width is their
    least-squares period (``profile_period``). The shortest such repeat is the board (two
    boards are a repeat too). Where none is found, boards of uneven width: a first peak of
    ROW_PEAK, its multiples at UNEVEN_BOARD_PEAK, at least ROW_MIN_REPEATS of them (their
    mean width; two would pass a plain wood's broad bands)."""
    correlation = across_grain_correlation(image, grain)
    if correlation is None:
        return None
    width = (profile_period(correlation, BOARD_PEAK, BOARD_PEAK, BOARD_MIN_REPEATS)
             or profile_period(correlation, ROW_PEAK, UNEVEN_BOARD_PEAK, ROW_MIN_REPEATS))
    return _across_grain_stripes(width, grain) if width is not None else None


def detect_wide_boards(image: np.ndarray, grain: str) -> tuple[float, float, float, float] | None:
    """Boards or ripples wider than a sixth of the photo across its grain (``wide_period``:
    one repeat within a third of it), as ``detect_boards`` gives boards but along the photo's
    lean where it has one (``_leaning_stripes``), or None. Asked after
    ``detect_long_lattice`` (``photo_structure``): a rug's bands of motifs repeat across its
    weave too, and their lattice says more. Unlike boards they take the grain's place there
    (WIDE_PEAK's note has the figures)."""
    correlation = across_grain_correlation(image, grain)
    width = wide_period(correlation) if correlation is not None else None
    return _leaning_stripes(image, width, grain) if width is not None else None


def _leaning_stripes(image: np.ndarray, spacing: float, grain: str) -> tuple[float, float, float, float]:
    """Stripes ``spacing`` px apart along the axis across ``grain``, running along the photo's
    lean where its gradients and its autocorrelation agree on one (``stripe_direction``)
    WIDE_LEAN_MIN..WIDE_LEAN_MAX degrees off the grain's axis; else across the grain
    (``_across_grain_stripes``). Ripples lean as a whole while their repeat down the photo
    stays sharp (WIDE_LEAN_MAX's note). The autocorrelation checks the gradients: a gold
    brick wall's lean 6 degrees, its courses and their autocorrelation 0.1."""
    across = stripe_direction(image)
    if across is None:
        return _across_grain_stripes(spacing, grain)
    axis = np.array([0.0, 1.0]) if grain == "x" else np.array([1.0, 0.0])
    cos = abs(float(across @ axis))
    if not WIDE_LEAN_MIN <= np.degrees(np.arccos(min(cos, 1.0))) <= WIDE_LEAN_MAX:
        return _across_grain_stripes(spacing, grain)
    return stripe_lattice(spacing * cos * np.sign(across @ axis) * across)  # spacing apart along the axis


def across_grain_correlation(image: np.ndarray, grain: str) -> np.ndarray | None:
    """The autocorrelation (1 at [0], circular) of the photo's luminance averaged along its
    grain, ``"x"`` or ``"y"``: a profile across it, without what varies slower than an eighth
    of it (light falling off, wide grain bands); None for a flat profile."""
    if grain not in ("x", "y"):
        raise ValueError(f"grain must be 'x' or 'y', got {grain!r}")
    profile = rec709_luminance(image).mean(axis=0 if grain == "y" else 1)
    profile -= ndimage.gaussian_filter1d(profile, len(profile) / 8, mode="wrap")
    spectrum = np.fft.fft(profile)
    correlation = np.fft.ifft(spectrum * np.conj(spectrum)).real
    if not correlation[0] > 0:
        return None
    return correlation / correlation[0]


def _across_grain_stripes(width: float, grain: str) -> tuple[float, float, float, float]:
    """A stripe lattice of ``width`` px across ``grain``: a across it, b along it."""
    return stripe_lattice(np.array([width, 0.0]) if grain == "y" else np.array([0.0, width]))


def stripe_lattice(across: np.ndarray) -> tuple[float, float, float, float]:
    """Stripes repeating by ``across`` (px, (x, y)) as a lattice (ax, ay, bx, by): b is a
    turned a quarter turn, along the stripes, where the photo does not repeat."""
    ax, ay = across
    return float(ax), float(ay), float(-ay), float(ax)


def profile_period(correlation: np.ndarray, peak: float, support: float, min_repeats: int) -> float | None:
    """The period of a profile from its autocorrelation (1D, 1 at [0], offset d at index d mod
    n), or None: the shortest lag of at least LATTICE_MIN_OFFSET px that peaks at ``peak`` or
    more and comes back near a share of at least LATTICE_SUPPORT of its multiples within a
    third of the profile, at least ``min_repeats`` of them, at ``support`` or more (a period
    between two pixels splits its peaks); the period is their least-squares fit."""
    reach = len(correlation) // 3
    for lag in range(LATTICE_MIN_OFFSET, reach // min_repeats + 1):
        if not (correlation[lag] >= peak and correlation[lag] >= correlation[lag - 1]
                and correlation[lag] >= correlation[lag + 1]):
            continue
        first = lag + float(parabola_top(*correlation[lag - 1 : lag + 2]))
        steps = np.arange(1, reach // first + 1, dtype=np.float64)
        radius = max(2, int(0.2 * lag))
        # near each multiple: the largest value, a true local maximum, located by a parabola
        windows = np.rint(steps * first).astype(int)[:, None] + np.arange(-radius, radius + 1)
        values = correlation[windows % len(correlation)]
        best = values.argmax(axis=1)
        use = (values.max(axis=1) >= support) & (best > 0) & (best < 2 * radius)
        if np.mean(use) < LATTICE_SUPPORT or use.sum() < min_repeats:
            continue
        steps, at = steps[use], windows[use, best[use]]  # all within the first half: no wrapping
        peaks = at + parabola_top(correlation[at - 1], correlation[at], correlation[at + 1])
        return float((steps * peaks).sum() / (steps ** 2).sum())
    return None


def wide_period(correlation: np.ndarray, peak: float = WIDE_PEAK, dip: float = WIDE_DIP) -> float | None:
    """The period of a profile that repeats only once within a third of itself (wide boards,
    ripples: over a sixth of the profile, where ``profile_period`` would want two multiples),
    from its autocorrelation (1D, 1 at [0]), or None: its first local maximum from
    LATTICE_MIN_OFFSET px on, kept where it lies beyond a sixth and within a quarter of the
    profile (in view four times or more), reaches ``peak``, and the correlation swung down to
    ``-dip`` or lower before it (a clean oscillation); located between pixels by a parabola.
    A narrower first repeat is the other rules' to judge (a brick wall in perspective:
    courses that drift apart); a wider one is a close-up's broad band (the packaged wood's
    100-px corner at the working size: 0.6 at 82 px)."""
    for lag in range(LATTICE_MIN_OFFSET, len(correlation) // 4 + 1):
        if correlation[lag] >= correlation[lag - 1] and correlation[lag] >= correlation[lag + 1]:
            if 6 * lag <= len(correlation) or correlation[lag] < peak or correlation[:lag].min() > -dip:
                return None
            return lag + float(parabola_top(*correlation[lag - 1: lag + 2]))
    return None


def detect_rows(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """Stripes too faint or too wavy for ``detect_stripes`` (rows of crops seen from above,
    courses of bricks whose head joints do not line up): their period as a stripe lattice
    (ax, ay, bx, by) in pixels, a across the rows and b along them, or None.

    The photo's gradients must run across one direction (``stripe_direction``: the
    autocorrelation turns it, since a profile smears a period for every degree it is off); its
    luminance averaged along the rows (``row_profile``, without slow trends) must
    repeat (``profile_period``: ROW_PEAK, ROW_SUPPORT_PEAK, ROW_MIN_REPEATS)."""
    across = stripe_direction(image)
    period = row_period(image, across) if across is not None else None
    if period is None:
        return None
    return stripe_lattice(period * across)


def detect_module_grid(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """Slabs or tiles of several sizes laid on one module (a pavement of 1 x 1 to 2 x 3
    slabs): the module as a lattice (ax, 0, 0, by) in pixels, or None. Their joints run along
    some module lines and not others, so no 2D repeat is strong enough for a lattice and the
    gradients run both ways (no stripes); the luminance averaged along x and along y each
    repeat at the module (``row_period``)."""
    across_x, across_y = row_period(image, np.array([1.0, 0.0])), row_period(image, np.array([0.0, 1.0]))
    if across_x is None or across_y is None:
        return None
    return across_x, 0.0, 0.0, across_y


def row_period(image: np.ndarray, across: np.ndarray) -> float | None:
    """The period across ``across`` (a unit (x, y)) of the photo's luminance averaged along
    the lines normal to it (``row_profile``), or None (``profile_period``: ROW_PEAK,
    ROW_SUPPORT_PEAK, ROW_MIN_REPEATS)."""
    correlation = autocorrelation(row_profile(image, across))
    if not correlation[0] > FLAT_PROFILE:  # (a flat photo's profile is rounding noise, with any period)
        return None
    return profile_period(correlation / correlation[0], ROW_PEAK, ROW_SUPPORT_PEAK, ROW_MIN_REPEATS)


def row_profile(image: np.ndarray, across: np.ndarray) -> np.ndarray:
    """The luminance averaged along the lines normal to ``across`` (a unit (x, y)), one
    value a pixel across, where a line crosses at least half as many pixels as the longest
    (a turned profile's ends average a corner), less what varies slower than an eighth of it."""
    luminance = rec709_luminance(image)
    rows, cols = np.indices(luminance.shape)
    position = cols * across[0] + rows * across[1]
    bins = np.floor(position - position.min()).astype(np.int64).ravel()
    counts = np.bincount(bins)
    sums = np.bincount(bins, luminance.ravel())
    full = np.flatnonzero(counts >= 0.5 * counts.max())
    profile = sums[full[0]: full[-1] + 1] / np.maximum(counts[full[0]: full[-1] + 1], 1)
    return profile - ndimage.gaussian_filter1d(profile, len(profile) / 8, mode="nearest")


def stripe_normal(image: np.ndarray) -> np.ndarray | None:
    """The unit vector (x, y) across a striped photo's stripes: the dominant direction of
    its luminance gradients (the structure tensor's first eigenvector, after a 1-px blur),
    or None when the gradient energy along it is under STRIPE_ANISOTROPY times that along
    the stripes."""
    luminance = ndimage.gaussian_filter(rec709_luminance(image), 1.0)
    gy, gx = np.gradient(luminance)
    tensor = np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])
    energy, vectors = np.linalg.eigh(tensor)  # ascending
    if not energy[1] >= STRIPE_ANISOTROPY * max(energy[0], 1e-12):
        return None
    return vectors[:, 1]


def stripe_direction(image: np.ndarray) -> np.ndarray | None:
    """``stripe_normal`` read again from the photo's luminance autocorrelation
    (``correlation_normal``), or None where the photo has no one direction of gradients."""
    across = stripe_normal(image)
    measured = luminance_correlation(image, least=1.0) if across is not None else None  # (no peaks wanted)
    return correlation_normal(measured[0], across) if measured is not None else None


def correlation_normal(correlation: np.ndarray, across: np.ndarray) -> np.ndarray:
    """``across`` (a ``stripe_normal``) read again from the autocorrelation within a third of
    the image, the dominant direction of its gradients, where the two differ by
    NORMAL_KEEP_DEGREES to NORMAL_AGREE_DEGREES. The photo's own gradients lean with whatever
    crosses the stripes (the leaves on 0ad's farmland_a rows: 7 degrees off, which put a ridge
    bump 38 px along the rows 4.6 px across them, a period; the correlation: 0.01); on clean
    stripes they are exact, and the correlation's slowly fading tone patches turn it a little
    (the packaged cardboards: 0.05 degrees, 0.8 from the correlation)."""
    height, width = correlation.shape
    window = np.fft.fftshift(correlation)[height // 2 - height // 3: height // 2 + height // 3 + 1,
                                          width // 2 - width // 3: width // 2 + width // 3 + 1]
    gy, gx = np.gradient(window)
    tensor = np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])
    refined = np.linalg.eigh(tensor)[1][:, 1]
    turn = np.degrees(np.arccos(min(abs(float(refined @ across)), 1.0)))
    return refined * np.sign(refined @ across) if NORMAL_KEEP_DEGREES < turn <= NORMAL_AGREE_DEGREES else across
