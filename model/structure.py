"""What regular structure a photo has, for a fit to build in: grain, a repeat lattice,
stripes, boards. Functions over (H, W, 3) RGB arrays in [0, 1] at the working resolution;
lattices are two basis vectors (ax, ay, bx, by) in pixels, x right, y down.

    grain, lattice_px = photo_structure(photo)   # what model.fit builds in by default

* ``detect_lattice``: a 2D repeat (bricks, tile grids, perforated metal), refined by least
  squares, then ``fold_lattice`` moves it to where the photo folds sharpest;
* ``detect_stripes``: a repeat along one direction only (corrugated board);
* ``detect_rows``: stripes that wave or break, seen in the profile along them (crop rows);
* ``detect_module_grid``: slabs or tiles of several sizes on one module (a pavement);
* ``detect_grain``: streaks along image x or y (wood, brushed metal);
* ``detect_boards``: on a photo with grain, boards side by side (plank floors, decking);
* ``detect_direction_lattice``: a 2D repeat of the direction streaks run in, not of their
  tone (parquet: blocks of slats, up-down and left-right in a checkerboard);
* ``detect_even``: a photo with none of these that is even at large scales (gravel, asphalt).
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from model.config import ModelConfig
from model.lattice import fold_on_lattice, lattice_cell_sizes
from worker.colour import even_lighting

# Grain detection (``grain="auto"``): a photo has grain when its luminance gradient energy
# across one image axis is at least GRAIN_RATIO times that along the other, at every
# blur in GRAIN_SCALES (px at the working resolution), so fine scratches alone or one
# coarse band alone do not count. Measured on the 41 packaged photos (log2 of the ratio
# at 1/2/4 px): the five wood photos (1.6-6.0), brushed metal (1.9-2.2), a striped rug
# (1.8) and skimage's brick laid on end (1.6-1.8: long joints up-down) pass; the brick
# wall (-0.06 at 4 px), cinder blocks (0.84), corrugated cardboard (0.19 at 4 px) do not.
GRAIN_RATIO = 3.0
GRAIN_SCALES = (1.0, 2.0, 4.0)
# How much longer a fit's noise cells are along the grain (``ModelConfig.grain_stretch``):
# STRONG_GRAIN_STRETCH where the gradient ratio is at least GRAIN_RATIO^2 at every blur
# (planed wood, planks: lines that run across the whole photo), else GRAIN_STRETCH. 60-s
# fits, seeds 0 / 1, quality-protocol tile style error, stretch 8 -> 16: ratio 11-63 (the
# validation wood, two training woods, planks) 0.038 / 0.039 -> 0.035 / 0.035, 0.035 / 0.030
# -> 0.009 / 0.008, 0.056 / 0.045 -> 0.044 / 0.033, 0.152 / 0.116 -> 0.097 / 0.098, and the
# lines run on instead of breaking into waves; ratio 3-5 (an old wood, the rug, brushed
# metal, skimage's brick) 0.457 / 0.331 -> 0.581 / 0.365, 10.5 / 10.3 -> 13.1 / 12.5,
# 0.029 / 0.051 -> 0.030 / 0.036, 0.337 / 0.367 -> 0.336 / 0.329.
GRAIN_STRETCH = ModelConfig.grain_stretch  # the model's default, 8
STRONG_GRAIN_STRETCH = 2 * GRAIN_STRETCH
# Grain off its image axis (``grain_tilt``, ``straighten``): the noise can be stretched
# along world x or y only, so a fit of a photo whose grain leans draws it along the axis
# as blobs with pale streaks (vpython_wood_old, about 7 degrees). Measured on the packaged
# photos with grain: that wood -6.9 degrees, brushed metal 2.5, the other six within 0.4
# (the striped rug 0.34). A fit turns a photo whose grain leans at least GRAIN_TILT_MIN degrees
# so that it runs along the nearer axis, and learns from the largest centred rectangle of
# the photo's shape inside the turned photo (a square: 0.78 of each side at 20 degrees,
# 0.71 at 45). Past about 30 degrees the axis test (``detect_grain``) no longer sees the
# grain (a wood photo turned 35-60 degrees: none found, the fit drew isotropic blotches):
# ``leaning_grain`` then looks for it on the photo turned by its main orientation. None of
# the 41 packaged photos without grain gains one that way (granite, the most directional,
# reaches a gradient ratio of 1.6 turned, under GRAIN_RATIO).
GRAIN_TILT_MIN = 3.0
GRAIN_TILT_MAX = 45.0
GRAIN_TILT_BLUR = 2.0


# Lattice detection (``lattice="auto"``): the photo repeats on a 2D lattice when its
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
# A lattice whose peaks are not all this strong loses to grain when the photo has grain:
# the wood planks' lattice (0.44) made a 60-s fit draw diagonal blobs, their grain (y)
# vertical boards.
LATTICE_STRONG = 0.6
LATTICE_SUPPORT = 0.6
LATTICE_SUPPORT_PEAK = 0.25
LATTICE_MIN_OFFSET = 4
LATTICE_TIE = 0.05  # peaks this close to the strongest count as equally strong
FINER_TIMES = 3  # how many times _finer_lattice may refine a lattice
PEAK_REACH, PEAK_STEP = 0.6, 0.1  # where and how finely peak_height reads between pixels
LANCZOS_TAPS = np.arange(-2, 4)  # Lanczos-3 reads the six samples floor(t) - 2 .. floor(t) + 3
# The correlation is scaled by its origin less white noise's share of it (``pixel_noise``),
# at most NOISE_SHARE_MAX: noise of 0.02-0.04 had lost the validation concrete's grid and the
# cardboards' stripes. Fine texture reads as noise too (gravel); capped, its peaks at most
# double, and no stochastic packaged photo or crop gained a lattice (make structure).
NOISE_SHARE_MAX = 0.5
# A repeat along stripes (``_repeats_along_stripes``) is a peak: its correlation (the largest
# within a pixel) tops the ridge's RIDGE_STEP px either way along it by LATTICE_TIE. Read
# within a pixel because on a turned photo the ridge leans off the pixel grid: the validation
# brick wall turned 5 degrees has its brick repeat at (32.9, -2.9) px, 0.74 at the nearest
# pixel, 0.86 one pixel over, and it lost its bricks (courses alone) to a single-pixel reading.
RIDGE_STEP = 4.0
# A lattice found on the unwrapped correlation is measured on the wrapped one where that
# finds the same lattice with no basis vector more than this many px away
# (``_unwrapped_found_wrapped_measured``). On the packaged photos they agree within 0.1 px.
WRAPPED_AGREE_PX = 1.0
# Refinement: every lattice point within a third of the image whose correlation peak is at
# least LATTICE_REFINE_PEAK, located to a fraction of a pixel, fits the basis by least
# squares; a basis read off single integer peaks can be a pixel or two off (the validation
# brick wall's was -14 px instead of about -16 px down, and its bond leaned).
LATTICE_REFINE_PEAK = 0.3
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

# Evenness (``detect_even``): the means of a photo's EVEN_BLOCK-px blocks vary by less than
# EVEN_SHARE of its luminance variance: nothing in it is larger than a few blocks. Measured on
# the 41 packaged photos at 256 px (share at 32 px): the metal grills 0.000 / 0.004, a
# ceiling tile and stucco 0.001, the skimage and validation gravel 0.015 / 0.016, asphalt
# 0.016, skimage grass 0.017, a grass 0.025, drywall 0.026; then concrete 0.033, the brick
# wall 0.041, the validation grass 0.073, granite 0.061, wood 0.15-0.44. A fit of an even
# photo mutes the noise octaves whose cells are EVEN_BLOCK px or larger (model.fit): the
# validation gravel's tiles otherwise keep blotches of 35-100 px with 3-6x the photo's
# power there (docs/DECISIONS.md, "Even photos mute their coarse octaves").
EVEN_BLOCK = 32
EVEN_SHARE = 0.03


def rec709_luminance(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB -> (H, W) float64 Rec. 709 luminance, what every detector here reads."""
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


