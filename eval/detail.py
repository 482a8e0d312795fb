"""A photo's own resolution: what the detail stage adds to a fit, measured against the full photo.

    make quality-detail
    python -m eval.detail --exemplars data/textures/val --fits runs/fits-detail --out docs/eval/detail

Each photo at least twice the working size (512 px and up on its short side) is fitted as an
upload's refinement is (``model.fit.fit_exemplar``, 70 s) with a detail stage after it
(``--detail-seconds``, ``model/detail.py``), into ``--fits`` (kept: a rerun only measures).
Then, through the product path (ONNX samplers, ``worker.tiles.render_tile``, the fit's colour
table as the service computes it):

* ``native``: the fit's tiles at the photo's own scale, zoom ``6 + log2(factor)`` (one tile
  pixel per photo pixel, the photo read at ``factor`` x the working size, up to 4), without
  the detail stage (``sampler.onnx``: the working-size texture magnified) and with it
  (``sampler_detail.onnx``), each as the style error over the floor of the photo at that size
  (``eval/style_floor.py``: 128 px crops, four corners); by-example noise of the full photo
  beside them;
* ``working``: the fit's tiles at zoom 6 over the working-size photo's floor, the figure of
  ``make quality`` (tiles there and below are drawn without the detail octaves).

Tiles: 256 px at (0, 0) and (1, 0), seeds 1 and 2. Writes ``results.json`` and ``results.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from eval.by_example import by_example_tile, gaussianise
from eval.quality import FittedRuntime, texture_code
from eval.style_floor import crop_errors, photo_floor, style_ratio
from worker.colour import linear_to_srgb
from worker.contract import DETAIL_SAMPLER, DETAIL_SECONDS
from worker.images import read_image
from worker.photo import resize_short_side
from worker.runtime import ModelRuntime, SamplerSession
from worker.tiles import NATIVE_ZOOM, native_zoom_for, render_tile

TILE = 256
POSITIONS = ((0, 0), (1, 0))
SEEDS = (1, 2)
FIT_SECONDS = 70.0


def tiles(runtime, code: np.ndarray, zoom: int) -> np.ndarray:  # noqa: ANN001 (a FittedRuntime)
    """sRGB tiles (len(SEEDS) * len(POSITIONS), TILE, TILE, 3) at ``zoom``, one sample a pixel."""
    return np.stack([linear_to_srgb(render_tile(runtime.sampler, code, seed, zoom, x, y, TILE,
                                                pixels_per_unit=runtime.pixels_per_unit, supersample=1))
                     for seed in SEEDS for x, y in POSITIONS])


def by_example(photo: np.ndarray) -> np.ndarray:
    example = gaussianise(photo)
    return np.stack([by_example_tile(example, TILE, TILE, (x * TILE, y * TILE), seed)
                     for seed in SEEDS for x, y in POSITIONS])


def measure(model: ModelRuntime, path: Path, fit_dir: Path) -> dict:
    """The figures of one fitted photo (module docstring)."""
    image = read_image(path.read_bytes(), max_pixels=1 << 26)
    manifest = json.loads((fit_dir / "manifest.json").read_text())
    detail = manifest.get("detail") or {}
    factor = int(detail.get("factor", 1))
    fit = FittedRuntime(model, fit_dir)
    code = texture_code(fit, image)  # the fit's colour table, as the service computes it for the texture
    zoom = native_zoom_for(factor)
    full = resize_short_side(image, model.short_side * factor)
    floor_full, floor_working = photo_floor(full), photo_floor(resize_short_side(image, model.short_side))

    def over(images: np.ndarray, floor) -> float:  # noqa: ANN001
        return style_ratio(float(crop_errors(images, floor).mean()), floor.floor)

    row = {"photo": path.name, "size": list(image.shape[:2]), "factor": factor, "zoom": zoom,
           "detail": detail, "working": over(tiles(fit, code, NATIVE_ZOOM), floor_working),
           "native_fit": over(tiles(fit, code, zoom), floor_full), "native_by_example": over(by_example(full), floor_full)}
    if detail.get("sampler"):
        fit.sampler = SamplerSession(fit_dir / DETAIL_SAMPLER)  # the same code and colour table
        row["native_detail"] = over(tiles(fit, code, zoom), floor_full)
    else:  # the stage did not beat its start: the texture serves the fit at every zoom
        row["native_detail"] = row["native_fit"]
    return row


def to_markdown(rows: list[dict], settings: dict) -> str:
    lines = ["# Detail at the photo's resolution", "",
             f"`python -m eval.detail` ({settings['date']}): each fit {settings['fit_seconds']:g} s, detail stage "
             f"{settings['detail_seconds']:g} s, seed 0, {settings['machine']}. Style error over the photo's floor "
             "(lower is better; ~1 is as good as more of the photo) at the photo's own scale (`native`: the photo "
             "at factor x the working size, zoom 6 + log2 factor) and at the working size (zoom 6).", "",
             "| photo | px | factor | steps | native: fit | native: fit + detail | native: by-example "
             "| working: fit |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        steps = r["detail"].get("steps", "")
        kept = "" if r["detail"].get("sampler") else " (not kept)"
        lines.append(f"| {r['photo']} | {r['size'][1]}x{r['size'][0]} | {r['factor']} | {steps} | "
                     f"{r['native_fit']:.2f} | {r['native_detail']:.2f}{kept} | {r['native_by_example']:.2f} | "
                     f"{r['working']:.2f} |")
    if rows:
        med = {key: float(np.median([r[key] for r in rows])) for key in
               ("native_fit", "native_detail", "native_by_example", "working")}
        lines.append(f"| **median** | | | | {med['native_fit']:.2f} | {med['native_detail']:.2f} | "
                     f"{med['native_by_example']:.2f} | {med['working']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m eval.detail", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", type=Path, default=Path("model/weights"))
    p.add_argument("--exemplars", type=Path, default=Path("data/textures/val"))
    p.add_argument("--fits", type=Path, default=Path("runs/fits-detail"))
    p.add_argument("--out", type=Path, default=Path("docs/eval/detail"))
    p.add_argument("--seconds", type=float, default=FIT_SECONDS)
    p.add_argument("--detail-seconds", type=float, default=DETAIL_SECONDS)
    p.add_argument("--machine", default="", help="what it ran on, for the report")
    args = p.parse_args(argv)
    model = ModelRuntime(args.model_dir)
    rows = []
    for path in sorted(args.exemplars.glob("*.png")):
        size = read_image(path.read_bytes(), max_pixels=1 << 26).shape[:2]
        if min(size) < 2 * model.short_side:
            continue
        fit_dir = args.fits / path.stem
        if not (fit_dir / "manifest.json").is_file():
            from model.fit import fit_exemplar  # torch: only to fit

            fit_exemplar(path, fit_dir, init_checkpoint=args.model_dir / "space.pt", minutes=args.seconds / 60,
                         detail_seconds=args.detail_seconds)
        rows.append(measure(model, path, fit_dir))
        print(json.dumps({k: rows[-1][k] for k in ("photo", "factor", "native_fit", "native_detail", "working")}),
              flush=True)
    settings = {"date": time.strftime("%Y-%m-%d"), "fit_seconds": args.seconds,
                "detail_seconds": args.detail_seconds, "machine": args.machine or "this machine"}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"settings": settings, "photos": rows}, indent=2) + "\n")
    (args.out / "results.md").write_text(to_markdown(rows, settings))
    print((args.out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
