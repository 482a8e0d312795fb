"""How far a space reaches: for each photo, the best code the space itself has for it, beside
the code its encoder gives.

    make space-reach
    python -m eval.space_reach --model-dir model/weights --exemplars data/textures-large/val \
        --families 40 --steps 200 --out docs/eval/space-reach

The best code comes from a code-only fit (``code_fit``): the fit's single-mode run
(``model.fit.fit_config``) from the encoder's code, with the space's learning rates at 0 and
no structure built in (no grain, lattice, evenness or lean), so only the code learns against
the photo, for ``--steps`` (its rate falling to 10% over them, as a fit's over its time); its
code at the end is taken. The codes are scored as ``make
quality`` scores tiles (native zoom, through the space's sampler) by the style error over the
photo's floor (``eval/style_floor.py``): the encoder's as an upload serves it (its colour table
as the upload computes one: ``make quality``'s figure), then the encoder's and the code-only
fit's alike, each with a colour table as a fit's is computed (the two tables differ: on
scikit-image's gravel the encoder's code scores 3.1 and 2.7).

Where the encoder's figure is well above the code-only fit's, a better encoder would help;
where both are high, the space cannot draw the photo with any code, and only a fit's structure
or a new space can. The codes are kept in ``--codes`` (a rerun only measures). Writes
``results.json`` and ``results.md`` to ``--out``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from eval.quality import one_per_family, render_tiles, texture_code
from eval.style_floor import crop_errors, photo_floor, style_ratio
from worker.images import read_image
from worker.photo import resize_short_side
from worker.runtime import ModelRuntime

CODE_STEPS = 200  # a 40-s fit's steps on a 2-core CPU (218-250): a code of 8 numbers has settled by then


class CodeRuntime:
    """The space's own sampler with a given code, read as ``eval.quality`` reads a fit's
    (``texture_code`` computes its colour table for it)."""

    def __init__(self, model: ModelRuntime, code: np.ndarray):
        self.sampler, self.fitted_code = model.sampler, np.asarray(code, np.float32).reshape(-1)
        self.short_side, self.pixels_per_unit = model.short_side, model.pixels_per_unit


def code_fit(photo_path: Path, space_checkpoint: Path, steps: int = CODE_STEPS, seed: int = 0) -> dict:
    """The code a code-only fit of ``steps`` learns for the photo (module docstring) and its
    steps. Raises where the run moved any weight of the space: the figures score the code
    through the space's own sampler."""
    import torch

    from model.data import load_exemplar
    from model.fit import PATCH, detect_structure, fit_config
    from model.networks import load_checkpoint
    from model.train import train

    space, _ = load_checkpoint(space_checkpoint)
    photo = load_exemplar(photo_path, space.cfg.exemplar_short_side, quantise=False)
    nothing = detect_structure(photo, space.cfg, grain=None, lattice=None, even=None, lean=None)
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = fit_config(nothing, space.cfg, exemplar=photo_path, run_dir=run_dir, init=space_checkpoint,
                         minutes=1.0, patch=PATCH, rate="falling", seed=seed, loss="gram", device="cpu",
                         quiet=True, precision="auto", threads=0, spectrum=0.0)
        # the space frozen; the code at the run's end (a fit's probe would keep its best state,
        # the start itself where a few steps beat nothing: a code of 8 numbers settles instead)
        # counted in steps, not time: the same codes on a busy machine or a fast one
        cfg = dataclasses.replace(cfg, lr=0.0, transform_lr=0.0, probe_every=0, minutes=None, steps=steps,
                                  decay_by_time=False, decay_start=0, decay_end=steps)
        model, ckpt = load_checkpoint(train(cfg))
    before = space.field.state_dict()
    moved = [name for name, value in model.field.state_dict().items() if not torch.equal(value, before[name])]
    if moved:
        raise RuntimeError(f"a code-only fit moved the space's {', '.join(moved)}")
    return {"code": ckpt["code"].reshape(-1).tolist(), "steps": int(ckpt["step"])}


