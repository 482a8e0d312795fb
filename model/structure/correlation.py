"""A photo's luminance autocorrelation and its peaks: what the repeat detectors of
``model.structure`` (its lattices and stripes) read, and the thresholds they share. Functions
over (H, W, 3) RGB arrays in [0, 1] at the working resolution and over correlations laid out
as circular ones (offset d at index d mod n, the origin at [0, 0]); offsets are (dx, dy) in
pixels, x right, y down.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

# Lattice detection (``lattices.detect_lattice``): the photo repeats on a 2D lattice when its
# luminance autocorrelation has two independent peaks (not the origin, within a third of
# the image, at least LATTICE_MIN_OFFSET px away) both at least LATTICE_PEAK of the
# origin's value, and the lattice they span shows: of its points within a third of the
# image, at least LATTICE_SUPPORT have a peak of LATTICE_SUPPORT_PEAK or more nearby (a
# chance peak does not come back at 2a, a + b, ...; a lattice's does). Measured on the 41
# packaged photos at 256 px (peaks; support): found in 10, the brick wall (0.88 / 0.67;
# 1.00), cinder blocks, both metal grills, white and black-and-white floor tiles, ceiling
# tiles (0.83-1.0, 64 px tiles: a window of a quarter of the image, as before, missed
# them), concrete tiles (0.61 / 0.56), a woven cardboard (0.68 / 0.53) and a concrete photo
# that is a CG texture repeated 4 x 4 (0.54 / 0.45), all supported 0.95-1.00. The wood
# planks' (0.44 / 0.44; 1.00) gives way to their grain (LATTICE_STRONG); another cardboard
# has peaks 0.41 / 0.37 but support 0.14; the other 29 have no two peaks >= 0.3.
LATTICE_PEAK = 0.3
LATTICE_REACH = 1 / 3  # of the image's height and width: where repeats are looked for
# A lattice whose peaks are not all this strong loses to grain when the photo has grain:
# the wood planks' lattice (0.44) made a 60-s fit draw diagonal blobs, their grain (y)
# vertical boards.
LATTICE_STRONG = 0.6
LATTICE_SUPPORT = 0.6
LATTICE_SUPPORT_PEAK = 0.25
LATTICE_MIN_OFFSET = 4
LATTICE_TIE = 0.05  # peaks this close to the strongest count as equally strong
PEAK_REACH, PEAK_STEP = 0.6, 0.1  # where and how finely peak_height reads between pixels
LANCZOS_TAPS = np.arange(-2, 4)  # Lanczos-3 reads the six samples floor(t) - 2 .. floor(t) + 3
# The correlation is scaled by its origin less white noise's share of it (``pixel_noise``),
# at most NOISE_SHARE_MAX: noise of 0.02-0.04 had lost the validation concrete's grid and the
# cardboards' stripes. Fine texture reads as noise too (gravel); capped, its peaks at most
# double, and no stochastic packaged photo or crop gained a lattice (make structure).
NOISE_SHARE_MAX = 0.5
# A lattice found on the unwrapped correlation is measured on the wrapped one where that
# finds the same lattice with no basis vector more than this many px away
# (``unwrapped_found_wrapped_measured``). On the packaged photos they agree within 0.1 px.
WRAPPED_AGREE_PX = 1.0


def rec709_luminance(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB -> (H, W) float64 Rec. 709 luminance, what every detector of model.structure reads."""
    return np.asarray(image, np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def autocorrelation(values: np.ndarray) -> np.ndarray:
    """The autocorrelation of a zero-mean signal (1D or 2D) over the overlap of each offset
    with the signal itself (no wrapping: a photo does not tile, and its opposite edges,
    wrapped onto each other, add a seam's worth of false correlation), normalised by the
    overlap's size. Laid out as a circular autocorrelation of the same shape (offset d at
    index d mod n, offsets -n/2..n/2), so it is indexed like one; not yet scaled to 1 at 0."""
    shape = values.shape
    padded = [2 * n for n in shape]
    spectrum = np.fft.rfftn(values, padded)
    full = np.fft.irfftn(spectrum * np.conj(spectrum), padded)
    offsets = [(np.arange(n) + n // 2) % n - n // 2 for n in shape]  # signed, at index d mod n
    grid = np.ix_(*[d % (2 * n) for d, n in zip(offsets, shape)])
    overlap = functools.reduce(np.multiply, np.ix_(*[n - np.abs(d) for d, n in zip(offsets, shape)]))
    return full[grid] / overlap


def luminance_correlation(image: np.ndarray, wrap: bool = False, within: float = LATTICE_REACH,
                          least: float = LATTICE_PEAK) -> tuple[np.ndarray, list[tuple]] | None:
    """The photo's luminance autocorrelation, normalised to 1 at the origin ([0, 0]) less
    its white noise (``pixel_noise``, so values can pass 1 there; NOISE_SHARE_MAX),
    and its repeat peaks: local maxima of at least ``least``, at least
    LATTICE_MIN_OFFSET px from the origin and within ``within`` of the image, as (value,
    length, dx, dy). None for a flat photo. ``wrap``: circular (the photo taken as a tile,
    exact where it is one), else over each offset's overlap (``autocorrelation``)."""
    luminance = rec709_luminance(image)
    luminance -= luminance.mean()
    if wrap:
        spectrum = np.fft.fft2(luminance)
        correlation = np.fft.ifft2(spectrum * np.conj(spectrum)).real
    else:
        correlation = autocorrelation(luminance)
    if not correlation[0, 0] > 0:
        return None
    # White noise adds to the origin alone: scaled by the origin less the noise's share, the
    # repeats of a faint pattern in a noisy photo read as high as in the clean one.
    noise = min(pixel_noise(luminance) ** 2 / max(float(np.mean(luminance ** 2)), 1e-12), NOISE_SHARE_MAX)
    correlation /= correlation[0, 0] * (1.0 - noise)
    return correlation, repeat_peaks(correlation, within, least)


def repeat_peaks(correlation: np.ndarray, within: float = LATTICE_REACH, least: float = LATTICE_PEAK
                 ) -> list[tuple]:
    """A normalised correlation's (origin at [0, 0], wrapping) repeat peaks: local maxima of
    at least ``least``, at least LATTICE_MIN_OFFSET px from the origin and within
    ``within`` of the image, as (value, length, dx, dy)."""
    height, width = correlation.shape
    dy = (np.arange(height) + height // 2) % height - height // 2  # signed offsets, origin at 0
    dx = (np.arange(width) + width // 2) % width - width // 2
    dy, dx = np.meshgrid(dy, dx, indexing="ij")
    peaks = ((correlation == ndimage.maximum_filter(correlation, size=5, mode="wrap"))
             & (correlation >= least) & (np.hypot(dx, dy) >= LATTICE_MIN_OFFSET)
             & (np.abs(dx) <= int(width * within + 1e-9)) & (np.abs(dy) <= int(height * within + 1e-9)))
    return list(zip(correlation[peaks], np.hypot(dx[peaks], dy[peaks]), dx[peaks], dy[peaks]))

def peak_height(correlation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The height of the correlation's peaks at ``points`` ((N, 2) offsets dx, dy, rounded to
    pixels) between pixels: the largest value of its Lanczos-3 interpolation within
    PEAK_REACH px of each, on a PEAK_STEP px grid. A sharp repeat off the pixel grid reads low
    at its nearest pixel (hexagonal tiles of 15 px: 0.76 against 0.84 for an on-grid one);
    the parabolas through its neighbours, used before, still read 11-px tiles 0.09 low, this
    0.055 (the rest is the tiles' own pixels: grout drawn off the grid is not the same grout)."""
    height, width = correlation.shape
    centres = np.rint(np.asarray(points, np.float64).reshape(-1, 2))
    offsets = np.arange(-PEAK_REACH, PEAK_REACH + 1e-9, PEAK_STEP)
    # (N, S) sub-pixel positions along x and along y; every pair of them is a point read
    (first_x, wx), (first_y, wy) = (_lanczos_taps(centres[:, k:k + 1] + offsets) for k in (0, 1))
    rows, cols = first_y[..., None] + LANCZOS_TAPS, first_x[..., None] + LANCZOS_TAPS  # (N, S, 6) each
    # values[n, i, j, p, q]: the sample at row rows[n, i, p], column cols[n, j, q]
    values = correlation[rows[:, :, None, :, None] % height, cols[:, None, :, None, :] % width]
    read = np.einsum("nip,nijpq,njq->nij", wy, values, wx)
    return read.reshape(len(centres), -1).max(axis=1)


def _lanczos_taps(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``t`` (any shape, px) -> (floor(t) as int, the Lanczos-3 weights of the samples
    at floor(t) + LANCZOS_TAPS, shape t.shape + (6,), normalised to sum to 1)."""
    first = np.floor(t)
    distance = t[..., None] - (first[..., None] + LANCZOS_TAPS)
    weights = np.where(np.abs(distance) < 3, np.sinc(distance) * np.sinc(distance / 3), 0.0)
    return first.astype(int), weights / weights.sum(axis=-1, keepdims=True)


def pixel_noise(values: np.ndarray) -> float:
    """The standard deviation of white noise on a 2D signal, estimated robustly from its
    finest diagonal detail (Donoho's median absolute deviation of the diagonal Haar
    coefficients over 2x2 blocks, / 0.6745): edges and smooth shading barely move the
    median, fine texture does (the packaged gravel reads 0.11 of its 0-1 luminance, the
    brick wall 0.004, concrete 0.002; with noise of 0.02 per channel added, 0.015 and up)."""
    height, width = (n // 2 * 2 for n in values.shape)
    v = np.asarray(values, np.float64)[:height, :width]
    diagonal = (v[0::2, 0::2] - v[0::2, 1::2] - v[1::2, 0::2] + v[1::2, 1::2]) / 2
    return float(np.median(np.abs(diagonal)) / 0.6745)


def strongest_peak(candidates: list[tuple], tie: float = LATTICE_TIE) -> tuple:
    """The shortest of the (near-)strongest peaks (within ``tie`` of the top): not a multiple of it."""
    top = max(value for value, *_ in candidates)
    return min((c for c in candidates if c[0] >= top - tie), key=lambda c: c[1])

def unwrapped_found_wrapped_measured(image: np.ndarray, find) -> tuple[float, float, float, float] | None:  # noqa: ANN001
    """``find(image, wrap)``'s lattice: the one found without wrapping (a photo's opposite
    edges do not meet: wrapped, they add a seam of false correlation, and crops of the
    validation brick wall came out with a course on the ridge of the bed joints instead of
    the bond), but its wrapped measurement where that is the same lattice: a photo that
    does tile (CG textures) is measured exactly so (the validation grill 18.29 px, 14
    holes to 256 px; unwrapped 18.22, and its 60-s fit scored 0.34 instead of 0.13)."""
    found = find(image, wrap=False)
    if found is None:
        return None
    wrapped = find(image, wrap=True)
    if wrapped is None or not same_lattice(found, wrapped):
        return found
    # and within a pixel of it: a step's tenth is 12 px on a 120-px tile, and the wrapped
    # correlation of a close-up of tiles peaks at half the image, where its two edges meet
    first, second = np.asarray(found, np.float64).reshape(2, 2), np.asarray(wrapped, np.float64).reshape(2, 2)
    moved = np.abs(second - np.round(second @ np.linalg.inv(first)) @ first).max()
    return wrapped if moved <= WRAPPED_AGREE_PX else found


def same_lattice(a, b, tolerance: float = 0.1) -> bool:  # noqa: ANN001
    """Whether two bases (ax, ay, bx, by) in pixels span the same lattice: each is a whole
    combination of the other, to ``tolerance`` of a step, with determinant +-1."""
    first, second = np.asarray(a, np.float64).reshape(2, 2), np.asarray(b, np.float64).reshape(2, 2)
    steps = second @ np.linalg.inv(first)  # rows: b's vectors in a's steps
    whole = np.round(steps)
    return bool(np.abs(steps - whole).max() <= tolerance and abs(round(np.linalg.det(whole))) == 1)

def within_a_pixel(correlation: np.ndarray, point: np.ndarray) -> float:
    """The correlation's largest value within a pixel of ``point`` (dx, dy): a peak, or a
    ridge's crest off the pixel grid."""
    height, width = correlation.shape
    x, y = np.rint(point).astype(int)
    return float(correlation[(y + np.arange(-1, 2))[:, None] % height, (x + np.arange(-1, 2))[None, :] % width].max())


def parabola_top(before, at, after):
    """Offset from the middle sample of the top of the parabola through three equally
    spaced samples (arrays or numbers), 0 where they do not bend down."""
    curve = np.asarray(before - 2 * at + after, np.float64)
    return np.where(curve < 0, 0.5 * (before - after) / np.where(curve < 0, curve, -1.0), 0.0)


def locate_peaks(correlation: np.ndarray, predicted: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Near each predicted repeat (N, 2) (x, y px; rounded), the correlation's largest value
    within ``radius``: its position to a fraction of a pixel (a parabola through it and its
    neighbours along x and along y) (N, 2), its value (N,), and whether it is a true local
    maximum, not the window's edge climbing towards a neighbouring peak (N,)."""
    height, width = correlation.shape
    window = np.arange(-radius, radius + 1)
    ys = predicted[:, 1, None, None] + window[None, :, None]       # (N, K, 1) signed offsets
    xs = predicted[:, 0, None, None] + window[None, None, :]       # (N, 1, K)
    values = correlation[ys % height, xs % width]
    # offsets past half the image are the opposite ones (d - n): a window around a repeat
    # near half the image would find the repeat at -d there and take it for one at n - d
    values = np.where((np.abs(ys) <= height // 2) & (np.abs(xs) <= width // 2), values, -np.inf)
    values = values.reshape(len(predicted), -1)
    best = values.argmax(axis=1)
    peak_y, peak_x = predicted[:, 1] + window[best // len(window)], predicted[:, 0] + window[best % len(window)]
    at = correlation[peak_y % height, peak_x % width]
    dx = parabola_top(correlation[peak_y % height, (peak_x - 1) % width], at, correlation[peak_y % height, (peak_x + 1) % width])
    dy = parabola_top(correlation[(peak_y - 1) % height, peak_x % width], at, correlation[(peak_y + 1) % height, peak_x % width])
    interior = (np.abs(peak_x - predicted[:, 0]) < radius) & (np.abs(peak_y - predicted[:, 1]) < radius)
    return np.stack([peak_x + dx, peak_y + dy], axis=1), values.max(axis=1), interior

