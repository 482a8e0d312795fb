"""model/structure/: what regular structure a photo has (grain, a repeat lattice,
stripes, boards), measured on synthetic photos of known structure and on packaged ones."""
from __future__ import annotations

import numpy as np
from scipy import ndimage
import pytest

from model.structure import (GRAIN_STRETCH, STRONG_GRAIN_STRETCH, detect_boards, detect_direction_lattice,
                             detect_even, detect_grain, detect_large_cells, detect_lattice, detect_long_lattice,
                             detect_module_grid, detect_rows, detect_stripes, detect_wide_boards, fold_lattice,
                             grain_stretch, grain_tilt, grain_turn, leaning_grain, photo_lean, photo_structure,
                             same_lattice, straighten)
from model.structure.correlation import autocorrelation, luminance_correlation, peak_height, pixel_noise
from model.structure.lattices import _finer_lattice, _lattice_on, _repeats_along_stripes, shortest_basis
from model.structure.stripes import stripe_normal
from eval.synthetic_photos import (banded_motifs, boards, corrugation, crop_rows, fibres, hexagonal_tiles,
                                module_pavement, parquet, ripples, running_bond, streaks, two_by_two, wavy_rows)
from worker.colour import even_lighting


def test_detect_grain_finds_axis_aligned_streaks_only(skimage_textures):
    assert detect_grain(streaks()) == "y"                     # bands across x: the grain runs up-down
    assert detect_grain(streaks().transpose(1, 0, 2)) == "x"
    assert detect_grain(streaks(angle_degrees=45)) is None    # a fit can stretch along x or y only
    assert detect_grain(np.full((64, 64, 3), 0.5)) is None     # flat: no gradients at all
    for name in ("grass", "gravel"):                           # isotropic photos
        assert detect_grain(skimage_textures[name]) is None, name


def test_a_strong_grain_gets_the_long_stretch_a_weak_one_the_usual():
    """Gradients across the grain at least GRAIN_RATIO^2 those along it at every blur: the
    fit's noise cells are STRONG_GRAIN_STRETCH long, a weaker grain GRAIN_STRETCH; either axis."""
    strong, weak = fibres(40, 4), fibres(12, 4)
    assert detect_grain(strong) == detect_grain(weak) == "y"
    assert grain_stretch(strong, "y") == grain_stretch(streaks(), "y") == STRONG_GRAIN_STRETCH == 16.0
    assert grain_stretch(weak, "y") == GRAIN_STRETCH == 8.0
    assert grain_stretch(strong.transpose(1, 0, 2), "x") == STRONG_GRAIN_STRETCH
    assert grain_stretch(weak.transpose(1, 0, 2), "x") == GRAIN_STRETCH
    assert grain_stretch(strong, "x") == GRAIN_STRETCH  # measured along the grain it is given


def test_detect_lattice_finds_a_running_bond_and_nothing_in_stochastic_photos(skimage_textures):
    ax, ay, bx, by = detect_lattice(running_bond())

    def on_the_bond(x: float, y: float) -> bool:  # whole courses down, half a brick along per course
        courses = round(y / 11)
        along = x - courses * 16
        return abs(y - 11 * courses) < 0.25 and abs(along - 32 * round(along / 32)) < 0.25

    assert on_the_bond(ax, ay) and on_the_bond(bx, by), (ax, ay, bx, by)
    assert abs(ax * by - ay * bx) == pytest.approx(32 * 11, rel=0.02)  # the bond's lattice, not a sublattice
    for name in ("grass", "gravel"):
        assert detect_lattice(skimage_textures[name]) is None, name
    assert detect_lattice(np.full((64, 64, 3), 0.5)) is None


def test_fold_lattice_moves_a_bond_that_is_off_onto_the_photos_own():
    # the validation brick wall's peaks gave -13.8 px per course where the bond is -16: a
    # lattice that far off averages the vertical joints out of the mean cell
    image = running_bond()
    off = fold_lattice(image, (32.0, 0.0, -13.8, 11.0))
    assert off[:2] == pytest.approx((32.0, 0.0), abs=0.3)
    assert off[2] == pytest.approx(-16.0, abs=0.3) and off[3] == pytest.approx(11.0, abs=0.3)
    assert fold_lattice(image, (32.0, 0.0, 16.0, 11.0)) == pytest.approx((32.0, 0.0, 16.0, 11.0), abs=0.3)


def test_autocorrelation_is_the_mean_over_each_offsets_overlap():
    """No wrapping: at offset (dy, dx) the mean of l(p) l(p + d) over the pixels where both
    are in the image, at index (dy mod h, dx mod w)."""
    values = np.random.default_rng(0).standard_normal((6, 8))
    found = autocorrelation(values)
    assert found.shape == values.shape
    for dy in range(-3, 3):
        for dx in range(-4, 4):
            a = values[max(0, -dy):6 - max(0, dy), max(0, -dx):8 - max(0, dx)]
            b = values[max(0, dy):6 - max(0, -dy), max(0, dx):8 - max(0, -dx)]
            assert found[dy % 6, dx % 8] == pytest.approx(np.mean(a * b), abs=1e-12), (dy, dx)


