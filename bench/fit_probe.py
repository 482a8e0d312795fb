"""The fit's probe: how long one score of its fixed planes takes (model/probe.py ``Probe``).

A fit (the product's refinement: 240 s) scores itself every 25 steps on 4 planes of 256 px
(twice its training patch); each score is the field on 262,144 points and VGG16 on four
256^2 images, without gradients. The figure: the probe as ``Probe.score`` computes it (one
plane, one image at a time: ``render_slices`` and ``Objective`` chunk when gradients are
off), against the reference of the same work in one batch, measured in the same run on one
torch thread, as a fit runs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.common import best_of

PLANES, SIZE = 4, 256


def bench_probe(space: Path, repeats: int = 2, log=print) -> dict:
    import torch

    from model.networks import load_checkpoint
    from model.slices import linear_to_srgb, plane_points, random_planes, render_slices
    from model.vgg import GATYS_LAYERS, shared_vgg

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model, _ = load_checkpoint(space)
        field, vgg = model.field, shared_vgg(GATYS_LAYERS)
        origins, axes = random_planes(PLANES, np.random.default_rng(12345))
        codes = torch.from_numpy(np.random.default_rng(0).normal(0, 0.5, (PLANES, model.cfg.code_size))).float()
        seeds = torch.arange(PLANES, dtype=torch.int64) + 7
        with torch.no_grad():
            images = render_slices(field, codes, seeds, origins, axes, SIZE)

            def field_batched():  # the reference: every plane's points in one call
                points = plane_points(origins, axes, SIZE, field.cfg.pixels_per_unit)
                linear_to_srgb(field(points, codes, seeds))

            timings = {
                "render_per_plane_s": best_of(lambda: render_slices(field, codes, seeds, origins, axes, SIZE), repeats),
                "render_batched_s": best_of(field_batched, repeats),
                "vgg_per_image_s": best_of(lambda: [vgg(image[None]) for image in images], repeats),
                "vgg_batched_s": best_of(lambda: vgg(images), repeats),
            }
    finally:
        torch.set_num_threads(threads)
    timings["probe_s"] = timings["render_per_plane_s"] + timings["vgg_per_image_s"]
    timings["probe_batched_s"] = timings["render_batched_s"] + timings["vgg_batched_s"]
    log(f"  fit probe ({PLANES} planes of {SIZE} px, 1 thread): {timings['probe_s']:.2f} s "
        f"(field {timings['render_per_plane_s']:.2f} + VGG {timings['vgg_per_image_s']:.2f}); reference, "
        f"one batch: {timings['probe_batched_s']:.2f} s (field {timings['render_batched_s']:.2f} + VGG "
        f"{timings['vgg_batched_s']:.2f})")
    return {f"fit_{k}": v for k, v in timings.items()}


def bench_steps(space: Path, photo: Path | None = None, repeats: int = 3, steps: int = 4, log=print) -> dict:
    """A fit's optimiser step (``model.train.train_step``: two 128-px patches, the decoder, the
    VGG16 Gram loss, backward, Adam), float32 against bfloat16 autocast, one torch thread, the
    two runs interleaved so that both see the same machine. The figure: bf16 / fp32 step time
    (below 1: bf16 is faster; on CPUs without native bfloat16 ``--precision auto`` keeps fp32)."""
    import tempfile

    import torch
    from PIL import Image

    from model.device import cpu_has_native_bf16
    from model.objective import Objective
    from model.train import setup, train_step
    from model.train_config import TrainConfig

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        if photo is None or not Path(photo).is_file():  # scikit-image's brick (CC0) when no photo is given
            from skimage import data

            photo = Path(folder) / "brick.png"
            Image.fromarray(data.brick()).convert("RGB").save(photo)

        def run_of(precision: str):  # noqa: ANN202
            cfg = TrainConfig(mode="single", exemplar=str(photo), out=f"{folder}/{precision}", init=str(space),
                              no_nearest=True, smooth=True, colour_normalise=True, isotropic_transforms=True,
                              patch=128, batch=2, lr=1e-3, transform_lr=5e-3, warmup=20, quiet=True,
                              precision=precision)
            run = setup(cfg)
            run.objective = Objective(run.images, tuple(cfg.layers.split(",")), cfg.loss, cfg.colour_weight,
                                      cfg.colour_normalise, run.device, precision=run.precision)
            run.model.train()
            train_step(run)  # first-call costs (oneDNN kernels, allocations) out of the timing
            return run

        try:
            runs = {precision: run_of(precision) for precision in ("fp32", "bf16")}
            best = {precision: float("inf") for precision in runs}
            for _ in range(repeats):
                for precision, run in runs.items():
                    best[precision] = min(best[precision], best_of(lambda: train_step(run), steps))
        finally:
            torch.set_num_threads(threads)
    timings = {"fit_step_fp32_s": best["fp32"], "fit_step_bf16_s": best["bf16"],
               "fit_native_bf16": cpu_has_native_bf16()}
    log(f"  fit step (2 x 128 px, 1 thread): fp32 {best['fp32']:.3f} s ({1 / best['fp32']:.2f} steps/s), bf16 "
        f"{best['bf16']:.3f} s ({1 / best['bf16']:.2f} steps/s); native bf16: {timings['fit_native_bf16']}")
    return timings