def _strongest(candidates: list[tuple], tie: float = LATTICE_TIE) -> tuple:
    """The shortest of the (near-)strongest peaks (within ``tie`` of the top): not a multiple of it."""
    top = max(value for value, *_ in candidates)
    return min((c for c in candidates if c[0] >= top - tie), key=lambda c: c[1])


def detect_lattice(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """The 2D lattice a regular photo repeats on, two basis vectors in pixels (ax, ay, bx,
    by; x right, y down) at the image's resolution, or None. ``image``: (H, W, 3) RGB.
    Found on the unwrapped autocorrelation, measured on the wrapped one where that finds
    the same lattice (``_unwrapped_found_wrapped_measured``)."""
    return _unwrapped_found_wrapped_measured(image, _lattice_on)


def _unwrapped_found_wrapped_measured(image: np.ndarray, find) -> tuple[float, float, float, float] | None:  # noqa: ANN001
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


def detect_large_cells(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """``detect_lattice`` with repeats looked for up to LARGE_CELL_REACH of the image, kept
    only if both basis vectors are at least LARGE_CELL_MIN of its shorter side (for photos
    where nothing else was found: ``photo_structure``), as its shortest basis
    (``shortest_basis``): with two tiles across, a repeat of half the image is as far one
    way as the other, and the diagonal can come out as a basis vector."""
    found = _unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, within=LARGE_CELL_REACH))
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
    return min(_within_a_pixel(correlation, np.array(found[:2])),
               _within_a_pixel(correlation, np.array(found[2:]))) < LATTICE_STRONG