@pytest.mark.parametrize("size, offset", [(230, 0), (200, 13), (181, 37)])
def test_detect_lattice_finds_a_running_bond_in_a_photo_that_does_not_tile(size, offset):
    """A photo's opposite edges do not meet: a wrapped autocorrelation saw a seam there and
    lost these crops of the bond (None); every lattice vector found must be on the bond."""
    found = detect_lattice(running_bond(300)[offset:offset + size, offset:offset + size])
    assert found is not None
    vectors = np.array(found).reshape(2, 2) @ np.linalg.inv(np.array([[32.0, 0.0], [16.0, 11.0]]))  # in bond steps
    assert np.abs(vectors - np.round(vectors)).max() < 0.05, found


def test_a_photo_that_tiles_is_measured_wrapped_one_that_does_not_unwrapped():
    """Found without wrapping; where the wrapped autocorrelation finds the same lattice (a
    photo that tiles, as CG textures do) its exact measurement is the one kept."""
    y, x = np.mgrid[0:256, 0:256].astype(np.float64)
    u, v = 2 * np.pi * x / (256 / 14), 2 * np.pi * y / (256 / 12)  # 14 x 12 holes: a tile
    holes = 0.5 + 0.25 * np.tanh(3 * (np.cos(u) + np.cos(v) + 0.6 * np.cos(u + v)))
    tile = np.repeat(np.clip(holes + 0.05 * np.random.default_rng(0).standard_normal(holes.shape), 0, 1)[..., None],
                     3, axis=2)
    assert same_lattice(_lattice_on(tile, False), _lattice_on(tile, True))
    assert detect_lattice(tile) == _lattice_on(tile, True)
    crop = running_bond(300)[:230, :230]  # the wrapped correlation loses this bond
    assert _lattice_on(crop, True) is None and detect_lattice(crop) == _lattice_on(crop, False)


def test_same_lattice_takes_any_basis_of_it_and_no_sublattice():
    bond = (32.0, 0.0, 16.0, 11.0)
    assert same_lattice(bond, (32.0, 0.0, -16.0, 11.0))        # b - a
    assert same_lattice(bond, (16.05, 11.0, -15.95, 11.0))     # b and b - a, a twentieth of a pixel off
    assert not same_lattice(bond, (32.0, 0.0, 0.0, 22.0))      # two courses: a sublattice
    assert not same_lattice(bond, (32.0, 0.0, 0.0, 11.0))      # the course alone: another lattice


def test_detect_lattice_measures_a_skewed_lattice_to_a_fraction_of_a_pixel():
    """Blobs on a lattice with non-integer, skewed basis vectors: single integer peaks are
    up to half a pixel off each; the least-squares refinement over every lattice point in
    view must find the lattice within 0.15 px per basis vector."""
    true = np.array([[23.4, 1.3], [9.3, 17.7]])
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:256, 0:256].astype(np.float64)
    image = np.zeros((256, 256))
    for i in range(-4, 20):
        for j in range(-4, 20):
            cx, cy = i * true[0] + j * true[1]
            image += rng.uniform(0.7, 1.0) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 2.5 ** 2))
    image = np.clip(0.2 + 0.6 * image + 0.03 * rng.standard_normal(image.shape), 0, 1)
    found = np.array(detect_lattice(np.repeat(image[..., None], 3, axis=2))).reshape(2, 2)
    # the same lattice: each true vector an integer combination of the found ones, and back
    change = true @ np.linalg.inv(found)
    assert abs(abs(np.linalg.det(np.rint(change))) - 1) < 1e-9, found
    assert np.abs(np.rint(change) @ found - true).max() < 0.15, found


def test_detect_lattice_finds_a_tile_grid_four_tiles_across():
    """Square tiles of a quarter of the photo (the validation floor tiles: 4 x 4 tiles of
    64 px at the working resolution), grey-veined with thin grout: the autocorrelation
    peaks are only ~0.45 and sit at a quarter of the image, yet the grid is found."""
    rng = np.random.default_rng(5)
    size, tile = 256, 64
    veins = ndimage.gaussian_filter(rng.standard_normal((size, size)), 6)
    image = 0.85 + 0.5 * veins / np.abs(veins).max() * 0.2
    y, x = np.mgrid[0:size, 0:size]
    image[(y % tile == 0) | (x % tile == 0)] = 0.55                    # 1-px grout
    found = detect_lattice(np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2))
    assert found is not None
    change = np.array([[tile, 0], [0, tile]]) @ np.linalg.inv(np.array(found).reshape(2, 2))
    assert np.abs(change - np.rint(change)).max() < 0.02 and abs(abs(np.linalg.det(np.rint(change))) - 1) < 1e-9, found


def test_tiles_larger_than_a_third_of_the_photo_are_found_where_nothing_else_is(skimage_textures):
    """2.5 tiles of 102 px across (a floor photographed close), not tiling: past the reach
    of detect_lattice, found by detect_large_cells, which photo_structure asks last; photos
    without a repeat and striped ones keep what they had."""
    rng = np.random.default_rng(5)
    size, tile = 256, 102.4
    veins = ndimage.gaussian_filter(rng.standard_normal((size, size)), 6)
    image = 0.85 + 0.1 * veins / np.abs(veins).max()
    y, x = np.mgrid[0:size, 0:size]
    image[(np.abs((y + 20) % tile) < 1.5) | (np.abs((x + 20) % tile) < 1.5)] = 0.55  # grout
    photo = np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)
    assert detect_lattice(photo) is None
    grain, found = photo_structure(photo)
    assert grain is None and found == detect_large_cells(even_lighting(photo))  # (what the detectors read)
    change = np.array([[tile, 0], [0, tile]]) @ np.linalg.inv(np.array(found).reshape(2, 2))
    assert np.abs(change - np.rint(change)).max() < 0.02 and abs(abs(np.linalg.det(np.rint(change))) - 1) < 1e-9, found
    for name in ("grass", "gravel", "brick"):
        assert detect_large_cells(skimage_textures[name]) is None, name
    assert photo_structure(corrugation()) == (None, pytest.approx(detect_stripes(even_lighting(corrugation()))))


