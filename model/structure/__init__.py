"""What regular structure a photo has, for a fit to build in: grain, a repeat lattice,
stripes, boards. Functions over (H, W, 3) RGB arrays in [0, 1] at the working resolution;
lattices are two basis vectors (ax, ay, bx, by) in pixels, x right, y down.

    grain, lattice_px = photo_structure(photo)   # what model.fit builds in by default

``photo_structure`` (here) asks the detectors in turn; each module holds one kind:

* ``lattices``: a 2D repeat (``detect_lattice``: bricks, tile grids, perforated metal),
  refined by least squares, then moved to where the photo folds sharpest (``fold_lattice``);
  a far one (``detect_long_lattice``: a rug's bands), large cells (``detect_large_cells``),
  and the lattice of the direction streaks run in (``detect_direction_lattice``: parquet);
* ``stripes``: a repeat along one direction only (``detect_stripes``: corrugated board),
  boards across a grain (``detect_boards``, ``detect_wide_boards``: plank floors, ripples),
  stripes seen only in their profile (``detect_rows``: crop rows), slabs of several sizes on
  one module (``detect_module_grid``: a pavement);
* ``grain``: streaks along image x or y (``detect_grain``: wood, brushed metal), their
  stretch and lean, the photo's lean (``photo_lean``), and evenness at large scales
  (``detect_even``: gravel, asphalt);
* ``correlation``: the luminance autocorrelation and its peaks, which lattices and stripes read.
"""
from __future__ import annotations

import numpy as np

from model.structure.correlation import same_lattice
from model.structure.grain import (EVEN_BLOCK, GRAIN_STRETCH, STRONG_GRAIN_STRETCH, detect_even, detect_grain,
                                   grain_stretch, grain_tilt, grain_turn, leaning_grain, photo_lean, straighten,
                                   turn_lattice)
from model.structure.lattices import (detect_direction_lattice, detect_large_cells, detect_lattice,
                                      detect_long_lattice, fold_lattice)
from model.structure.stripes import (detect_boards, detect_module_grid, detect_rows, detect_stripes,
                                     detect_wide_boards)
from worker.colour import even_lighting

__all__ = ["EVEN_BLOCK", "GRAIN_STRETCH", "STRONG_GRAIN_STRETCH", "detect_boards", "detect_direction_lattice",
           "detect_even", "detect_grain", "detect_large_cells", "detect_lattice", "detect_long_lattice",
           "detect_module_grid", "detect_rows", "detect_stripes", "detect_wide_boards", "fold_lattice",
           "grain_stretch", "grain_tilt", "grain_turn", "leaning_grain", "photo_lean", "photo_structure",
           "same_lattice", "straighten", "turn_lattice"]


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
    (``detect_large_cells``); a module grid (``detect_module_grid``: slabs of several
    sizes). Boards come before stripes on a grain photo: its boards' joints are stripes too,
    and the stripe detector reads their repeat at any multiple (9.3-px synthetic boards: 28
    px, three boards) and would drop the grain. ``grain`` "x" / "y" / None and ``lattice``
    None are taken as given. A photo with a lattice or stripes gets no grain.

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