def detect_direction_lattice(image: np.ndarray) -> tuple[float, float, float, float] | None:
    """The lattice the direction of a photo's streaks repeats on (parquet: square blocks of
    slats, up-down and left-right in a checkerboard, each slat its own tone), found as
    ``detect_lattice`` finds one, on ``direction_correlation``: the smallest translations
    that map the pattern of directions onto itself, (n, n) and (n, -n) px for blocks of n
    px. For photos where nothing else was found (``photo_structure``). Folded as a lattice
    of luminance is (``fold_lattice``), on the direction field: the correlation's peaks are
    pyramids a block wide, and a seam, wrapped, tilts them (40-px synthetic blocks: 40.5 px
    wrapped, 40.0 folded)."""
    found = _unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, correlate=direction_correlation,
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
    found = _unwrapped_found_wrapped_measured(image, functools.partial(_lattice_on, within=LARGE_CELL_REACH,
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
    value_a, length_a, ax, ay = _strongest(found, tie)
    others = [c for c in found if abs(ax * c[3] - ay * c[2]) > 0.5 * length_a * c[1]]
    if not others:
        return None
    value_b, _, bx, by = _strongest(others, tie)
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
            _within_a_pixel(correlation, v) >= _within_a_pixel(correlation, v / 2) + LONG_HALF_DIP for v in basis)):
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
    crest = max(_within_a_pixel(correlation, vector - step), _within_a_pixel(correlation, vector + step))
    return bool(_within_a_pixel(correlation, vector) >= crest + LATTICE_TIE)  # not a ridge's noise


def _within_a_pixel(correlation: np.ndarray, point: np.ndarray) -> float:
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