@pytest.mark.parametrize("weave", [0.0, 0.08])
def test_a_lattice_reaching_past_a_third_of_the_photo_is_found_and_beats_the_grain(weave, skimage_textures):
    """A rug's bands of motifs: 60 px along them, 110 px down, past detect_lattice's reach.
    With a weave (grain x) the grain came first and the fit drew streaks; the lattice wins
    now, grain or not. Stochastic photos, stripes and a weak far repeat find none."""
    photo = banded_motifs(weave=weave)
    evened = even_lighting(photo)
    assert detect_lattice(evened) is None and detect_grain(evened) == ("x" if weave else None)
    grain, found = photo_structure(photo)
    assert grain is None and found is not None
    assert same_lattice(found, (60.0, 0.0, 0.0, 110.0), tolerance=0.01), found
    assert photo_structure(photo, grain="y") == ("y", found)  # a grain asked for is kept
    for name in ("grass", "gravel", "brick"):
        assert detect_long_lattice(even_lighting(skimage_textures[name])) is None, name
    assert detect_long_lattice(even_lighting(corrugation())) is None
    # along grain the correlation is a ridge whose noise has maxima: boards' (0, 93) px, 0.62
    assert detect_long_lattice(even_lighting(boards())) is None
    # a far repeat needs one strong peak: a faint grid of 100-px tiles (peaks ~0.5) is
    # left to detect_large_cells, which photo_structure asks last, a clear one is found
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:256, 0:256]
    texture = ndimage.gaussian_filter(rng.standard_normal((256, 256)), 2) / 0.14
    for noise, found in ((0.06, False), (0.01, True)):
        image = 0.8 + noise * texture
        image[(y % 100 < 2) | (x % 100 < 2)] -= 0.25
        assert (detect_long_lattice(np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)) is not None) == found


def test_two_tiles_across_are_found_at_their_size_not_at_half_the_photo():
    """2.1 tiles of 121 px across (the fewest a correlation up to half the image shows):
    found at 121 px, not 128 (repeats at -121 px lie within the search window around +121
    once it crosses half the image, and read as +135), as the two shortest vectors."""
    rng = np.random.default_rng(7)
    size, tile = 256, 121.0
    veins = ndimage.gaussian_filter(rng.standard_normal((size, size)), 6)
    image = 0.85 + 0.1 * veins / np.abs(veins).max()
    y, x = np.mgrid[0:size, 0:size]
    image[(np.abs((y + 30) % tile) < 1.5) | (np.abs((x + 30) % tile) < 1.5)] = 0.55
    grain, found = photo_structure(np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2))
    assert grain is None and found is not None
    lengths = np.hypot(*np.array(found).reshape(2, 2).T)
    assert np.abs(lengths - tile).max() < 1.0, found
    assert same_lattice(found, (tile, 0, 0, tile), tolerance=0.01), found


