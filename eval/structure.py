"""What ``model.structure.photo_structure`` finds, on the packaged photos and on photos cut
and turned from them as a user might take them: the reference to diff after a change to a
detector (docs/DECISIONS.md's structure figures come from it).

    make structure
    python -m eval.structure --out docs/eval/structure

Every photo is read as a fit reads it (``model.data.load_exemplar``: short side 256,
unquantised). Cut-outs are taken from the photo at that size, rounded to 8 bits (as a saved
PNG) and read back at short side 256, so their repeats come out larger by 256 / side:

* **packaged**: the 41 photos of ``data/textures`` (train and val), each as it is;
* **crops**: each validation photo cut to 100-230 px squares at offsets 0 and 37;
* **turns**: the validation brick wall turned by -15..15 degrees (``straighten``: the largest
  centred square inside the turned photo); right when it finds the lattice of the photo as
  it is, turned the same way, to 0.08 of a step (a turned photo is measured on fewer bricks);
* **degraded**: every packaged photo as a phone might deliver it: JPEG at quality 60,
  Gaussian noise (sigma 0.02, 0.04), a 1-px blur, a vignette (corners 30% darker), light
  falling off across it (0.8x to 1.2x left to right), taken at 160 px and enlarged; each
  counts as kept when it finds the clean photo's grain and the same lattice (to a twentieth
  of a step);
* **close-ups**: the two validation photos of 64-px tiles (floor tiles, concrete) cut to
  128-180 px at offsets 0, 20 and 37, so 2 to 2.8 tiles across; the true lattice is the
  square of 64 x 256 / side px, and a found lattice is right when it is the same lattice to
  a twentieth of a step (``same_lattice``);
* **hexagonal tiles** (synthetic, ``eval/synthetic_photos.py``): 9-45 px from centre to corner,
  turned 0, 7, 15 and 30 degrees, right to a twentieth of a step.

Writes ``results.json`` (every photo's grain and lattice in px) and ``results.md``.
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from model.data import load_exemplar
from model.structure import photo_structure, same_lattice, straighten
from worker.decode import read_image
from worker.photo import resize_short_side

from eval.synthetic_photos import hexagonal_tiles  # the synthetic tilings the tests use too

SHORT_SIDE = 256
CROP_SIDES, CROP_OFFSETS = (100, 128, 160, 200, 230), (0, 37)
TURNS = tuple(float(d) for d in range(-15, 16) if d)
TURNED, TURN_RIGHT_TO = "miniworld_brick_wall_1", 0.08
HEX_RADII, HEX_TURNS = (9, 11, 13, 15, 17, 20, 23, 26, 30, 35, 40, 45), (0.0, 7.0, 15.0, 30.0)
CLOSE_UP_PHOTOS, TILE_PX = ("miniworld_floor_tiles_white", "miniworld_concrete_3"), 64.0
CLOSE_UP_SIDES, CLOSE_UP_OFFSETS = (128, 132, 136, 140, 144, 160, 180), (0, 20, 37)
RIGHT_TO = 0.05  # of a step (same_lattice's tolerance)


def as_jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    buffer = io.BytesIO()
    Image.fromarray(np.round(image * 255.0).astype(np.uint8)).save(buffer, "JPEG", quality=quality)
    return resize_short_side(read_image(buffer.getvalue(), max_pixels=1 << 24), SHORT_SIDE)


def with_noise(image: np.ndarray, sigma: float) -> np.ndarray:
    return np.clip(image + np.random.default_rng(0).normal(0.0, sigma, image.shape), 0, 1).astype(np.float32)


def shaded(image: np.ndarray, vignette: float = 0.0, falloff: float = 0.0) -> np.ndarray:
    """``image`` times a vignette (corners 1 - vignette) and a left-to-right ramp (1 -+ falloff)."""
    height, width = image.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    radius2 = ((x - width / 2) ** 2 + (y - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    light = (1 - vignette * radius2) * (1 + falloff * (2 * x / (width - 1) - 1))
    return np.clip(image * light[..., None], 0, 1).astype(np.float32)


DEGRADED = {
    "jpeg 60": lambda image: as_jpeg(image, 60),
    "noise 0.02": lambda image: with_noise(image, 0.02),
    "noise 0.04": lambda image: with_noise(image, 0.04),
    "blur 1 px": lambda image: ndimage.gaussian_filter(image, (1.0, 1.0, 0.0)),
    "vignette 30%": lambda image: shaded(image, vignette=0.3),
    "falloff 20%": lambda image: shaded(image, falloff=0.2),
    "160 px": lambda image: resize_short_side(resize_short_side(image, 160), SHORT_SIDE),
}


def read_back(image: np.ndarray) -> np.ndarray:
    """A cut-out as a fit reads it once saved: 8 bits, then resized to SHORT_SIDE."""
    return resize_short_side(np.round(image * 255.0).astype(np.float32) / 255.0, SHORT_SIDE)


def structure_row(name: str, photo: np.ndarray, truth: tuple | None = None, right_to: float = RIGHT_TO) -> dict:
    grain, lattice = photo_structure(photo)
    row = {"photo": name, "grain": grain, "lattice_px": [round(v, 2) for v in lattice] if lattice else None}
    if truth is not None:
        row["truth_px"] = [round(float(v), 2) for v in truth]
        row["right"] = bool(lattice is not None and same_lattice(lattice, truth, right_to))
    return row


def turned_lattice(lattice: tuple, degrees: float) -> tuple:
    """``lattice`` (px) as it lies in the photo turned by ``straighten(photo, degrees)``."""
    turn = np.radians(-degrees)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    return tuple(float(v) for v in (np.asarray(lattice, np.float64).reshape(2, 2) @ rotation.T).ravel())


def measure(data: Path) -> dict[str, list[dict]]:
    photos = {p.stem: load_exemplar(p, SHORT_SIDE, quantise=False) for p in sorted(data.glob("*/*.png"))}
    validation = sorted(p.stem for p in (data / "val").glob("*.png"))
    rows = {"packaged": [structure_row(name, photo) for name, photo in photos.items()], "crops": [], "turns": [],
            "degraded": [], "close-ups": [], "hexagonal tiles": []}
    for clean in rows["packaged"]:
        truth = tuple(clean["lattice_px"]) if clean["lattice_px"] else None
        for how, degrade in DEGRADED.items():
            row = structure_row(f"{clean['photo']}, {how}", degrade(photos[clean["photo"]]))
            row["right"] = row["grain"] == clean["grain"] and (
                row["lattice_px"] is None if truth is None
                else row["lattice_px"] is not None and same_lattice(row["lattice_px"], truth, RIGHT_TO))
            rows["degraded"].append(row)
    for name in validation:
        for side in CROP_SIDES:
            for offset in CROP_OFFSETS:
                cut = photos[name][offset:offset + side, offset:offset + side]
                rows["crops"].append(structure_row(f"{name} {side} px at {offset}", read_back(cut)))
    upright = next(r["lattice_px"] for r in rows["packaged"] if r["photo"] == TURNED)
    for degrees in TURNS:
        rows["turns"].append(structure_row(f"{TURNED} turned {degrees:g} deg", straighten(photos[TURNED], degrees),
                                           turned_lattice(upright, degrees), TURN_RIGHT_TO))
    for name in CLOSE_UP_PHOTOS:
        for side in CLOSE_UP_SIDES:
            tile = TILE_PX * SHORT_SIDE / side
            for offset in CLOSE_UP_OFFSETS:
                cut = photos[name][offset:offset + side, offset:offset + side]
                rows["close-ups"].append(structure_row(f"{name} {side} px at {offset} ({side / TILE_PX:.2f} tiles "
                                                       f"across)", read_back(cut), (tile, 0.0, 0.0, tile)))
    for radius in HEX_RADII:
        for degrees in HEX_TURNS:
            photo, truth = hexagonal_tiles(radius, degrees)
            rows["hexagonal tiles"].append(structure_row(f"{radius} px turned {degrees:g} deg", photo, truth))
    return rows


def to_markdown(rows: dict[str, list[dict]]) -> str:
    lines = ["# What model/structure/ finds", "",
             "`make structure` (eval/structure.py). Lattices in px at the working resolution (ax, ay, bx, by; x right, "
             "y down); close-ups, hexagonal tiles: right when the same lattice as the truth to a twentieth of a step; turns: "
             "the upright photo's lattice turned, to 0.08 of a step.", ""]
    def right(section: str) -> str:
        return f"{sum(r['right'] for r in rows[section])} of {len(rows[section])}"

    lines += [f"Close-ups right: {right('close-ups')}. Degraded copies that find what the clean photo does: "
              f"{right('degraded')}. Turns right: {right('turns')}. Hexagonal tiles right: {right('hexagonal tiles')}.", ""]
    for section, found in rows.items():
        if section == "degraded":  # only the copies that differ from their clean photo
            found = [r for r in found if not r["right"]]
        truths = section in ("close-ups", "turns", "hexagonal tiles")
        lines += [f"## {section}" + (" (the copies that differ)" if section == "degraded" else ""), "",
                  "| photo | grain | lattice (px) |" + (" truth | right |" if truths else ""),
                  "|---|---|---|" + ("---|---|" if truths else "")]
        for r in found:
            lattice = ", ".join(f"{v:.1f}" for v in r["lattice_px"]) if r["lattice_px"] else "-"
            truth = f"{r['truth_px'][0]:.1f}" if section == "close-ups" else (  # (a square grid: its side)
                ", ".join(f"{v:.1f}" for v in r["truth_px"]) if truths else "")
            extra = f" {truth} | {'yes' if r['right'] else 'no'} |" if truths else ""
            lines.append(f"| {r['photo']} | {r['grain'] or '-'} | {lattice} |{extra}")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/textures"), help="folder with train/ and val/")
    parser.add_argument("--out", type=Path, default=Path("docs/eval/structure"))
    args = parser.parse_args(argv)
    if not (args.data / "val").is_dir():
        parser.error(f"no {args.data}/val: run make data")
    start = time.perf_counter()
    rows = measure(args.data)
    seconds = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    # one photo a line: the file diffs like the table
    sections = [f'"{section}": [\n' + ",\n".join(json.dumps(row) for row in found) + "\n]" for section, found in rows.items()]
    (args.out / "results.json").write_text("{\n" + ",\n".join(sections) + "\n}\n")
    (args.out / "results.md").write_text(to_markdown(rows))
    print(f"wrote {args.out}/results.json, results.md ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