def measure(model: ModelRuntime, path: Path, code: list[float]) -> dict:
    """Each as its tiles' style error over the photo's floor: the encoder's code as an upload
    serves it (``uploaded``: its colour table as the upload computes one, ``make quality``'s
    figure), and the encoder's code and ``code`` with a fit's colour table (``encoder``,
    ``code_only``: the two codes compared alike)."""
    image = read_image(path.read_bytes(), max_pixels=1 << 26)
    floor = photo_floor(resize_short_side(image, model.short_side))

    def over_floor(runtime, vector: np.ndarray) -> float:  # noqa: ANN001 (a ModelRuntime or CodeRuntime)
        tiles = render_tiles(runtime, vector)
        return style_ratio(float(crop_errors(tiles, floor).mean()), floor.floor)

    def with_fit_table(z) -> float:  # noqa: ANN001
        fitted = CodeRuntime(model, z)
        return over_floor(fitted, texture_code(fitted, image))

    uploaded = texture_code(model, image)  # the encoder's code and the upload's colour table, encoded once
    return {"photo": path.stem, "uploaded": over_floor(model, uploaded),
            "encoder": with_fit_table(uploaded[:model.code_size]), "code_only": with_fit_table(code)}


def summarise(rows: list[dict]) -> dict:
    """Medians and geometric means of both figures, and on how many photos the code-only fit's
    code scores lower than the encoder's."""
    summary = {"photos": len(rows), "lower": sum(r["code_only"] < r["encoder"] for r in rows)}
    for key in ("uploaded", "encoder", "code_only"):
        values = [r[key] for r in rows if r[key] is not None and r[key] > 0]
        summary[f"{key}_median"] = float(np.median(values)) if values else None
        summary[f"{key}_geomean"] = math.exp(float(np.mean(np.log(values)))) if values else None
    return summary


def to_markdown(rows: list[dict], summary: dict, settings: dict) -> str:
    lines = ["# How far the space reaches", "",
             f"`python -m eval.space_reach` ({settings['date']}, {settings['machine']}): space "
             f"{settings['version']}, {summary['photos']} photos of `{settings['exemplars']}`, code-only fits of "
             f"{settings['steps']} steps (seed 0). Style error over the photo's floor (~1: as close to the photo as "
             "more of it is) of the encoder's code as an upload serves it, and of the encoder's code and the best code "
             "the space has for the photo (its code-only fit's), both with a fit's colour table.", "",
             "| photo | encoder code, uploaded | encoder code | code-only fit | steps |", "|---|---|---|---|---|"]
    lines += [f"| {r['photo']} | {r['uploaded']:.2f} | {r['encoder']:.2f} | {r['code_only']:.2f} | {r['steps']} |"
              for r in rows]
    if rows:
        lines += [f"| **median** | **{summary['uploaded_median']:.2f}** | **{summary['encoder_median']:.2f}** | "
                  f"**{summary['code_only_median']:.2f}** | |",
                  f"| geometric mean | {summary['uploaded_geomean']:.2f} | {summary['encoder_geomean']:.2f} | "
                  f"{summary['code_only_geomean']:.2f} | |",
                  "", f"The code-only fit's code is lower than the encoder's on {summary['lower']} of {summary['photos']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m eval.space_reach", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", type=Path, default=Path("model/weights"))
    p.add_argument("--exemplars", type=Path, default=Path("data/textures-large/val"))
    p.add_argument("--families", type=int, default=40, help="one photo of each of this many families "
                   "(eval/quality.py's choice, as make quality-large measures)")
    p.add_argument("--codes", type=Path, default=Path("runs/space-reach"), help="code-only fits kept here")
    p.add_argument("--out", type=Path, default=Path("docs/eval/space-reach"))
    p.add_argument("--steps", type=int, default=CODE_STEPS, help="steps of each code-only fit")
    p.add_argument("--machine", default="", help="what it ran on, for the report")
    args = p.parse_args(argv)
    model = ModelRuntime(args.model_dir)
    rows = []
    args.codes.mkdir(parents=True, exist_ok=True)
    for path in one_per_family(args.exemplars, args.families):
        kept = args.codes / f"{path.stem}.json"
        if not kept.is_file():
            kept.write_text(json.dumps(code_fit(path, args.model_dir / "space.pt", args.steps)) + "\n")
        fitted = json.loads(kept.read_text())
        rows.append(measure(model, path, fitted["code"]) | {"steps": fitted["steps"]})
        print(json.dumps(rows[-1]), flush=True)
    summary = summarise(rows)
    settings = {"date": time.strftime("%Y-%m-%d"), "steps": args.steps, "exemplars": str(args.exemplars),
                "version": model.manifest["version"], "machine": args.machine or "this machine"}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"settings": settings, "summary": summary, "photos": rows},
                                                      indent=2) + "\n")
    (args.out / "results.md").write_text(to_markdown(rows, summary, settings))
    print((args.out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