def test_a_repeat_along_leaning_stripes_is_read_within_a_pixel():
    """On a turned photo the ridge of the courses leans off the pixel grid, and the basis
    vector along it, fitted over many repeats, rounds to a pixel beside the peak (the
    validation brick wall turned 5 degrees: 0.74 there, 0.86 at the peak, 0.75 on the ridge
    2 px on, and its bricks were dropped for courses alone). A ridge without a peak stays
    no repeat."""
    size, lean = 128, np.radians(5.0)
    along, across = np.array([np.cos(lean), np.sin(lean)]), np.array([-np.sin(lean), np.cos(lean)])
    offsets = (np.arange(size) + size // 2) % size - size // 2  # signed, as the correlation is laid out
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    distance = np.abs(dx * across[0] + dy * across[1])             # from the ridge through the origin
    ridge = 0.75 * np.exp(-0.5 * (distance / 0.8) ** 2)
    brick = 32.9 * along                                            # the repeat along the ridge
    peak_pixel = np.rint(brick).astype(int) + np.array([-1, 0])      # where its peak shows: a pixel off
    correlation = ridge.copy()
    correlation[peak_pixel[1] % size, peak_pixel[0] % size] = 0.86
    correlation[-peak_pixel[1] % size, -peak_pixel[0] % size] = 0.86  # an autocorrelation is symmetric
    basis = np.array([brick, 10.7 * across + 16.0 * along])
    assert _repeats_along_stripes(correlation, basis, across)
    assert not _repeats_along_stripes(ridge, basis, across)


def test_a_tile_grid_in_a_vignette_keeps_its_grid():
    """Corners 60% darker (a strong vignette): the detectors read the photo with its smooth
    shading divided out, so the 64-px grid is found as on the evenly lit photo (before:
    none)."""
    rng = np.random.default_rng(5)
    size, tile = 256, 64
    veins = ndimage.gaussian_filter(rng.standard_normal((size, size)), 6)
    image = 0.85 + 0.1 * veins / np.abs(veins).max()
    y, x = np.mgrid[0:size, 0:size]
    image[(y % tile == 0) | (x % tile == 0)] = 0.55
    falloff = 1 - 0.3 * ((x - size / 2) ** 2 + (y - size / 2) ** 2) / (size * size / 4)
    grain, found = photo_structure(np.repeat((image * falloff)[..., None], 3, axis=2).astype(np.float32))
    assert grain is None and found is not None and same_lattice(found, (tile, 0, 0, tile), tolerance=0.01), found


def test_a_lattice_of_every_other_repeat_is_made_twice_as_fine():
    """Near-tied peaks can give the second vector two courses down instead of the bond
    (a stacked lattice, every other repeat): its half step (a + b) / 2 is a peak, so the
    bond comes back. Half a brick along the course, on the courses' ridge, is no repeat:
    the bond stays as it is."""
    photo = running_bond()
    correlation, peaks = luminance_correlation(photo)
    across = stripe_normal(photo)
    stacked = np.array([[32.0, 0.0], [0.0, 22.0]])
    finer = _finer_lattice(correlation, stacked, peaks, across)
    assert same_lattice(finer.ravel(), (32.0, 0.0, 16.0, 11.0), tolerance=0.05), finer
    bond = np.array([[32.0, 0.0], [16.0, 11.0]])
    assert np.array_equal(_finer_lattice(correlation, bond, peaks, across), bond)


@pytest.mark.parametrize("radius, turn", [(15, 0.0), (17, 0.0), (20, 0.0), (26, 7.0), (13, 30.0)])
def test_hexagonal_tiles_get_their_own_lattice_not_one_of_every_second_third_or_fourth_tile(radius, turn):
    """Hexagonal tiles repeat off the pixel grid, where their peaks read low: these came out
    as lattices of every 2nd (15 px, 26 px turned; 13 px turned 30 degrees until peaks were
    read by Lanczos interpolation), 4th (17 px) and 3rd (20 px) tile."""
    photo, truth = hexagonal_tiles(radius, turn)
    found = detect_lattice(photo)
    assert found is not None and same_lattice(found, truth, tolerance=0.05), (found, truth)


def test_peak_height_reads_a_peak_between_pixels():
    """A smooth peak of height 1 half a pixel off the grid both ways reads 0.78 at its
    nearest pixel and 0.90 by the parabolas through its neighbours; between pixels, by
    Lanczos interpolation, within 0.02 of 1. On the grid it reads what the pixel holds."""
    y, x = np.mgrid[0:64, 0:64]
    dy, dx = (y + 32) % 64 - 32, (x + 32) % 64 - 32  # offsets laid out as a correlation's
    correlation = np.exp(-((dx - 9.5) ** 2 + (dy - 16.5) ** 2) / 2.0) + np.exp(-(dx ** 2 + (dy + 20) ** 2) / 2.0)
    heights = peak_height(correlation, np.array([[10.0, 16.0], [0.0, -20.0]]))
    assert abs(heights[0] - 1.0) < 0.02 and abs(heights[1] - 1.0) < 1e-9, heights


def test_pixel_noise_reads_white_noise_and_not_edges():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:256, 0:256]
    grid = np.where((y % 64 < 3) | (x % 64 < 3), 0.5, 0.8) + 0.1 * np.sin(x / 40.0)  # edges, shading
    assert pixel_noise(grid) < 1e-3
    for sigma in (0.01, 0.03):
        assert pixel_noise(grid + sigma * rng.standard_normal(grid.shape)) == pytest.approx(sigma, rel=0.1)


@pytest.mark.parametrize("grout, noise", [(0.05, 0.02), (0.05, 0.03), (0.08, 0.04)])
def test_a_faint_grid_keeps_its_lattice_under_noise(grout, noise):
    """Grout 0.05-0.08 darker than a mottled glaze, under white noise of 0.02-0.04 (a phone
    in dim light): the noise had pulled every repeat under LATTICE_PEAK (none found)."""
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:256, 0:256]
    image = 0.7 + 0.02 * ndimage.gaussian_filter(rng.standard_normal((256, 256)), 6) / 0.05
    image[(y % 64 < 3) | (x % 64 < 3)] -= grout
    image = image + noise * rng.standard_normal((256, 256))
    grain, found = photo_structure(np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2))
    assert grain is None and found is not None and same_lattice(found, (64, 0, 0, 64), tolerance=0.05), found


def test_shortest_basis_spans_the_same_lattice_with_its_shortest_vectors():
    assert shortest_basis((128, 128, 128, 0)) == pytest.approx((128, 0, 0, 128))
    assert shortest_basis((5, 0, 47, 1)) == pytest.approx((2, 1, 1, -2))  # 47 - 9 x 5 = 2, then (5, 0) - 2 (2, 1)
    for basis in [(128, 128, 128, 0), (5, 0, 47, 1), (3, 4, -7, 11)]:
        reduced = np.array(shortest_basis(basis)).reshape(2, 2)
        assert same_lattice(basis, reduced.ravel(), tolerance=1e-9)
        a, b = reduced
        assert abs(a @ b) <= 0.5 * (a @ a) + 1e-9 and a @ a <= b @ b + 1e-9  # Gauss-reduced
    grid = (0.0, 64.0, -64.0, 0.0)  # already shortest: as it was, order and signs too
    assert shortest_basis(grid) == grid
    # a running bond's basis (a brick along, half a brick per course) is not the shortest:
    # its diagonals are (which is why only large cells are reduced)
    assert shortest_basis((32.0, 0.0, -16.0, 13.8)) == pytest.approx((16.0, -13.8, 16.0, 13.8))