def _locate_peaks(correlation: np.ndarray, predicted: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def refine_lattice(correlation: np.ndarray, basis: np.ndarray, within: float = LATTICE_REACH) -> tuple[np.ndarray, float]:
    """A least-squares basis (2, 2) (rows a, b as x, y) for the lattice points i a + j b
    that ``correlation`` (normalised, origin at [0, 0], wrapping) shows, and the lattice's
    support: the share of its points within ``within`` of the image with a peak of at least
    LATTICE_SUPPORT_PEAK nearby. The fit uses each point's local peak, if at least
    LATTICE_REFINE_PEAK, to a fraction of a pixel (``_locate_peaks``). ``basis`` comes back
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
    points, value, interior = _locate_peaks(correlation, predicted, max(1, int(0.2 * shortest)))
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
    Found and measured as ``detect_lattice`` is (``_unwrapped_found_wrapped_measured``)."""
    return _unwrapped_found_wrapped_measured(image, _stripes_on)


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
    value, length, ax, ay = _strongest(found)
    height, width = correlation.shape
    reach = int(np.ceil(max(height, width) / length))
    steps = np.array([k for k in range(-reach, reach + 1) if k], np.float64)
    predicted = steps[:, None] * np.array([ax, ay], np.float64)
    inside = (np.abs(predicted[:, 0]) < width / 3) & (np.abs(predicted[:, 1]) < height / 3)
    steps, predicted = steps[inside], np.rint(predicted[inside]).astype(int)
    if len(steps) < STRIPE_MIN_REPEATS:
        return None
    points, values, interior = _locate_peaks(correlation, predicted, max(1, int(0.2 * length)))
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


def detect_grain(image: np.ndarray) -> str | None:
    """The axis the photo's grain runs along, ``"x"`` (left-right) or ``"y"`` (up-down),
    or None for an isotropic photo. ``image``: (H, W, 3) RGB in [0, 1] at the working
    resolution. Diagonal grain counts as none (a fit can stretch along x or y only)."""
    log_ratios = _gradient_log_ratios(image)
    threshold = np.log2(GRAIN_RATIO)
    if min(log_ratios) >= threshold:
        return "y"  # changes across columns, constant down them: streaks run up-down
    if max(log_ratios) <= -threshold:
        return "x"
    return None


def _gradient_log_ratios(image: np.ndarray) -> list[float]:
    """log2 of the luminance gradient energy across columns over that across rows, at each
    blur in GRAIN_SCALES: positive where streaks run up-down (y), negative left-right (x)."""
    luminance = rec709_luminance(image)
    log_ratios = []
    for sigma in GRAIN_SCALES:
        rows, cols = np.gradient(ndimage.gaussian_filter(luminance, sigma))
        log_ratios.append(np.log2(max(float(np.mean(cols ** 2)), 1e-20) / max(float(np.mean(rows ** 2)), 1e-20)))
    return log_ratios


def grain_stretch(image: np.ndarray, grain: str) -> float:
    """How much longer the fit's noise cells are along ``grain`` ("x" or "y"): the strong
    stretch where the photo's gradient ratio is at least GRAIN_RATIO^2 at every blur."""
    log_ratios = np.asarray(_gradient_log_ratios(image)) * (1.0 if grain == "y" else -1.0)
    return STRONG_GRAIN_STRETCH if log_ratios.min() >= 2 * np.log2(GRAIN_RATIO) else GRAIN_STRETCH


def grain_tilt(image: np.ndarray, grain: str) -> float:
    """Degrees from the image axis ``grain`` (``"x"`` or ``"y"``) to the direction the
    photo's grain runs, measured from +x towards +y (x right, y down: clockwise as shown),
    in (-90, 90]. The grain runs where the luminance changes least: across the main axis of
    the structure tensor (the mean outer product of the luminance gradient, taken as
    derivatives of a GRAIN_TILT_BLUR px Gaussian: ``structure_tensor``)."""
    (xx, xy), (_, yy) = structure_tensor(image)
    across = 0.5 * np.degrees(np.arctan2(2 * xy, xx - yy))
    axis = 0.0 if grain == "x" else 90.0
    return float(-((axis - across) % 180.0 - 90.0))


def structure_tensor(image: np.ndarray, blur: float = GRAIN_TILT_BLUR) -> np.ndarray:
    """(2, 2) float64: the mean outer product of the luminance gradient (x, y), taken as
    derivatives of a ``blur`` px Gaussian, without the border the blur mirrors."""
    luminance = rec709_luminance(image)
    margin = int(4 * blur)  # the blur's mirrored border bends leaning streaks
    # derivatives of the Gaussian: central differences damp the steeper component of a
    # leaning streak more and overstate its lean (by 7% on 9-px stripes)
    gy, gx = (ndimage.gaussian_filter(luminance, blur, order=order)[margin:-margin, margin:-margin]
              for order in ((1, 0), (0, 1)))
    return np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])


