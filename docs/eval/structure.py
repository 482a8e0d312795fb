"""What ``model.structure.photo_structure`` finds, on the packaged photos and on photos cut
and turned from them as a user might take them: the reference the notes' structure figures
come from, to diff after a change to a detector.

    make structure
    python docs/eval/structure.py --out docs/eval/structure

Every photo is read as a fit reads it (``model.data.load_exemplar``: short side 256,
unquantised). Cut-outs are taken from the photo at that size, rounded to 8 bits (as a saved
PNG) and read back at short side 256, so their repeats come out larger by 256 / side:

* **packaged**: the 41 photos of ``data/textures`` (train and val), each as it is;
* **crops**: each validation photo cut to 100-230 px squares at offsets 0 and 37;
* **turns**: the validation brick wall turned by a few degrees (``straighten``: the largest
  centred square inside the turned photo);
* **close-ups**: the two validation photos of 64-px tiles (floor tiles, concrete) cut to
  128-180 px at offsets 0, 20 and 37, so 2 to 2.8 tiles across; the true lattice is the
  square of 64 x 256 / side px, and a found lattice is right when it is the same lattice to
  a twentieth of a step (``same_lattice``).

Writes ``results.json`` (every photo's grain and lattice in px) and ``results.md``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from model.data import load_exemplar
from model.structure import photo_structure, same_lattice, straighten
from worker.images import resize_short_side

SHORT_SIDE = 256
CROP_SIDES, CROP_OFFSETS = (100, 128, 160, 200, 230), (0, 37)
TURNS = (3.0, 5.0, 10.0, -7.0)
TURNED = "miniworld_brick_wall_1"
CLOSE_UP_PHOTOS, TILE_PX = ("miniworld_floor_tiles_white", "miniworld_concrete_3"), 64.0
CLOSE_UP_SIDES, CLOSE_UP_OFFSETS = (128, 132, 136, 140, 144, 160, 180), (0, 20, 37)
RIGHT_TO = 0.05  # of a step (same_lattice's tolerance)


def read_back(image: np.ndarray) -> np.ndarray:
    """A cut-out as a fit reads it once saved: 8 bits, then resized to SHORT_SIDE."""
    return resize_short_side(np.round(image * 255.0).astype(np.float32) / 255.0, SHORT_SIDE)


def structure_row(name: str, photo: np.ndarray, truth: tuple | None = None) -> dict:
    grain, lattice = photo_structure(photo)
    row = {"photo": name, "grain": grain, "lattice_px": [round(v, 2) for v in lattice] if lattice else None}
    if truth is not None:
        row["truth_px"] = list(truth)
        row["right"] = bool(lattice is not None and same_lattice(lattice, truth, RIGHT_TO))
    return row


def measure(data: Path) -> dict[str, list[dict]]:
    photos = {p.stem: load_exemplar(p, SHORT_SIDE, quantise=False) for p in sorted(data.glob("*/*.png"))}
    validation = sorted(p.stem for p in (data / "val").glob("*.png"))
    rows = {"packaged": [structure_row(name, photo) for name, photo in photos.items()], "crops": [], "turns": [],
            "close-ups": []}
    for name in validation:
        for side in CROP_SIDES:
            for offset in CROP_OFFSETS:
                cut = photos[name][offset:offset + side, offset:offset + side]
                rows["crops"].append(structure_row(f"{name} {side} px at {offset}", read_back(cut)))
    for degrees in TURNS:
        rows["turns"].append(structure_row(f"{TURNED} turned {degrees:g} deg", straighten(photos[TURNED], degrees)))
    for name in CLOSE_UP_PHOTOS:
        for side in CLOSE_UP_SIDES:
            tile = TILE_PX * SHORT_SIDE / side
            for offset in CLOSE_UP_OFFSETS:
                cut = photos[name][offset:offset + side, offset:offset + side]
                rows["close-ups"].append(structure_row(f"{name} {side} px at {offset} ({side / TILE_PX:.2f} tiles "
                                                       f"across)", read_back(cut), (tile, 0.0, 0.0, tile)))
    return rows


def to_markdown(rows: dict[str, list[dict]]) -> str:
    lines = ["# What model/structure.py finds", "",
             "`make structure` (docs/eval/structure.py). Lattices in px at the working resolution (ax, ay, bx, by; x right, "
             "y down); close-ups: right when the same lattice as the true square grid to a twentieth of a step.", ""]
    close = rows["close-ups"]
    lines += [f"Close-ups right: {sum(r['right'] for r in close)} of {len(close)}.", ""]
    for section, found in rows.items():
        lines += [f"## {section}", "", "| photo | grain | lattice (px) |" + (" truth | right |" if section == "close-ups" else ""),
                  "|---|---|---|" + ("---|---|" if section == "close-ups" else "")]
        for r in found:
            lattice = ", ".join(f"{v:.1f}" for v in r["lattice_px"]) if r["lattice_px"] else "-"
            extra = f" {r['truth_px'][0]:.1f} | {'yes' if r['right'] else 'no'} |" if section == "close-ups" else ""
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
    (args.out / "results.json").write_text(json.dumps(rows, indent=1) + "\n")
    (args.out / "results.md").write_text(to_markdown(rows))
    print(f"wrote {args.out}/results.json, results.md ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