def test_a_weak_lattice_gives_way_to_grain(monkeypatch):
    """A lattice with peaks under LATTICE_STRONG is kept for a photo without grain and
    dropped for one with grain (wood planks: their weak lattice drew blobs, their grain
    boards); a strong lattice stays either way."""
    import model.structure.lattices as lattices

    rng = np.random.default_rng(5)
    size, tile = 256, 64
    y, x = np.mgrid[0:size, 0:size]

    def grid(noise: float) -> np.ndarray:
        image = 0.8 + noise * ndimage.gaussian_filter(rng.standard_normal((size, size)), 2) / 0.14
        image[(y % tile < 2) | (x % tile < 2)] -= 0.25
        return np.repeat(np.clip(image, 0, 1)[..., None], 3, axis=2)

    weak, strong = grid(0.05), grid(0.01)            # autocorrelation peaks ~0.56 and ~0.95
    assert detect_lattice(weak) is not None and detect_lattice(strong) is not None
    monkeypatch.setattr(lattices, "detect_grain", lambda image: "y")
    assert detect_lattice(weak) is None and detect_lattice(strong) is not None


def test_detect_stripes_measures_the_period_across_the_stripes(skimage_textures):
    """A photo that repeats along one direction only has no 2D lattice, but its stripes are
    found: the period across them to a fraction of a pixel, the second vector along them.
    The peak the search starts from may lean (any a + t s shows the same stripes); the
    period must not. Stripes correlate along whole ridges, where a bump can pass for a
    second repeat: detect_lattice must not take one (the faint-patch board below gave it
    b = (40.6, 52.9) px before it checked for a repeat along the stripes)."""
    for board in (dict(), dict(wander_px=0.0), dict(patches=0.06, noise=0.02)):
        image = corrugation(**board)
        assert detect_lattice(image) is None, board
        ax, ay, bx, by = detect_stripes(image)
        assert abs(ax) < 0.05 and abs(abs(ay) - 8.8) < 0.15, (board, ax, ay)
        assert (bx, by) == pytest.approx((-ay, ax))              # a quarter turn: along the stripes
    image = corrugation()
    ax, ay, _, _ = detect_stripes(image.transpose(1, 0, 2))  # ridges up-down: the period runs along x
    assert abs(abs(ax) - 8.8) < 0.15 and abs(ay) < 0.05, (ax, ay)
    for name in ("gravel", "grass", "brick"):               # stochastic, or grain without a period
        assert detect_stripes(skimage_textures[name]) is None, name
    assert detect_stripes(np.full((64, 64, 3), 0.5)) is None
    # a brick wall's courses are stripes too; fit_exemplar asks for stripes only where
    # detect_lattice finds no lattice, and it finds the bond
    assert detect_lattice(running_bond()) is not None


def test_faint_rows_under_leaning_leaves_are_stripes_straight_across_them():
    """0ad's farmland_a: rows of crops 10 px apart whose repeat reads 0.24-0.29 (under a
    lattice's 0.3), with leaves whose gradients lean off the rows. Before, the faint rows gave
    a chance lattice of 60-130 px, and stronger ones a period leaning 6 degrees (the photo's
    gradients); the rows' own correlation sets the direction now."""
    for rows, lean in ((0.02, 0.3), (0.04, 0.5)):
        grain, found = photo_structure(crop_rows(rows=rows, lean=lean))
        assert grain is None and found is not None, (rows, lean)
        ax, ay, bx, by = found
        assert abs(ax - 10.16) < 0.15 and abs(np.degrees(np.arctan2(ay, ax))) < 0.5, found
        assert (bx, by) == pytest.approx((-ay, ax))


def test_rows_that_wave_are_found_in_their_profile_where_stripes_are_not(skimage_textures):
    """0ad's temp_farmland: rows of crops 9.1 px apart whose 2D correlation fades within a few
    rows (they wave and break), too few for the stripes; averaged along the rows they repeat.
    Its 70-s fit without them was isotropic speckle (10.8x the photo's floor), on them 1.7x. A
    profile one degree off smears a period over 256 px, so the direction comes from the
    correlation."""
    image = even_lighting(wavy_rows())
    assert detect_lattice(image) is None and detect_stripes(image) is None and detect_grain(image) is None
    ax, ay, bx, by = detect_rows(image)
    assert abs(abs(ax) - 9.1) < 0.15 and abs(np.degrees(np.arctan2(ay, abs(ax)))) < 0.5, (ax, ay)
    assert (bx, by) == pytest.approx((-ay, ax))                    # along the rows
    assert photo_structure(wavy_rows()) == (None, pytest.approx((ax, ay, bx, by)))
    ax, ay, _, _ = detect_rows(image.transpose(1, 0, 2))          # rows left-right: the period runs down
    assert abs(ax) < 0.2 and abs(abs(ay) - 9.1) < 0.15, (ax, ay)
    straight = even_lighting(wavy_rows(wave=0.0))                  # rows that hold are stripes already
    assert detect_stripes(straight) is not None
    for name in ("gravel", "grass", "brick"):                      # stochastic, or grain without a period
        assert detect_rows(skimage_textures[name]) is None, name
    assert detect_rows(streaks()) is None                          # one piece of wood: no rows
    assert detect_rows(np.full((64, 64, 3), 0.5)) is None