def photo_lean(image: np.ndarray, blur: float = GRAIN_TILT_BLUR) -> tuple[float, float]:
    """(degrees, stretch): the direction the photo's features run along, as ``grain_tilt``
    measures it from +x towards +y, and how much longer they are along it than across it
    (the square root of the structure tensor's eigenvalue ratio: features stretched k times
    have gradients k times weaker along them)."""
    # eigenvalues ascending: the first vector is where luminance changes least, along the features
    values, vectors = np.linalg.eigh(structure_tensor(image, blur))
    if not values[1] > 0:  # a flat photo (no gradient anywhere) leans nowhere: a stretch of 0 broke the fit
        return 0.0, 1.0
    degrees = (np.degrees(np.arctan2(vectors[1, 0], vectors[0, 0])) + 90.0) % 180.0 - 90.0
    return float(degrees), float(np.sqrt(values[1] / max(values[0], 1e-30)))


def grain_turn(image: np.ndarray, grain: str | None) -> float:
    """The degrees a fit turns the photo by so its grain runs along ``grain``'s axis: its
    ``grain_tilt`` where that leans GRAIN_TILT_MIN..GRAIN_TILT_MAX degrees, else 0 (no
    grain, one close enough to the axis, or one too far off it to call along it)."""
    tilt = grain_tilt(image, grain) if grain else 0.0
    return tilt if GRAIN_TILT_MIN <= abs(tilt) <= GRAIN_TILT_MAX else 0.0


def leaning_grain(image: np.ndarray) -> str | None:
    """The axis, ``"x"`` or ``"y"``, of a grain that leans too far for ``detect_grain``
    (which compares the gradients along the image axes): the axis nearer the photo's main
    orientation (``grain_tilt``), if the photo turned onto it (``straighten``) has grain
    along it; else None. The fit then turns the photo by ``grain_turn``."""
    tilt = grain_tilt(image, "x")  # (-90, 90] from +x
    axis = "x" if abs(tilt) <= 45.0 else "y"
    turn = grain_tilt(image, axis)
    if not GRAIN_TILT_MIN <= abs(turn) <= GRAIN_TILT_MAX:
        return None  # along an axis already: what detect_grain found, it found
    return axis if detect_grain(straighten(image, turn)) == axis else None


