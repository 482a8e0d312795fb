"""Product-level quality protocol: what a user gets from an upload, measured.

    make quality
    python -m eval.quality --model-dir model/weights [--model-dir DIR --label NAME ...] \
        --exemplars data/textures/val --out docs/eval/quality

Everything goes through the product path, never through torch models: the photo is
decoded by ``worker.images.read_image`` (sRGB 0..1), its texture code comes from
``encoder.onnx`` with its colour table, as an upload gets them (``encode_texture``, via
``texture_code``, the only place that knows), and every pixel comes from
``sampler.onnx`` through ``worker`` (ONNX Runtime). Torch only runs the VGG16 metric.

Per photo and model, at native zoom (zoom 6: one tile pixel = one exemplar pixel at the
model's working resolution, short side ``exemplar_short_side``):

* tiles: ``render_tile`` of tiles (x, y) in {0, 1}^2, 256 px, seeds 1 and 2 (8 tiles),
  linear RGB -> sRGB (``worker.colour.linear_to_srgb``);
* colour: CIELAB (skimage, D65) of the photo at working resolution vs the tiles: deltaE
  of the means (CIE76 and CIEDE2000) and per-channel Lab std ratio tile / photo, for
  all 8 tiles pooled and for the worst single tile (largest deltaE; for std, the ratio
  furthest from 1 per channel). Targets: deltaE76 < 5, std ratio in [0.7, 1.4]. Beside
  them, the photo's own: its 128^2 windows at 64-px steps against the whole photo, the same
  two figures (``own_crop_colour``): a photo uneven at that scale has tiles as uneven;
* fits (``--fits``): the same figures for each photo's fitted sampler (``model.fit``
  output), with its fitted code and a colour table computed for that sampler;
* style: VGG16 Gram error (``model.losses.gram_loss``, the fixed default layer weights,
  Gatys layers, target = Gram of the whole photo at working resolution, as
  ``model/evaluate.py``), mean over the 8 tiles, against a baseline at the same tile
  positions and seeds: 8-octave value noise (octave k has 2^k cells per world unit,
  amplitude 2^-k, smoothstep interpolation, random sub-cell offset per octave),
  colour-matched to the photo's per-channel sRGB mean and std. Two baselines are made,
  independent per channel (``rgb``) and luminance-only (``lum``: one noise scaled per
  channel); the one with the lower error on that photo is the baseline (the stronger
  one; its name is reported). Win: ours < baseline. Target: wins on >= 80% of photos;
* style over the photo's floor (``eval/style_floor.py``): the same Gram error on
  128^2 crops at the working size. The photo's floor: each of its four corner crops against
  the mean Gram of the other three, averaged. A synthesis's error: each quadrant of each of
  the 8 tiles against the mean Gram of the four corner crops, averaged. Ratio = error /
  floor (as good as more of the photo: ~1), for the tiles, for the value-noise baseline (the
  kind with the lower crop error) and for by-example noise (``eval/by_example.py``: Heitz
  and Neyret 2018, histogram-preserving blending of random patches of the photo on a
  triangle grid) at the same tile positions and seeds, and for the photo itself off its
  corner grid (8 crops at random offsets: what a perfect synthesis of a photo whose period
  divides the crop size can score, well above 1). Medians over photos are reported;
* diversity: VGG feature distance (``model.losses.feature_distance``) between the seed-1
  and seed-2 tile at each position, mean over positions. Target: > 0 on every photo;
* 3D: style error of 256 px slices on 3 axis-aligned planes (xy, xz, yz at random
  offsets, not the tile plane) and 3 oblique planes (``model.slices.fixed_planes``),
  seeds 1 and 2, pixel spacing 1 / pixels_per_unit, sampled by ``runtime.sampler.sample``.
  Reported: oblique / axis mean style error. Target: <= 1.5, pooled and on the worst photo.
  The worst-photo target leaves out fits on a repeat lattice or stripes (``pattern_2d``: the
  fit's manifest names a lattice): their solid is the photo's 2D pattern carried through
  depth, as a brick wall's or a tiled floor's is, so a cut across it shows the pattern's
  cross-section, stretched; no solid shows one 2D lattice on every plane. Their ratios are
  reported beside the target. Grain fits (wood) are anisotropic too but stay in it.

``--families N`` measures one photo from each of N families of a corpus with an index
(``index.json`` beside the exemplar folder, ``model/corpus.py``): the large corpus's
validation families, never trained on (``make quality-large``). ``--list`` prints the chosen
photos and stops (``make fits-large`` fits the same ones). ``--carry LABEL`` keeps a model's
rows from the results already in ``--out``, as they were measured: the GPU fits of ``make
quality`` cannot be remade on a CPU, and a fit's rows do not depend on the encoder, so a
change to the upload's code re-measures its own column beside them.

Writes ``results.json`` (settings, per-photo numbers, summary) and ``results.md``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from skimage.color import deltaE_ciede2000, rgb2lab

from model.data import INDEX_FILE
from model.losses import feature_distance, gram_loss, gram_matrices
from model.slices import fixed_planes
from model.vgg import GATYS_LAYERS
from worker.colour import linear_to_srgb
from worker.colour_match import calibrate_texture, texture_vector
from worker.encode import encode_texture
from worker.images import read_image
from worker.photo import crop_starts, resize_short_side
from worker.runtime import ModelRuntime, SamplerSession
from worker.tiles import NATIVE_ZOOM, render_tile

from eval.by_example import TRIANGLE_EDGE, by_example_tile, gaussianise
from eval.style_floor import CROP, crop_errors, off_grid_error, photo_floor, style_ratio, vgg_features

TILE = 256
POSITIONS = ((0, 0), (1, 0), (0, 1), (1, 1))  # tile (x, y) at native zoom
SEEDS = (1, 2)
OCTAVES = 8
SLICE_PLANES = 3  # per kind (axis, oblique)
PLANE_SEED = 0  # fixes the slice planes (as model/evaluate.py's default)
MAX_PIXELS = 1 << 26
TARGET_DELTA_E, TARGET_STD, TARGET_WINS, TARGET_OBLIQUE = 5.0, (0.7, 1.4), 0.8, 1.5


def texture_code(runtime: ModelRuntime, image: np.ndarray) -> np.ndarray:
    """What the product stores for a photo: z (8,) plus its colour table when there is one
    (a ``FittedRuntime`` brings its fitted code instead of the encoder's)."""
    code = getattr(runtime, "fitted_code", None)
    if code is None:  # an upload's own path (one resize for crops and colour table)
        return texture_vector(*encode_texture(runtime, image))
    working = resize_short_side(image, runtime.short_side)
    return texture_vector(code, calibrate_texture(runtime.sampler, code, working, curves="linear"))  # as a fit serves


class FittedRuntime:
    """A photo's fitted sampler (``model.fit`` output folder) in place of a model's encoder
    code and sampler, as a refined upload serves it: its own colour table is computed here."""

    def __init__(self, model: ModelRuntime, fit_dir: Path):
        self.sampler = SamplerSession(fit_dir / "sampler.onnx")
        self.fitted_code = np.asarray(json.loads((fit_dir / "code.json").read_text())["code"], np.float32)
        manifest = fit_dir / "manifest.json"  # a lattice (or stripes): a 2D pattern carried through depth
        self.pattern_2d = manifest.is_file() and bool(json.loads(manifest.read_text()).get("lattice"))
        self.short_side, self.pixels_per_unit = model.short_side, model.pixels_per_unit


def render_tiles(runtime: ModelRuntime, code: np.ndarray) -> np.ndarray:
    """Native-zoom tiles, sRGB: (len(SEEDS) * len(POSITIONS), TILE, TILE, 3) float32, seed-major."""
    return np.stack([linear_to_srgb(render_tile(runtime.sampler, code, seed, NATIVE_ZOOM, x, y, TILE,
                                                pixels_per_unit=runtime.pixels_per_unit))
                     for seed in SEEDS for x, y in POSITIONS])


def render_slices(runtime: ModelRuntime, code: np.ndarray, kind: str) -> np.ndarray:
    """256 px slices on ``fixed_planes(kind)``, sRGB: (len(SEEDS) * SLICE_PLANES, TILE, TILE, 3)."""
    origins, axes = (t.numpy() for t in fixed_planes(kind, SLICE_PLANES, PLANE_SEED))
    steps = (np.arange(TILE) + 0.5) / runtime.pixels_per_unit
    # point (i, j) = origin + step_j * u + step_i * v; (planes, rows, cols, 3) float64
    points = (origins[:, None, None] + steps[None, None, :, None] * axes[:, None, None, 0]
              + steps[None, :, None, None] * axes[:, None, None, 1])
    return np.stack([linear_to_srgb(runtime.sampler.sample(p.reshape(-1, 3), code, seed)).reshape(TILE, TILE, 3)
                     for seed in SEEDS for p in points])


def _interpolation_matrix(coords: np.ndarray, frequency: float, offset: float) -> np.ndarray:
    """(n, m) weights: row i blends the two lattice values around coords[i] * frequency + offset
    with smoothstep weights; column 0 is the lowest lattice index touched."""
    t = coords * frequency + offset
    cell = np.floor(t).astype(np.int64)
    f = t - cell
    w = f * f * (3.0 - 2.0 * f)
    cell -= cell.min()
    matrix = np.zeros((len(coords), cell.max() + 2))
    rows = np.arange(len(coords))
    matrix[rows, cell] = 1.0 - w
    matrix[rows, cell + 1] = w
    return matrix


def value_noise(height: int, width: int, pixels_per_unit: float, channels: int, seed: int,
                octaves: int = OCTAVES) -> np.ndarray:
    """Multi-octave value noise on pixels [0, width) x [0, height) of the native raster.

    Octave k has 2^k cells per world unit (pixel centre (i + 0.5) / pixels_per_unit),
    amplitude 2^-k, lattice values uniform in [0, 1), smoothstep interpolation, random
    sub-cell offset per octave and axis. Separable: octave = A_rows @ lattice @ A_cols^T.
    Returns (height, width, channels) float64 (unnormalised).
    """
    rng = np.random.default_rng(seed)
    rows, cols = ((np.arange(n) + 0.5) / pixels_per_unit for n in (height, width))
    out = np.zeros((height, width, channels))
    for k in range(octaves):
        a_rows = _interpolation_matrix(rows, 2.0**k, rng.random())
        a_cols = _interpolation_matrix(cols, 2.0**k, rng.random())
        lattice = rng.random((a_rows.shape[1], a_cols.shape[1], channels))
        out += 2.0**-k * np.einsum("ri,ijc,wj->rwc", a_rows, lattice, a_cols, optimize=True)
    return out


def colour_match(noise: np.ndarray, photo: np.ndarray) -> np.ndarray:
    """Noise (..., 1 or 3) -> sRGB (..., 3) float32 with the photo's per-channel mean and std
    (noise standardised over all its pixels; a 1-channel noise drives all three), clipped to 0..1."""
    flat = noise.reshape(-1, noise.shape[-1])
    standard = (noise - flat.mean(0)) / np.maximum(flat.std(0), 1e-12)
    pixels = photo.reshape(-1, 3)
    return np.clip(pixels.mean(0) + pixels.std(0) * standard, 0.0, 1.0).astype(np.float32)


def baseline_tiles(photo: np.ndarray, pixels_per_unit: float, kind: str) -> np.ndarray:
    """Colour-matched value noise at the tiles' positions and seeds, like ``render_tiles``."""
    span = TILE * (1 + max(max(p) for p in POSITIONS))
    tiles = []
    for seed in SEEDS:
        field = colour_match(value_noise(span, span, pixels_per_unit, 3 if kind == "rgb" else 1, seed), photo)
        tiles += [field[y * TILE:(y + 1) * TILE, x * TILE:(x + 1) * TILE] for x, y in POSITIONS]
    return np.stack(tiles)


def by_example_tiles(photo: np.ndarray) -> np.ndarray:
    """By-example noise of the photo (working size: one plane pixel per photo pixel) at the
    tiles' positions and seeds, like ``render_tiles``: (8, TILE, TILE, 3) float32 sRGB."""
    example = gaussianise(photo)  # once for all tiles
    return np.stack([by_example_tile(example, TILE, TILE, (x * TILE, y * TILE), seed)
                     for seed in SEEDS for x, y in POSITIONS])


def photo_baselines(photo: np.ndarray, pixels_per_unit: float, targets: dict[str, torch.Tensor]) -> dict:
    """What does not depend on the model, for a photo at one working size: the value-noise
    baselines' whole-photo style errors per kind, the photo's floor, and the crop errors of
    the value-noise kinds and of by-example noise."""
    floor = photo_floor(photo)
    whole, crop = {}, {}
    for kind in ("rgb", "lum"):
        tiles = baseline_tiles(photo, pixels_per_unit, kind)
        whole[kind] = float(style_errors(tiles, targets).mean())
        crop[f"value_noise_{kind}"] = float(crop_errors(tiles, floor).mean())
    crop["by_example"] = float(crop_errors(by_example_tiles(photo), floor).mean())
    crop["off_grid"] = off_grid_error(photo, floor)
    return {"whole": whole, "floor": floor, "crop": crop, "own_colour": own_crop_colour(photo)}


def floor_figures(ours_error: float, base: dict) -> dict:
    """One photo's style errors over its floor: the tiles', by-example noise's and the
    value-noise kind with the lower crop error (the stronger one)."""
    floor, crop = base["floor"], base["crop"]
    kind = min(("rgb", "lum"), key=lambda k: crop[f"value_noise_{k}"])
    return {"floor": floor.floor, "corner_errors": floor.corner_errors.tolist(),
            "error": ours_error, "ratio": style_ratio(ours_error, floor.floor),
            "by_example_error": crop["by_example"], "by_example_ratio": style_ratio(crop["by_example"], floor.floor),
            "value_noise_error": crop[f"value_noise_{kind}"], "value_noise_kind": kind,
            "value_noise_ratio": style_ratio(crop[f"value_noise_{kind}"], floor.floor),
            "off_grid_error": crop["off_grid"], "off_grid_ratio": style_ratio(crop["off_grid"], floor.floor)}


def style_errors(images: np.ndarray, targets: dict[str, torch.Tensor]) -> np.ndarray:
    """Gram error (default layer weights) of each image against the photo's Grams: (N,)."""
    with torch.no_grad():
        return gram_loss(vgg_features(images), targets, reduction="none").numpy()


def own_crop_colour(photo: np.ndarray) -> dict:
    """How far the photo's own ``CROP``-px windows (at half-crop steps, first and last flush
    with its borders) are from the whole photo: the largest deltaE76 of a window's mean Lab,
    and per channel the window's Lab std over the photo's furthest from 1. A photo that is not
    even at that scale (a lamp on a panel, a page of print) has windows far from its mean, and
    so may a tile that is the photo."""
    lab = rgb2lab(photo)
    height, width = lab.shape[:2]
    ys, xs = (crop_starts(n, CROP, 2 * (n // CROP) - 1) for n in (height, width))
    windows = np.stack([lab[y:y + CROP, x:x + CROP].reshape(-1, 3) for y in ys for x in xs])
    p_mean, p_std = lab.reshape(-1, 3).mean(0), lab.reshape(-1, 3).std(0)
    ratios = windows.std(1) / p_std
    return {"de76": float(np.linalg.norm(windows.mean(1) - p_mean, axis=1).max()),
            "std_ratio": ratios[np.abs(np.log(ratios)).argmax(0), [0, 1, 2]].tolist(), "windows": len(windows)}


def colour_figures(photo_lab: np.ndarray, tiles: np.ndarray) -> dict:
    """deltaE of mean Lab and Lab std ratios, pooled over tiles (N, H, W, 3) and worst tile."""
    lab = rgb2lab(tiles).reshape(len(tiles), -1, 3)
    p_mean, p_std = photo_lab.mean(0), photo_lab.std(0)
    t_mean, t_std = lab.mean(1), lab.std(1)  # (N, 3)
    pooled_mean, pooled_std = lab.reshape(-1, 3).mean(0), lab.reshape(-1, 3).std(0)
    de76 = np.linalg.norm(t_mean - p_mean, axis=1)
    de00 = deltaE_ciede2000(np.broadcast_to(p_mean, t_mean.shape), t_mean)
    ratios = t_std / p_std
    worst_ratio = ratios[np.abs(np.log(ratios)).argmax(0), [0, 1, 2]]
    return {"pooled": {"de76": float(np.linalg.norm(pooled_mean - p_mean)),
                       "de2000": float(deltaE_ciede2000(p_mean, pooled_mean)),
                       "std_ratio": (pooled_std / p_std).tolist()},
            "worst_tile": {"de76": float(de76.max()), "de2000": float(de00.max()), "std_ratio": worst_ratio.tolist()},
            "photo_lab_mean": p_mean.tolist(), "photo_lab_std": p_std.tolist(), "tiles_lab_mean": pooled_mean.tolist()}


def measure_photo(runtime: ModelRuntime, image: np.ndarray, baselines: dict) -> dict:
    """Every figure of one photo under one model (``baselines``: per-kind style errors, cached)."""
    photo = resize_short_side(image, runtime.short_side)
    with torch.no_grad():
        targets = gram_matrices(vgg_features(photo[None]))
    code = texture_code(runtime, image)
    tiles = render_tiles(runtime, code)
    features = vgg_features(tiles)
    with torch.no_grad():
        ours = gram_loss(features, targets, reduction="none").numpy()
        n = len(POSITIONS)
        diversity = feature_distance({k: v[:n] for k, v in features.items()},
                                     {k: v[n:] for k, v in features.items()}).numpy()
    key = (runtime.short_side, runtime.pixels_per_unit)
    if key not in baselines:  # the baselines and the floor depend on the working resolution only
        baselines[key] = photo_baselines(photo, runtime.pixels_per_unit, targets)
    base = baselines[key]["whole"]
    kind = min(base, key=base.get)
    floor = floor_figures(float(crop_errors(tiles, baselines[key]["floor"]).mean()), baselines[key])
    axis = style_errors(render_slices(runtime, code, "axis"), targets)
    oblique = style_errors(render_slices(runtime, code, "oblique"), targets)
    return {"colour": colour_figures(rgb2lab(photo).reshape(-1, 3), tiles) | {"photo_crops": baselines[key]["own_colour"]},
            "style": {"ours": float(ours.mean()), "ours_worst_tile": float(ours.max()),
                      "baseline": base[kind], "baseline_kind": kind, "baseline_rgb": base["rgb"],
                      "baseline_lum": base["lum"], "win": bool(ours.mean() < base[kind])},
            "style_floor": floor,
            "diversity": float(diversity.mean()), "diversity_min": float(diversity.min()),
            "style_axis": float(axis.mean()), "style_oblique": float(oblique.mean()),
            "oblique_over_axis": float(oblique.mean() / axis.mean()), "code_length": int(code.size),
            "pattern_2d": bool(getattr(runtime, "pattern_2d", False))}


def median_ratio(rows: list[dict], field: str) -> float | None:
    """Median over photos of ``style_floor[field]`` (photos without one left out), or None."""
    values = [r["style_floor"][field] for r in rows if r.get("style_floor", {}).get(field) is not None]
    return float(np.median(values)) if values else None


def summarise(rows: list[dict]) -> dict:
    """Worst cases over photos and pass / fail against the targets, for one model."""
    ratios = np.array([[r["colour"][w]["std_ratio"] for w in ("pooled", "worst_tile")] for r in rows])  # (P, 2, 3)
    wins = sum(r["style"]["win"] for r in rows)
    # the target is for solids that are not a 2D pattern carried through depth (a lattice or stripes fit:
    # its oblique cuts shear the pattern, as a cut through a brick wall would); those are listed apart
    solids = [r for r in rows if not r.get("pattern_2d")] or rows
    oblique = np.mean([r["style_oblique"] for r in solids]) / np.mean([r["style_axis"] for r in solids])
    worst_tile = max(rows, key=lambda r: r["colour"]["worst_tile"]["de76"])
    summary = {
        "max_de76_pooled": max(r["colour"]["pooled"]["de76"] for r in rows),
        "max_de76_worst_tile": worst_tile["colour"]["worst_tile"]["de76"],
        # that tile's photo: how far its own windows are from its mean (None before this figure)
        "max_de76_worst_tile_photo_crops": worst_tile["colour"].get("photo_crops", {}).get("de76"),
        "max_de2000_pooled": max(r["colour"]["pooled"]["de2000"] for r in rows),
        "std_ratio_range_pooled": [ratios[:, 0].min(0).tolist(), ratios[:, 0].max(0).tolist()],
        "std_ratio_range_worst_tile": [ratios[:, 1].min(0).tolist(), ratios[:, 1].max(0).tolist()],
        "wins": [wins, len(rows)], "min_diversity": min(r["diversity_min"] for r in rows),
        "oblique_over_axis": float(oblique), "max_oblique_over_axis": max(r["oblique_over_axis"] for r in rows),
        # the worst photo's target: solids that are not a 2D pattern carried through depth
        "max_oblique_over_axis_solid": max((r["oblique_over_axis"] for r in rows if not r.get("pattern_2d")),
                                           default=None),
        "oblique_over_axis_pattern_2d": sorted(r["oblique_over_axis"] for r in rows if r.get("pattern_2d")),
        "mean_style": float(np.mean([r["style"]["ours"] for r in rows])),
        # style error over the photo's floor (a ratio comparable across photos): medians over photos; by-example and
        # value noise are the model's own baselines (the same for models of one working size)
        "median_floor_ratio": median_ratio(rows, "ratio"),
        "median_floor_ratio_by_example": median_ratio(rows, "by_example_ratio"),
        "median_floor_ratio_value_noise": median_ratio(rows, "value_noise_ratio"),
        "median_floor_ratio_off_grid": median_ratio(rows, "off_grid_ratio"),
        "floor_ratio_below_by_example": [sum(r["style_floor"]["error"] < r["style_floor"]["by_example_error"]
                                             for r in rows if "style_floor" in r),
                                         sum("style_floor" in r for r in rows)],
    }
    worst_solid = summary["max_oblique_over_axis_solid"]
    low, high = TARGET_STD
    summary["pass"] = {
        "de76_pooled": summary["max_de76_pooled"] < TARGET_DELTA_E,
        "de76_worst_tile": summary["max_de76_worst_tile"] < TARGET_DELTA_E,
        "std_ratio_pooled": bool(((ratios[:, 0] >= low) & (ratios[:, 0] <= high)).all()),
        "std_ratio_worst_tile": bool(((ratios[:, 1] >= low) & (ratios[:, 1] <= high)).all()),
        "wins": wins >= TARGET_WINS * len(rows), "diversity": summary["min_diversity"] > 0,
        "oblique_over_axis": summary["oblique_over_axis"] <= TARGET_OBLIQUE,
        "oblique_over_axis_worst_photo": worst_solid is None or worst_solid <= TARGET_OBLIQUE,
    }
    return summary


def worst_photo(summary: dict) -> str:
    worst = summary.get("max_oblique_over_axis_solid", summary["max_oblique_over_axis"])
    return "no photo without a 2D pattern" if worst is None else f"worst photo {worst:.2f}"


def own_crops(summary: dict) -> str:
    """The worst tile's photo: its own crops' largest deltaE76 from its mean, when measured."""
    own = summary.get("max_de76_worst_tile_photo_crops")
    return "" if own is None else f" (its photo's crops {own:.2f})"


def pattern_note(summary: dict) -> str:
    """The ratios of fits on a lattice or stripes, which the worst-photo target leaves out."""
    ratios = summary.get("oblique_over_axis_pattern_2d") or []
    return f"; lattice and stripe fits {', '.join(f'{v:.2f}' for v in ratios)}" if ratios else ""


def floor_table(report: dict) -> list[str]:
    """Markdown lines: style error over each photo's floor, one column per model (the
    fit's empty when no --fits was given), by-example and value noise, and the medians."""
    models = report["models"]
    if not any("style_floor" in r for entry in models.values() for r in entry["photos"].values()):
        return []
    encoders = [label for label, entry in models.items() if entry.get("step") != "fit"]
    fits = [label for label, entry in models.items() if entry.get("step") == "fit"]
    columns = encoders + (fits or [None])  # None: the fit column, left empty
    first = models[encoders[0]]  # its baselines (at its working size) fill the baseline columns
    fmt = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    bold = lambda v: "" if v is None else f"**{v:.2f}**"  # noqa: E731 (a report from before a figure: empty)
    lines = ["", "## Style error over the photo's own floor", "",
             f"VGG Gram error of {CROP}^2 crops at the working size, divided by the photo's floor: its four "
             f"corner crops, each against the mean Gram of the other three (mean of the four). Syntheses: the "
             f"quadrants of the 8 tiles, each against the mean Gram of the four corners. ~1: as close to the "
             f"photo as more of the photo is. By-example: Heitz and Neyret 2018 (eval/by_example.py, triangle "
             f"edge {TRIANGLE_EDGE:g} px); value noise: the kind with the lower crop error. Photo off grid: "
             f"the photo's own crops at 8 random offsets, scored as a synthesis (well above 1 where the "
             f"photo repeats with a period dividing the crop size: its corners agree at one phase)."
             + ("" if fits else " Fit: no --fits given, left empty."), "",
             "| photo | floor | " + " | ".join(f"{c} / floor" if c else "fit / floor" for c in columns)
             + " | by-example / floor | value noise / floor (kind) | photo off grid / floor |",
             "|---" * (len(columns) + 5) + "|"]
    for photo, row in first["photos"].items():
        base = row.get("style_floor")
        if base is None:
            continue
        cells = [fmt(models[c]["photos"].get(photo, {}).get("style_floor", {}).get("ratio")) if c else ""
                 for c in columns]
        lines.append(f"| {photo} | {base['floor']:.4f} | " + " | ".join(cells) + f" | {fmt(base['by_example_ratio'])} "
                     f"| {fmt(base['value_noise_ratio'])} ({base['value_noise_kind']}) "
                     f"| {fmt(base.get('off_grid_ratio'))} |")
    medians = [fmt(models[c]["summary"].get("median_floor_ratio")) if c else "" for c in columns]
    s = first["summary"]
    lines.append("| **median** | | " + " | ".join(f"**{m}**" if m else "" for m in medians)
                 + f" | **{fmt(s.get('median_floor_ratio_by_example'))}** "
                   f"| **{fmt(s.get('median_floor_ratio_value_noise'))}** "
                   f"| {bold(s.get('median_floor_ratio_off_grid'))} |")
    return lines


def to_markdown(report: dict) -> str:
    """Summary table (one row per model), the style error over each photo's floor, then one
    per-photo table per model."""
    f3 = lambda values: "/".join(f"{v:.2f}" for v in values)  # noqa: E731
    mark = lambda ok: "" if ok else " **x**"  # noqa: E731
    lines = ["# Product quality", "", "Through encoder.onnx + sampler.onnx (worker/). Colour: CIELAB of the "
             "photo vs native-zoom tiles (x, y in {0,1}, seeds 1, 2). Std ratio: tile / photo, L/a/b. Style: VGG Gram "
             "error, ours vs the stronger colour-matched value-noise baseline. Targets: dE76 < 5, std ratio in "
             "[0.7, 1.4], wins >= 80%, diversity > 0, oblique / axis <= 1.5 (pooled over the photos and for "
             "the worst photo, both leaving out fits on a lattice or stripes, a 2D pattern carried through depth: "
             "their ratios are listed beside). Beside the worst tile: how far its photo's own "
             f"{CROP}-px windows (at {CROP // 2}-px steps) are from the photo's mean colour (largest dE76), the "
             "photo's own unevenness. "
             "**x**: target missed.", "",
             "| model | max dE76 pooled | max dE76 worst tile | max dE2000 pooled | std ratio pooled min..max "
             "| std ratio worst tile min..max | wins | min diversity | oblique / axis | mean style |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for label, entry in report["models"].items():
        s, ok = entry["summary"], entry["summary"]["pass"]
        lines.append(
            f"| {label} | {s['max_de76_pooled']:.2f}{mark(ok['de76_pooled'])} | {s['max_de76_worst_tile']:.2f}"
            f"{mark(ok['de76_worst_tile'])}{own_crops(s)} | {s['max_de2000_pooled']:.2f} | {f3(s['std_ratio_range_pooled'][0])} .. "
            f"{f3(s['std_ratio_range_pooled'][1])}{mark(ok['std_ratio_pooled'])} | "
            f"{f3(s['std_ratio_range_worst_tile'][0])} .. {f3(s['std_ratio_range_worst_tile'][1])}"
            f"{mark(ok['std_ratio_worst_tile'])} | {s['wins'][0]}/{s['wins'][1]}{mark(ok['wins'])} | "
            f"{s['min_diversity']:.3f}{mark(ok['diversity'])} | {s['oblique_over_axis']:.2f}"
            f"{mark(ok['oblique_over_axis'])} ({worst_photo(s)}{mark(ok['oblique_over_axis_worst_photo'])}"
            f"{pattern_note(s)}) | {s['mean_style']:.3f} |")
    lines += floor_table(report)
    for label, entry in report["models"].items():
        carried = ", carried from an earlier run (--carry)" if entry.get("carried") else ""
        lines += ["", f"## {label} ({entry['model_dir']}, version {entry['version']}, step {entry['step']}{carried})", "",
                  "| photo | dE76 pooled | dE2000 pooled | dE76 worst tile | dE76 photo's crops | std ratio pooled "
                  "| std ratio worst tile | std ratio photo's crops | style ours | baseline (kind) | win | diversity "
                  "| oblique / axis |", "|---" * 13 + "|"]
        # (a ratio marked 2D: a fit on a lattice or stripes, left out of the worst-photo target)
        for photo, r in entry["photos"].items():
            c, st, own = r["colour"], r["style"], r["colour"].get("photo_crops")  # own: None in older reports
            own_de, own_std = (f"{own['de76']:.2f}", f3(own["std_ratio"])) if own else ("", "")
            lines.append(f"| {photo} | {c['pooled']['de76']:.2f} | {c['pooled']['de2000']:.2f} | "
                         f"{c['worst_tile']['de76']:.2f} | {own_de} | {f3(c['pooled']['std_ratio'])} | "
                         f"{f3(c['worst_tile']['std_ratio'])} | {own_std} | {st['ours']:.3f} | {st['baseline']:.3f} "
                         f"({st['baseline_kind']}) | {'yes' if st['win'] else 'no'} | {r['diversity']:.3f} | "
                         f"{r['oblique_over_axis']:.2f}{' (2D)' if r.get('pattern_2d') else ''} |")
    return "\n".join(lines) + "\n"


def one_per_family(exemplars: Path, families: int) -> list[Path]:
    """One photo (the first by name) from each of ``families`` families of ``exemplars``, by the
    corpus's ``index.json`` beside it: the families first by the sha256 of their names, a fixed
    spread over the sources that no choice of ours steers."""
    index = json.loads((exemplars.parent / INDEX_FILE).read_text())
    by_family: dict[str, list[str]] = {}
    for entry in index["exemplars"]:
        if Path(entry["path"]).parent.name == exemplars.name:
            by_family.setdefault(entry["family"], []).append(entry["path"])
    if families > len(by_family):
        raise ValueError(f"{exemplars} has {len(by_family)} families, not {families}")
    chosen = sorted(by_family, key=lambda family: hashlib.sha256(family.encode()).hexdigest())[:families]
    return sorted(exemplars.parent / min(by_family[family]) for family in chosen)


def carried_models(results: Path, labels: list[str], photos: list[str]) -> dict:
    """The models named in ``labels`` from an earlier ``results.json``, as measured then; each
    must hold rows of photos measured now (a table of other photos would not compare)."""
    if not labels:
        return {}
    if not results.is_file():
        raise SystemExit(f"--carry: no earlier results at {results}")
    models = json.loads(results.read_text())["models"]
    missing = [label for label in labels if label not in models]
    if missing:
        raise SystemExit(f"--carry: {results} holds no {', '.join(missing)} (it holds {', '.join(models)})")
    for label in labels:
        other = sorted(set(models[label]["photos"]) - set(photos))
        if other:
            raise SystemExit(f"--carry: {label} in {results} was measured on other photos ({', '.join(other[:3])})")
    return {label: models[label] | {"carried": True} for label in labels}


def with_photo_figures(carried: dict, measured: dict) -> dict:
    """Carried models' rows take their photo's own colour figures from a model measured now
    (they are the photo's, as its floor is, and measured as this code measures them), and
    their summary again."""
    own = {name: row["colour"]["photo_crops"] for entry in measured.values()
           for name, row in entry["photos"].items() if "photo_crops" in row["colour"]}
    for entry in carried.values():
        for name, row in entry["photos"].items():
            if name in own:
                row["colour"]["photo_crops"] = own[name]
        entry["summary"] = summarise(list(entry["photos"].values()))
    return carried


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model-dir", type=Path, action="append", required=True, help="exported model (repeatable)")
    parser.add_argument("--label", action="append", default=[], help="name of each --model-dir, in order")
    parser.add_argument("--exemplars", type=Path, default=Path("data/textures/val"))
    parser.add_argument("--out", type=Path, default=Path("docs/eval/quality"))
    parser.add_argument("--fits", type=Path, help="folder of model.fit outputs, one per photo (FITS/<photo stem>/), "
                                                 "fitted from the first --model-dir: measured as one more model")
    parser.add_argument("--families", type=int, help="one photo from each of this many families (the corpus's "
                                                     "index.json beside --exemplars; default: every photo)")
    parser.add_argument("--list", action="store_true", help="print the photos measured and stop")
    parser.add_argument("--carry", action="append", default=[], metavar="LABEL",
                        help="keep this model's rows from OUT/results.json as measured before (repeatable)")
    args = parser.parse_args(argv)
    if len(args.label) > len(args.model_dir):
        parser.error("more --label than --model-dir")
    labels = args.label + [d.name for d in args.model_dir[len(args.label):]]
    photos = (one_per_family(args.exemplars, args.families) if args.families else
              sorted(p for p in args.exemplars.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")))
    if not photos:
        parser.error(f"no photos in {args.exemplars}")
    if args.list:
        print("\n".join(str(p) for p in photos))
        return 0
    carried = carried_models(args.out / "results.json", args.carry, [p.stem for p in photos])
    torch.set_num_threads(2)
    images = {p.stem: read_image(p.read_bytes(), max_pixels=MAX_PIXELS) for p in photos}
    baselines: dict[str, dict] = {name: {} for name in images}
    report = {"settings": {"tile": TILE, "zoom": NATIVE_ZOOM, "positions": POSITIONS, "seeds": SEEDS,
                           "octaves": OCTAVES, "slice_planes": SLICE_PLANES, "plane_seed": PLANE_SEED,
                           "layers": GATYS_LAYERS, "exemplars": str(args.exemplars), "families": args.families,
                           "floor_crop": CROP, "by_example_triangle_edge": TRIANGLE_EDGE}, "models": {}}
    for label, model_dir in zip(labels, args.model_dir):
        runtime, start = ModelRuntime(model_dir), time.perf_counter()
        rows = {name: measure_photo(runtime, image, baselines[name]) for name, image in images.items()}
        report["models"][label] = {
            "model_dir": str(model_dir), "version": runtime.version,
            "step": runtime.manifest["training"].get("steps"), "seconds": round(time.perf_counter() - start, 1),
            "summary": summarise(list(rows.values())), "photos": rows}
        print(f"{label}: {len(rows)} photos in {report['models'][label]['seconds']} s", flush=True)
    if args.fits:
        model, start = ModelRuntime(args.model_dir[0]), time.perf_counter()
        rows = {name: measure_photo(FittedRuntime(model, args.fits / name), image, baselines[name])
                for name, image in images.items() if (args.fits / name / "sampler.onnx").is_file()}
        report["models"][f"{labels[0]}-fit"] = {
            "model_dir": str(args.fits), "version": "per photo", "step": "fit",
            "seconds": round(time.perf_counter() - start, 1), "summary": summarise(list(rows.values())), "photos": rows}
    report["models"] |= with_photo_figures(carried, report["models"])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(report, indent=2) + "\n")
    markdown = to_markdown(report)
    (args.out / "results.md").write_text(markdown)
    print(markdown + f"\nwrote {args.out}/results.json, results.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