@pytest.mark.parametrize("seed", [8, 9])
def test_slabs_of_several_sizes_on_one_module_are_a_module_grid(seed, skimage_textures):
    """A pavement of 1 x 1 to 4 x 4 slabs on a 16-px module: joints run along some module lines
    only, so no 2D lattice, and both ways, so no stripes or rows; the luminance averaged along x
    and along y each repeat at the module. Nothing else is found before it."""
    photo = module_pavement(seed=seed)
    evened = even_lighting(photo)
    assert detect_lattice(evened) is None and detect_stripes(evened) is None and detect_rows(evened) is None
    ax, ay, bx, by = detect_module_grid(evened)
    assert abs(ax - 16) < 0.1 and abs(by - 16) < 0.1 and ay == bx == 0, (ax, by)
    assert photo_structure(photo) == (None, (ax, ay, bx, by))
    for name in ("gravel", "grass"):
        assert detect_module_grid(skimage_textures[name]) is None, name
    assert detect_module_grid(np.full((64, 64, 3), 0.5)) is None


@pytest.mark.parametrize("blend, found", [(0.0, True), (0.3, True), (0.5, False)])
def test_a_photo_of_two_by_two_copies_is_a_lattice_of_half_of_it(blend, found):
    """Game terrains made of 2 x 2 copies of one tile repeat at exactly half the photo, as far
    as the correlation reaches: such a lattice was never supported (its points were counted
    only under half the photo). Found when the copies repeat strongly (0.83 with 30% own
    noise); copies half their own (0.47) are too often chance for two repeats in view."""
    result = photo_structure(two_by_two(blend=blend))[1]
    assert (result is not None) == found, result
    if found:
        assert same_lattice(result, (128.0, 0.0, 0.0, 128.0), tolerance=0.01), result


def test_detect_boards_measures_the_board_width_across_the_grain(skimage_textures):
    """Boards repeat across their grain, which the photo's autocorrelation hides under the
    grain's streaks (no lattice; the stripe detector reads 9.3-px boards as 28-px stripes,
    three boards, and is not asked on a grain photo); averaged along the grain the joints
    show. The width comes to a fraction of a pixel, also where it falls between two pixels
    (whose peaks split), and the board is the shortest repeat, not two boards."""
    for width in (9.3, 12.5, 25.6):
        image = boards(width)
        assert detect_grain(image) == "y" and detect_lattice(image) is None
        ax, ay, bx, by = detect_boards(image, "y")
        assert abs(ax - width) < 0.1 and ay == 0 and (bx, by) == pytest.approx((0.0, ax)), (width, ax)
        assert photo_structure(image) == ("y", detect_boards(even_lighting(image), "y"))  # grain and boards, not stripes
    ax, ay, bx, by = detect_boards(boards().transpose(1, 0, 2), "x")  # boards left-right
    assert ax == 0 and abs(ay - 25.6) < 0.1 and (bx, by) == pytest.approx((-ay, 0.0))
    for seed in (5, 6):  # widths 16 px +- 10%: under BOARD_PEAK after two boards; their mean width
        uneven = even_lighting(boards(16.0, seed=seed, uneven=0.1))
        assert detect_lattice(uneven) is None
        ax, ay, _, _ = detect_boards(uneven, "y")
        assert abs(ax - 16.0) < 0.5 and ay == 0, (seed, ax)
    assert detect_boards(boards(), "x") is None                     # along the grain: no joints
    assert detect_boards(streaks(), "y") is None                    # one piece of wood
    assert detect_boards(skimage_textures["brick"], "y") is None     # grain without a period
    assert detect_boards(np.full((64, 64, 3), 0.5), "y") is None
    with pytest.raises(ValueError, match="grain"):
        detect_boards(boards(), None)


def test_wide_boards_and_ripples_repeat_once_within_a_third_of_the_photo():
    """Ripples over a sixth of the photo apart repeat too seldom for the board rules (two
    multiples within a third), but swing from crest to trough and back: read as stripes
    across the grain, to within the wave they bend by (a fifth of a period), in its place. A wood's broad bands, which do not swing back, a period in view under four times (a
    close-up's band) and fibres stay boards-free; so does a rug, whose far lattice is found
    first."""
    for period in (48.0, 56.0):
        for seed in (0, 1):
            photo = ripples(period, seed=seed)
            image = even_lighting(photo)
            assert detect_grain(image) == "x" and detect_boards(image, "x") is None
            ax, ay, bx, by = detect_wide_boards(image, "x")
            assert ax == 0 and abs(ay - period) < 0.1 * period and (bx, by) == pytest.approx((-ay, 0.0)), (period, ay)
            assert photo_structure(photo) == (None, (ax, ay, bx, by))
            assert photo_structure(photo, grain="x") == ("x", (ax, ay, bx, by))  # a grain asked for is kept
            assert detect_wide_boards(image, "y") is None  # along the ripples: no repeat
    assert detect_wide_boards(even_lighting(ripples(90.0)), "x") is None  # in view under four times
    assert detect_wide_boards(streaks(), "y") is None
    assert detect_wide_boards(even_lighting(fibres(40, 4)), "y") is None
    grain, found = photo_structure(banded_motifs(weave=0.08))
    assert grain is None and same_lattice(found, (60.0, 0.0, 0.0, 110.0), tolerance=0.01)


def test_leaning_ripples_are_stripes_along_their_lean():
    """Ripples whose crests lean 10-12 degrees, found down the photo, run their stripes
    along the lean, as far apart as the crests: upright stripes cross every crest at that
    angle (the savanna dunes, 11 degrees: 3.8x their floor upright, 2.5x along the lean).
    (Straight leaning crests often smear the upright profile: those are found on the
    photo turned by its grain's lean, ``model.fit.detect_structure``.)"""
    for lean in (-12.0, -10.0, 10.0, 12.0):
        ax, ay, bx, by = detect_wide_boards(even_lighting(ripples(48.0, lean=lean)), "x")
        assert abs(np.degrees(np.arctan2(-ax, ay)) - lean) < 2.0, (lean, ax, ay)
        assert abs(np.hypot(ax, ay) - 48.0) < 0.1 * 48.0 and (bx, by) == pytest.approx((-ay, ax))