def turn_lattice(lattice: tuple[float, float, float, float], degrees: float) -> tuple[float, float, float, float]:
    """A lattice (ax, ay, bx, by) found on a photo ``straighten``ed by ``degrees``, in the
    photo's own frame: both vectors turned by ``degrees`` from +x towards +y."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    ax, ay, bx, by = lattice
    return (float(c * ax - s * ay), float(s * ax + c * ay), float(c * bx - s * by), float(s * bx + c * by))


def straighten(image: np.ndarray, degrees: float) -> np.ndarray:
    """``image`` turned by ``-degrees`` (a grain at ``degrees``, as ``grain_tilt`` measures,
    comes to lie along its axis): the largest centred rectangle of the image's own aspect
    that the turned image covers, at the same pixel size. Cubic interpolation, clipped to
    [0, 1]; (h, w, 3) -> (h', w', 3) with h' / h = w' / w <= 1."""
    height, width = image.shape[:2]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    # a w' x h' rectangle fits inside the turned w x h one when w'c + h'|s| <= w and w'|s| + h'c <= h
    shrink = min(width / (width * c + height * abs(s)), height / (width * abs(s) + height * c))
    out_h, out_w = int(height * shrink), int(width * shrink)
    rows, cols = np.mgrid[0:out_h, 0:out_w].astype(np.float64)
    y, x = rows - (out_h - 1) / 2, cols - (out_w - 1) / 2
    # output pixel (x, y) shows the photo at (x, y) turned by +degrees (x right, y down)
    src_x, src_y = x * c - y * s + (width - 1) / 2, x * s + y * c + (height - 1) / 2
    turned = [ndimage.map_coordinates(np.asarray(image[..., k], np.float64), [src_y, src_x], order=3, mode="nearest")
              for k in range(image.shape[2])]
    return np.clip(np.stack(turned, axis=-1), 0.0, 1.0).astype(image.dtype)


def detect_even(image: np.ndarray) -> bool:
    """Whether the photo's luminance is even at large scales: the variance of its
    ``EVEN_BLOCK``-px block means is below ``EVEN_SHARE`` of the pixels' variance (a flat
    photo, with no variance, is not called even: there is nothing to mute for)."""
    lum = rec709_luminance(image)
    rows, cols = lum.shape[0] // EVEN_BLOCK, lum.shape[1] // EVEN_BLOCK
    if rows * cols < 4 or lum.var() <= 1e-8:
        return False
    blocks = lum[:rows * EVEN_BLOCK, :cols * EVEN_BLOCK].reshape(rows, EVEN_BLOCK, cols, EVEN_BLOCK).mean(axis=(1, 3))
    return bool(blocks.var() < EVEN_SHARE * lum.var())


def photo_structure(photo: np.ndarray, grain: str | None = "auto", lattice: str | None = "auto"
                    ) -> tuple[str | None, tuple[float, float, float, float] | None]:
    """What a fit builds in for ``photo``: (grain, lattice in pixels).

    In this order, each where the ones before found nothing: a lattice (``detect_lattice``,
    folded; ``lattice="auto"``); grain along an axis (``detect_grain``; ``grain="auto"``);
    on a grain photo boards (``detect_boards``, which keep the grain), on one without,
    stripes (``detect_stripes``), else rows (``detect_rows``); a lattice reaching past a
    third of the photo (``detect_long_lattice``, which drops a detected grain: a rug's
    bands); on a grain photo, boards or ripples wider than a sixth of it
    (``detect_wide_boards``, which drop the grain too); a leaning grain (``leaning_grain``,
    without boards: they are looked for on the turned photo); a lattice of the direction of
    the streaks (``detect_direction_lattice``: parquet); large cells
    (``detect_large_cells``); a module grid (``detect_module_grid``: slabs of several sizes). Boards come before stripes on a grain photo: its boards'
    joints are stripes too, and the stripe detector reads their repeat at any multiple
    (9.3-px synthetic boards: 28 px, three boards) and would drop the grain. ``grain``
    "x" / "y" / None and ``lattice`` None are taken as given. A photo with a lattice or
    stripes gets no grain.

    The detectors read the photo with its smooth shading divided out
    (``worker.colour.even_lighting``): light falling off across a photo, or a vignette,
    otherwise dominates its luminance autocorrelation and its block means."""
    photo = even_lighting(photo)
    found = detect_lattice(photo) if lattice == "auto" else None
    found = fold_lattice(photo, found) if found else None
    asked = grain
    if grain == "auto":
        grain = None if found else detect_grain(photo)
    if lattice == "auto" and found is None:
        # boards: stripes that keep their grain; stripes: a lattice whose second vector
        # carries no repeat; rows: stripes seen only in their profile
        found = detect_boards(photo, grain) if grain else detect_stripes(photo) or detect_rows(photo)
    if lattice == "auto" and found is None:  # a rug's far lattice, else ripples: either replaces the grain
        found = detect_long_lattice(photo) or (detect_wide_boards(photo, grain) if grain else None)
        if found is not None and asked == "auto":
            grain = None
    if asked == "auto" and grain is None and found is None:
        grain = leaning_grain(photo)
    if lattice == "auto" and found is None and grain is None:
        found = detect_direction_lattice(photo)
    if lattice == "auto" and found is None and grain is None:
        found = detect_large_cells(photo)
    if lattice == "auto" and found is None and grain is None:
        found = detect_module_grid(photo)
    return grain, found
