"""Fit one exemplar (the paper's *single* mode), starting from the shipped space.

    python -m model.fit IMAGE OUTDIR [--minutes 4] [--init model/weights/space.pt] [--device auto]

Starts from the space's encoder code for IMAGE and its decoder, then optimises the
code, the translator (so the per-octave transforms) and the decoder for this one
exemplar. Writes OUTDIR/sampler.onnx (DESIGN.md Contract 1, same inputs and outputs
as the shipped sampler), OUTDIR/code.json (the code to feed it), OUTDIR/manifest.json
and OUTDIR/fit.pt (weights and code, for ``model.evaluate``). The worker runs this as
the ``fit`` job where torch is installed.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from model.export import TILEABLE_SAMPLER, export_sampler, export_tileable_sampler, model_version
from model.networks import load_checkpoint
from model.train import TrainConfig, train

DEFAULT_INIT = Path(__file__).resolve().parent / "weights" / "space.pt"
DEFAULT_MINUTES = 4.0  # inside the 5-minute budget on 2 cores, with export
# Learning rates of a fit: the decoder moves gently from the space's weights; the
# per-octave transforms and the code move faster, since a new exemplar mostly needs new
# scales, stretches (grain) and colours. At the space's own 2e-4 a 4-minute wood fit
# stayed flat.
FIT_LR = 1e-3
FIT_TRANSFORM_LR = 5e-3
# Every this many steps the fit scores itself on fixed planes and keeps its best state, so
# a fit never ends worse (by its own objective) than the code it started from.
PROBE_EVERY = 25


def fit_exemplar(image_path, out_dir, *, init_checkpoint=DEFAULT_INIT, minutes: float = DEFAULT_MINUTES,
                 patch: int = 64, grain: str | None = None, loss: str = "gram", progress=None, quiet: bool = True,
                 seed: int = 0, threads: int = 0, device: str = "cpu") -> dict:
    """Fit IMAGE and write the fitted sampler; returns {'code', 'sampler', 'version', 'steps'}.

    ``threads``: torch threads (process-wide; 0 leaves torch's setting as it is).
    ``device``: where the steps run, ``cpu`` | ``cuda`` | ``auto`` (cuda when available);
    the export and the files written are the same either way.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    init = Path(init_checkpoint)
    if not init.exists():
        raise FileNotFoundError(f"no space checkpoint at {init}; train one (make train) or pass --init")
    space, _ = load_checkpoint(init)
    space_cfg = space.cfg
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = TrainConfig(
            mode="single", exemplar=str(image_path), out=run_dir, init=str(init),
            # the space's architecture, which --init requires
            variant=space_cfg.variant, dims=space_cfg.dims, short_side=space_cfg.exemplar_short_side,
            no_nearest=not space_cfg.nearest_input, smooth=space_cfg.smooth,
            # a space trained for colour tables fits the same way: structure under the photo's colours
            colour_normalise=space_cfg.colour_blind_encoder, isotropic_transforms=space_cfg.isotropic_transforms,
            minutes=float(minutes), patch=patch, batch=2, lr=FIT_LR, transform_lr=FIT_TRANSFORM_LR, warmup=20,
            seed=seed, loss=loss, ckpt_every=1_000_000, probe_every=PROBE_EVERY, device=device, quiet=quiet,
            grain=grain or None, threads=threads or 0)
        ckpt_path = train(cfg, progress=progress)
        model, ckpt = load_checkpoint(ckpt_path)
    # Weights, config and code without the optimiser: what model.evaluate needs to compare
    # the fit with the space's encoder code on the same exemplar.
    torch.save({key: ckpt.get(key) for key in ("config", "model", "code", "step", "wall_seconds", "mode", "data",
                                               "loss", "layers", "final_loss", "probe")} | {"init": str(init)},
               out_dir / "fit.pt")
    export_sampler(model.field, out_dir / "sampler.onnx")
    export_tileable_sampler(model.field, out_dir / TILEABLE_SAMPLER)
    code = ckpt["code"].reshape(-1).tolist()
    (out_dir / "code.json").write_text(json.dumps({"code": code}) + "\n")
    manifest = {
        "version": model_version(out_dir / "sampler.onnx"),
        "kind": "fitted",
        "tileable_sampler": TILEABLE_SAMPLER,
        "base_model": init.name,
        "pixels_per_unit": space_cfg.pixels_per_unit,
        "code": code,
        "steps": ckpt["step"],
        "wall_seconds": round(ckpt["wall_seconds"], 1),
        "final_loss": ckpt.get("final_loss"),
        "probe": ckpt.get("probe"),
        "output_colour": "linear",
        "grain": ckpt["config"].get("grain"),
    }
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return {"code": code, "sampler": str(out_dir / "sampler.onnx"), "version": manifest["version"],
            "steps": ckpt["step"]}


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m model.fit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image")
    p.add_argument("outdir")
    p.add_argument("--init", default=str(DEFAULT_INIT), help="space checkpoint to start from")
    p.add_argument("--minutes", type=float, default=DEFAULT_MINUTES)
    p.add_argument("--patch", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--grain", choices=["x", "y"], help="anisotropic exemplar: its grain runs along image x or y")
    p.add_argument("--loss", choices=["gram", "swd"], default="gram", help="VGG feature statistics to match")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu",
                   help="where the fit's steps run (auto: cuda when available)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = p.parse_args(argv)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    result = fit_exemplar(args.image, args.outdir, init_checkpoint=args.init, minutes=args.minutes,
                          patch=args.patch, grain=args.grain, loss=args.loss, quiet=False, seed=args.seed,
                          device=args.device, threads=args.threads)
    print(json.dumps({k: result[k] for k in ("version", "steps", "sampler")}))


if __name__ == "__main__":
    main()