def test_photo_structure_decides_what_a_fit_builds_in(skimage_textures):
    """Lattice first, then stripes, then grain; boards only on a photo with grain, and they
    keep it (rows on one without); "auto" detects, None turns a part off, an explicit grain is
    kept as given."""
    bond, board, plain = running_bond(), corrugation(), boards()
    grain, lattice = photo_structure(bond)
    evened = even_lighting(bond)  # what the detectors read
    assert grain is None and lattice == pytest.approx(fold_lattice(evened, detect_lattice(evened)))
    assert photo_structure(board) == (None, pytest.approx(detect_stripes(even_lighting(board))))
    assert photo_structure(plain) == ("y", pytest.approx(detect_boards(even_lighting(plain), "y")))
    assert photo_structure(streaks()) == ("y", None)                       # one piece of wood
    assert photo_structure(skimage_textures["gravel"]) == (None, None)
    assert photo_structure(plain, lattice=None) == ("y", None)             # grain alone
    grain, rows = photo_structure(plain, grain=None)                       # no grain: no boards, but their
    assert grain is None and abs(abs(rows[0]) - 25.6) < 0.2 and abs(rows[1]) < 0.5, rows  # repeat is rows
    assert photo_structure(bond, grain="x")[0] == "x"                      # asked for: kept
    assert photo_structure(board, grain=None, lattice=None) == (None, None)


@pytest.mark.parametrize("lean", [-12.0, 6.0, 12.0])
def test_grain_tilt_reads_a_lean_and_straighten_takes_it_out(lean):
    photo = streaks(angle_degrees=lean)
    assert detect_grain(photo) == "y"                       # still taken as grain along y
    assert grain_tilt(photo, "y") == pytest.approx(lean, abs=0.2)
    assert grain_tilt(photo.transpose(1, 0, 2), "x") == pytest.approx(-lean, abs=0.2)  # mirrored
    straight = straighten(photo, lean)
    assert grain_tilt(straight, "y") == pytest.approx(0.0, abs=0.2)
    c, s = np.cos(np.radians(lean)), np.sin(np.radians(abs(lean)))
    assert straight.shape == (int(256 / (c + s)),) * 2 + (3,)  # the largest square inside the turned photo
    assert np.abs(straighten(photo, 0.0) - photo).max() < 1e-5  # no turn: the photo itself


@pytest.mark.parametrize("lean, axis, turn", [(35.0, "y", 35.0), (-40.0, "y", -40.0), (60.0, "x", -30.0)])
def test_a_grain_leaning_past_the_axis_test_is_found_on_the_turned_photo(lean, axis, turn):
    """Streaks 30-60 degrees off both axes: the axis test finds no grain; the photo turned
    by its main orientation has one along the nearer axis, and the fit turns it by that."""
    photo = streaks(angle_degrees=lean)
    assert detect_grain(photo) is None
    assert leaning_grain(photo) == axis and photo_structure(photo) == (axis, None)
    assert grain_turn(photo, axis) == pytest.approx(turn, abs=0.3)
    assert detect_grain(straighten(photo, grain_turn(photo, axis))) == axis
    assert photo_structure(photo, grain=None) == (None, None)  # an isotropic fit asked for: none


def test_leaning_grain_finds_none_on_isotropic_or_upright_photos(skimage_textures):
    for name in ("grass", "gravel", "brick"):  # the brick's grain is upright: detect_grain's
        assert leaning_grain(skimage_textures[name]) is None, name
    assert leaning_grain(streaks()) is None and leaning_grain(np.full((64, 64, 3), 0.5)) is None


@pytest.mark.parametrize("lean", [6.0, 12.0])
def test_straighten_keeps_the_pixel_size(lean):
    """Each column of the straightened photo is the upright streaks' band at the same
    pixel pitch (one offset for all columns, to a tenth of a pixel); 5% larger or smaller
    pixels lose the match."""
    straight = straighten(streaks(angle_degrees=lean), lean).mean(axis=(0, 2))
    upright = streaks(size=512)[:, :, 0].mean(axis=0)
    width = len(straight)

    def match(pitch: float) -> float:
        return max(np.corrcoef(straight, np.interp(np.arange(width) * pitch + offset, np.arange(512.0), upright))[0, 1]
                   for offset in np.arange(0.0, 512 - 1.05 * width, 0.1))

    assert match(1.0) > 0.95
    assert match(1.05) < 0.8 and match(0.95) < 0.8


def test_detect_even_tells_gravel_from_a_photo_with_large_patches(skimage_textures):
    """Gravel at the working resolution is even at 32 px and larger (its 512-px original,
    pebbles twice the size, is not); the same gravel under a slow light-dark wave is not,
    nor is a flat photo (nothing varies)."""
    from worker.photo import resize_short_side

    assert not detect_even(skimage_textures["gravel"])
    gravel = resize_short_side(skimage_textures["gravel"], 256)
    assert detect_even(gravel)
    y = np.linspace(0, 2 * np.pi, gravel.shape[0])[:, None, None]
    assert not detect_even(np.clip(gravel * (0.7 + 0.3 * np.sin(y)), 0, 1))
    assert not detect_even(np.full((256, 256, 3), 0.5))


