"""Quality a fit reaches per time budget (``make bench-fit-budget``; not part of ``make test``).

    .venv/bin/python bench/fit_budget.py [--photos A.png B.png ...] [--seconds 30 60 120]
                                         [--precision auto] [--threads 0] [--seed 0] [--reference-seconds 240]

Each photo is fitted (``python -m model.fit``, one at a time, on every core as the fit lane runs
them by default: ``--threads``) for every budget, then scored as ``make quality`` scores fits: the VGG Gram style error
of its native-zoom tiles against the whole photo, and their error over the photo's own floor
(``eval/style_floor.py``). The reference, measured in the same run: a float32 fit of
``--reference-seconds`` on one thread (240: the refinement before bfloat16 and before fits
took every core), and the encoder code. Prints a
table and merges it into bench/out/results.json under ``fit_budget``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script

from bench.common import merge_results  # noqa: E402

VAL = ROOT / "data" / "textures" / "val"
PHOTOS = ("miniworld_brick_wall_1.png", "vpython_granite.png", "miniworld_wood_1.png")


def quality_module():
    """eval/quality.py, the protocol ``make quality`` runs (imported late: it needs torch)."""
    import eval.quality

    return eval.quality


def fit(photo: Path, out: Path, seconds: float, precision: str, threads: int, seed: int = 0) -> dict:
    subprocess.run([sys.executable, "-m", "model.fit", str(photo), str(out), "--minutes", str(seconds / 60),
                    "--threads", str(threads), "--precision", precision, "--seed", str(seed),
                    "--detail-seconds", "0"], check=True, cwd=ROOT,  # (the working size is scored)
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads((out / "manifest.json").read_text())


def score(q, runtime, photo: Path) -> tuple[float, float | None]:  # noqa: ANN001
    """(style error, error over the photo's floor) of ``runtime``'s tiles for ``photo``."""
    import torch

    from eval.style_floor import crop_errors, photo_floor, style_ratio

    image = q.read_image(photo.read_bytes(), max_pixels=q.MAX_PIXELS)
    working = q.resize_short_side(image, runtime.short_side)
    with torch.no_grad():
        targets = q.gram_matrices(q.vgg_features(working[None]))
    tiles = q.render_tiles(runtime, q.texture_code(runtime, image))
    style = float(q.style_errors(tiles, targets).mean())
    floor = photo_floor(working)
    return style, style_ratio(float(crop_errors(tiles, floor).mean()), floor.floor)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=Path, nargs="+", default=[VAL / name for name in PHOTOS])
    parser.add_argument("--seconds", type=float, nargs="+", default=[30.0, 60.0, 120.0])
    parser.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"])
    parser.add_argument("--threads", type=int, default=0, help="torch threads of the fits (0: every core, as the "
                        "service's TEXSPACE_FIT_THREADS default)")
    parser.add_argument("--seed", type=int, default=0, help="the fits' seed (model.fit --seed)")
    parser.add_argument("--reference-seconds", type=float, default=240.0,
                        help="float32 reference on one thread (0: none)")
    args = parser.parse_args(argv)
    q = quality_module()
    model = q.ModelRuntime(ROOT / "model" / "weights")
    runs = [(seconds, args.precision, args.threads) for seconds in args.seconds]
    if args.reference_seconds:
        runs.append((args.reference_seconds, "fp32", 1))
    rows = []
    with tempfile.TemporaryDirectory(prefix="texspace-fit-budget-") as folder:
        for photo in args.photos:
            encoder = score(q, model, photo)
            rows.append({"photo": photo.stem, "run": "encoder code", "steps": 0, "style": encoder[0],
                         "floor_ratio": encoder[1]})
            for seconds, precision, threads in runs:
                out = Path(folder) / f"{photo.stem}-{precision}-{seconds:g}"
                manifest = fit(photo, out, seconds, precision, threads, args.seed)
                style, ratio = score(q, q.FittedRuntime(model, out), photo)
                cores = "every core" if threads == 0 else f"{threads} thread" + "s" * (threads > 1)
                rows.append({"photo": photo.stem, "run": f"{seconds:g} s {manifest['precision']}, {cores}",
                             "steps": manifest["steps"], "style": style, "floor_ratio": ratio})
                print(f"{photo.stem:28s} {rows[-1]['run']:>26s} {manifest['steps']:4d} steps  style "
                      f"{style:.4f}  / floor {ratio if ratio is None else round(ratio, 2)}", flush=True)
    print(f"\n| photo | run | steps | style error | over the photo's floor |\n|---|---|---|---|---|")
    for row in rows:
        ratio = "-" if row["floor_ratio"] is None else f"{row['floor_ratio']:.2f}"
        print(f"| {row['photo']} | {row['run']} | {row['steps']} | {row['style']:.4f} | {ratio} |")
    merge_results({"fit_budget": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
