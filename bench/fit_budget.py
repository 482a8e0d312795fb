"""Quality a fit reaches per time budget (``make bench-fit-budget``; not part of ``make test``).

    .venv/bin/python bench/fit_budget.py [--photos A.png B.png ...] [--seconds 30 60 120]
                                         [--precision auto] [--threads 0] [--seeds 0 1 2]
                                         [--reference-seconds 240] [--reference-checkout DIR]

Each photo is fitted (``python -m model.fit``, one at a time, on every core as the fit lane runs
them by default: ``--threads``) for every budget and seed, then scored as ``make quality`` scores
fits: the VGG Gram style error of its native-zoom tiles against the whole photo, and their error
over the photo's own floor (``eval/style_floor.py``). The reference, measured in the same run: a
float32 fit of ``--reference-seconds`` on one thread (240: the refinement before bfloat16 and
before fits took every core), and the encoder code. ``--reference-checkout``: the reference fits
run the ``model.fit`` of that folder instead, an older checkout of this project (``git worktree
add /tmp/before 85b91e4``: the 4-minute float32 fit when fits were made fast), with its own
defaults and space, on one thread; every fit is scored here, by this checkout's protocol. A fit's
error moves between seeds by as much as between settings: with several ``--seeds`` the table ends
with each run's mean over them and its ratio to the reference's mean. Prints the tables and
merges them into bench/out/results.json under ``fit_budget``.
"""
from __future__ import annotations

import argparse
import json
import statistics
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


def fit(photo: Path, out: Path, seconds: float, precision: str, threads: int, seed: int = 0,
        checkout: Path | None = None) -> dict:
    """``model.fit`` of this checkout, or with ``checkout`` that folder's with only the flags every
    version has (an older one knows no --precision or --detail-seconds)."""
    flags = ["--minutes", str(seconds / 60), "--threads", str(threads), "--seed", str(seed)]
    if checkout is None:
        flags += ["--precision", precision, "--detail-seconds", "0"]  # (the working size is scored)
    subprocess.run([sys.executable, "-m", "model.fit", str(photo.resolve()), str(out), *flags], check=True,
                   cwd=checkout or ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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


def seed_means(rows: list[dict]) -> list[dict]:
    """Each (photo, run)'s mean style error over its seeds, and its ratio to the mean of the
    photo's reference run (the rows marked ``reference``; None without one)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["photo"], row["run"]), []).append(row)
    means = {key: statistics.fmean(r["style"] for r in group) for key, group in groups.items()}
    reference = {photo: means[photo, run] for (photo, run), group in groups.items() if group[0]["reference"]}
    return [{"photo": photo, "run": run, "seeds": len(groups[photo, run]), "style": mean,
             "vs_reference": mean / reference[photo] if photo in reference else None}
            for (photo, run), mean in means.items()]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=Path, nargs="+", default=[VAL / name for name in PHOTOS])
    parser.add_argument("--seconds", type=float, nargs="+", default=[30.0, 60.0, 120.0])
    parser.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"])
    parser.add_argument("--threads", type=int, default=0, help="torch threads of the fits (0: every core, as the "
                        "service's TEXSPACE_FIT_THREADS default)")
    parser.add_argument("--seeds", "--seed", type=int, nargs="+", default=[0], help="the fits' seeds (model.fit --seed)")
    parser.add_argument("--reference-seconds", type=float, default=240.0,
                        help="float32 reference on one thread (0: none)")
    parser.add_argument("--reference-checkout", type=Path, default=None,
                        help="run the reference fits with this folder's model.fit (an older checkout)")
    args = parser.parse_args(argv)
    q = quality_module()
    model = q.ModelRuntime(ROOT / "model" / "weights")
    # (seconds, precision, threads, checkout, whether it is the reference)
    runs = [(seconds, args.precision, args.threads, None, False) for seconds in args.seconds]
    if args.reference_seconds:
        runs.append((args.reference_seconds, "fp32", 1, args.reference_checkout, True))
    rows = []
    with tempfile.TemporaryDirectory(prefix="texspace-fit-budget-") as folder:
        for photo in args.photos:
            encoder = score(q, model, photo)
            rows.append({"photo": photo.stem, "run": "encoder code", "seed": None, "reference": False, "steps": 0,
                         "style": encoder[0], "floor_ratio": encoder[1]})
            for seed in args.seeds:
                for seconds, precision, threads, checkout, reference in runs:
                    out = Path(folder) / f"{photo.stem}-{precision}-{seconds:g}-{seed}{'-ref' * reference}"
                    manifest = fit(photo, out, seconds, precision, threads, seed, checkout)
                    style, ratio = score(q, q.FittedRuntime(model, out), photo)
                    cores = "every core" if threads == 0 else f"{threads} thread" + "s" * (threads > 1)
                    run = f"{seconds:g} s {manifest.get('precision', 'fp32')}, {cores}"
                    if reference:
                        run = f"reference: {run}" + (f" ({checkout.name})" if checkout is not None else "")
                    rows.append({"photo": photo.stem, "run": run, "seed": seed, "reference": reference,
                                 "steps": manifest["steps"], "style": style, "floor_ratio": ratio})
                    print(f"{photo.stem:28s} {run:>36s} seed {seed} {manifest['steps']:4d} steps  style "
                          f"{style:.4f}  / floor {ratio if ratio is None else round(ratio, 2)}", flush=True)
    print("\n| photo | run | seed | steps | style error | over the photo's floor |\n|---|---|---|---|---|---|")
    for row in rows:
        ratio = "-" if row["floor_ratio"] is None else f"{row['floor_ratio']:.2f}"
        seed = "-" if row["seed"] is None else row["seed"]
        print(f"| {row['photo']} | {row['run']} | {seed} | {row['steps']} | {row['style']:.4f} | {ratio} |")
    means = seed_means([row for row in rows if row["seed"] is not None])
    if len(args.seeds) > 1:
        print("\n| photo | run | seeds | mean style error | / the reference's mean |\n|---|---|---|---|---|")
        for row in means:
            ratio = "-" if row["vs_reference"] is None else f"{row['vs_reference']:.2f}"
            print(f"| {row['photo']} | {row['run']} | {row['seeds']} | {row['style']:.4f} | {ratio} |")
    merge_results({"fit_budget": rows, "fit_budget_seed_means": means})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