def leaning_blobs(degrees: float, along: float, across: float, size: int = 256, seed: int = 0) -> np.ndarray:
    """Noise low-passed by a Gaussian of ``along`` px along the direction ``degrees`` (from +x
    towards +y, y down the rows) and ``across`` px across it: blobs that lean and stretch."""
    spectrum = np.fft.fft2(np.random.default_rng(seed).standard_normal((size, size)))
    ky, kx = np.meshgrid(np.fft.fftfreq(size) * 2 * np.pi, np.fft.fftfreq(size) * 2 * np.pi, indexing="ij")
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    k_along, k_across = kx * c + ky * s, -kx * s + ky * c
    noise = np.fft.ifft2(spectrum * np.exp(-0.5 * ((along * k_along) ** 2 + (across * k_across) ** 2))).real
    return np.repeat(np.clip(0.5 + 0.15 * noise / noise.std(), 0, 1)[..., None], 3, axis=2)


@pytest.mark.parametrize("degrees", [-39.0, 20.0, 75.0])
def test_photo_lean_reads_where_blobs_run_and_how_much_longer_they_are(degrees):
    """Blobs 8 px long and 3 px across: photo_lean gives their direction and, through its
    own 2-px blur, a stretch of sqrt((64 + 4) / (9 + 4)) = 2.3 (a mild lean reads within a few
    degrees: one photo's blobs are a sample); blobs without a direction, a stretch near 1.
    Its angle is grain_tilt's."""
    photo = leaning_blobs(degrees, 8.0, 3.0)
    lean, stretch = photo_lean(photo)
    assert lean == pytest.approx(degrees, abs=2.0)
    assert stretch == pytest.approx(np.sqrt(68 / 13), rel=0.1)
    assert grain_tilt(photo, "x") == pytest.approx(lean, abs=0.1)
    assert photo_lean(leaning_blobs(0.0, 4.0, 4.0))[1] < 1.08


def as_jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` saved as a JPEG at ``quality`` and read back, as a phone delivers a photo."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.round(image * 255.0).astype(np.uint8)).save(buffer, "JPEG", quality=quality)
    return np.asarray(Image.open(buffer), np.float32) / 255.0


def turned_parquet_as_a_phone_takes_it() -> tuple[np.ndarray, tuple[float, float, float, float]]:
    photo, lattice = parquet(32, 4, turn_degrees=4.0, noise=0.03, seed=3)
    return as_jpeg(photo, 60), lattice


@pytest.mark.parametrize("make", [
    lambda: parquet(32, 4),                                   # 4 slats a block
    lambda: parquet(40, 4, seed=1),
    lambda: parquet(64, 8, seed=5),                           # four blocks across
    lambda: parquet(24, 2, joint=0.05, seed=2),               # basket weave: two slats, faint joints
    lambda: parquet(32, 4, noise=0.06, seed=7),               # grainy
    turned_parquet_as_a_phone_takes_it,                       # turned 4 degrees, noise, JPEG 60
], ids=["32px", "40px", "64px", "basket", "noisy", "turned-jpeg"])
def test_parquet_gets_the_lattice_of_its_blocks_directions(make):
    """Blocks of slats, up-down and left-right in a checkerboard, each slat its own tone:
    the luminance shows the slats' pitch, no block repeat (no lattice before
    ``detect_direction_lattice``); the direction of the streaks repeats on (n, n) and
    (n, -n) px for blocks of n px, and photo_structure finds that lattice within 5%."""
    photo, truth = make()
    evened = even_lighting(photo)
    assert detect_grain(evened) is None                       # as many slats run each way
    assert same_lattice(detect_direction_lattice(evened), truth, 0.05)
    grain, lattice = photo_structure(photo)
    assert grain is None and same_lattice(lattice, truth, 0.05), (lattice, truth)


def test_parquet_was_missed_by_the_luminance_lattice():
    """Why it needs the directions: the luminance correlation's strongest repeats are one
    slat across (8 px) both ways, whose grid no block repeats (support 0.2), and the
    blocks' checkerboard reads 0.42 there, under the slats."""
    photo = even_lighting(parquet(32, 4)[0])
    correlation, peaks = luminance_correlation(photo)
    strongest = max(peaks, key=lambda peak: peak[0])
    assert strongest[1] == pytest.approx(8.0)
    assert detect_lattice(photo) is None and detect_stripes(photo) is None


def test_wood_and_noise_get_no_direction_lattice(skimage_textures):
    """Grain all one way has no pattern of directions: a plank photo stand-in keeps its
    grain (and boards, a repeat across it only), wood without boards gets no lattice, also
    where its grain is not asked for; stochastic photos get none."""
    plain = boards()
    for wood in (plain, streaks(), fibres(40, 4)):
        assert detect_direction_lattice(even_lighting(wood)) is None
    assert photo_structure(plain) == ("y", pytest.approx(detect_boards(even_lighting(plain), "y")))
    assert photo_structure(streaks()) == ("y", None)
    assert photo_structure(streaks(), grain=None) == (None, None)
    noise = np.random.default_rng(0).uniform(0.0, 1.0, (256, 256, 3))
    blobs = fibres(4, 4)  # isotropic blotches
    for name, photo in (("white noise", noise), ("blobs", blobs), ("gravel", skimage_textures["gravel"]),
                        ("grass", skimage_textures["grass"])):
        assert detect_direction_lattice(even_lighting(photo)) is None, name
        assert photo_structure(photo)[1] is None, name
