"""Fit one exemplar (the paper's *single* mode), starting from the shipped space.

    python -m model.fit IMAGE OUTDIR [--minutes M (default 70 s)] [--init model/weights/space.pt] [--device auto]

Starts from the space's encoder code for IMAGE and its decoder, then optimises the
code, the translator (so the per-octave transforms) and the decoder for this one
exemplar. Writes OUTDIR/sampler.onnx (docs/ARCHITECTURE.md, Contract 1, same inputs and outputs
as the shipped sampler), OUTDIR/code.json (the code to feed it), OUTDIR/manifest.json
and OUTDIR/fit.pt (weights and code, for ``model.evaluate``). The worker runs this as
the ``fit`` job where torch is installed. What regular structure the fit builds in (grain,
a repeat lattice, stripes, boards) is for ``model.structure`` to detect.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from model.config import ModelConfig
from model.data import load_exemplar
from model.detail import detail_factor, fit_detail
from model.export import TILEABLE_SAMPLER, export_sampler, export_tileable_sampler, model_version
from model.device import resolve_device, resolve_precision
from model.networks import load_checkpoint
from model.probe import Interim
from model.structure import (EVEN_BLOCK, GRAIN_STRETCH, detect_even, grain_stretch, grain_turn, photo_lean,
                             photo_structure, straighten, turn_lattice)
from model.train import train
from model.train_config import TrainConfig
from worker.contract import DETAIL_SAMPLER, DETAIL_SECONDS, DETAIL_TILEABLE_SAMPLER
from worker.photo import resize_short_side

DEFAULT_INIT = Path(__file__).resolve().parent / "weights" / "space.pt"
# An upload's refinement is the product's latency: 70 s on every core (the service's budget,
# service/settings.py FIT_SECONDS). On a 2-core AVX2 EPYC it makes 68-75 steps, the 90-s
# one-thread fit it replaced 56-64, at the same style error (docs/DECISIONS.md).
DEFAULT_SECONDS = 70.0
DEFAULT_MINUTES = DEFAULT_SECONDS / 60
# Learning rates of a fit: the decoder moves gently from the space's weights; the
# per-octave transforms and the code move faster, since a new exemplar mostly needs new
# scales, stretches (grain) and colours. At the space's own 2e-4 a 4-minute wood fit
# stayed flat.
FIT_LR = 1e-3
FIT_TRANSFORM_LR = 5e-3
# A fit's rates fall linearly to 10% over its minutes (``rate="falling"``, the default):
# most 60-s fits kept a state from step 25 or 50 and drifted after it. Seeds 0-3, tile
# style error, falling / constant (geometric mean): wood 0.89, grass 0.90, gravel 0.94,
# cardboard (stripes) 0.80. 2D lattice fits on 64-px patches were mixed (bricks 1.15, grill
# 1.26); on 128-px patches (``PATCH``) they fall too: seeds 0-1, floor tiles 0.09/0.10 ->
# 0.031/0.045, grill 1.15/0.87 -> 0.60/0.49, bricks 0.10/0.12 -> 0.12/0.13.
RATES = ("falling", "constant")
# Every this many steps the fit scores itself on fixed planes and keeps its best state, so
# a fit never ends worse (by its own objective) than the code it started from.
PROBE_EVERY = 25
# Patch side of a fit's steps, in working-resolution pixels. 60-s fits, one thread, two at a
# time, seeds 0 and 1, quality-protocol style error (mean of the seeds, 64 -> 128 px):
# gravel 2.17 -> 1.75, granite 0.445 -> 0.318, wood 0.041 -> 0.034, concrete 0.009 ->
# 0.007, cardboard 0.066 -> 0.063, grass 0.011 -> 0.015, with a quarter of the steps (~100
# instead of ~410): the Gram statistics of the deeper layers need the larger patch. Lattice
# fits too, since they start on the photo's mean cell (``start_on_mean_cell``): on 64 px
# the floor tiles' fits never beat their first 100 steps on the probe (it scores 2x the
# patch), and the tiles scored 0.28/0.45 (seeds 0/1, constant rates); on 128 px with
# falling rates 0.031/0.045; grill 0.99/1.50 -> 0.60/0.49, bricks 0.15/0.15 -> 0.12/0.13
# (tile set 1, against the Lanczos photo, 2026-11-27). Stripe fits: the validation
# cardboard, seeds 0-3, 64 -> 128 px: 0.054 -> 0.0048, 0.021 -> 0.0049, 0.017 -> 0.012,
# 0.052 -> 0.0032.
PATCH = 128
# An upload's refinement serves a first result this many seconds into its fit (``interim``):
# the probe's best state then (its start too, if the fit builds structure in: model/probe.py,
# ``Interim``). With the start, the export and the
# colour table it is served about 20 s after the fit starts; lattice fits start on the photo's
# mean cell, so even ~20 steps show the bond or grid the encoder's patches lack. Uploads queued
# together each get theirs before any fit goes on (the service pauses a fit at its interim's second).
INTERIM_SECONDS = 10.0
# A lattice fit trains one patch per step (and its lattice partner, model/train.py) instead
# of two: it needs the steps. Measured before the partners, the brick wall on one thread,
# 60 s, best probe score (lower is better): batch 2 425 steps 0.28 (courses only), 90 s
# 625 steps 0.10 (bricks), batch 1 648 steps 0.086 (bricks).


def fit_exemplar(image_path, out_dir, *, init_checkpoint=DEFAULT_INIT, minutes: float = DEFAULT_MINUTES,
                 patch: int | None = None, grain: str | None = "auto", loss: str = "gram", progress=None,
                 quiet: bool = True, seed: int = 0, threads: int = 0, device: str = "cpu", lattice: str | None = "auto",
                 rate: str = "falling", spectrum: float = 0.0, even: str | None = "auto",
                 lean: str | None = "auto", interim=None, interim_seconds: float = INTERIM_SECONDS,
                 precision: str = "auto", run_dir: str | Path | None = None, pause=None,
                 shade: str | None = "auto", detail_seconds: float = 0.0, wants_detail=None,
                 start_code=None) -> dict:
    """Fit IMAGE and write the fitted sampler; returns {'code', 'sampler', 'version', 'steps', 'grain',
    'straightened', 'grain_stretch', 'lattice', 'muted_octaves', 'lean', 'detail'}.

    ``patch``: side of the training patches; None: ``PATCH``.
    ``grain``: ``"x"``, ``"y"``, None (isotropic) or ``"auto"`` (the default, as the CLI's and
    the service's); ``lattice``: ``"auto"`` (the default) or None: what
    ``model.structure.photo_structure`` detects on the photo. A grain leaning
    3-45 degrees off its nearer axis (``model.structure.grain_turn``) is straightened first: the
    fit learns from the turned photo, and its tiles show the grain straight (``straightened``:
    the degrees turned, 0 when not); a lattice found there without a grain is turned back and
    fitted on the photo as it is. The manifest and the result say what was used (the
    lattice in world units).
    ``threads``: torch threads (process-wide; 0 leaves torch's setting as it is).
    ``device``: where the steps run, ``cpu`` | ``cuda`` | ``auto`` (cuda when available);
    the export and the files written are the same either way.
    ``precision``: ``auto`` | ``bf16`` | ``fp32``, the arithmetic of the steps' VGG loss and
    decoder (``model.device.resolve_precision``; the exported samplers are float32 either way).
    ``rate``: ``"falling"`` (the learning rates fall to 10% over ``minutes``) or ``"constant"``;
    the manifest says which.
    ``spectrum``: weight of the spectrum loss (``TrainConfig.spectrum``; 0: off, the default).
    ``even``: ``"auto"``: a photo with no grain or lattice that is even at large scales
    (``model.structure.detect_even``) is fitted with its coarse octaves muted (``coarse_octaves``;
    the probe still compares with the unmuted start); None: never. ``muted_octaves`` in the
    result: how many the served sampler has muted (0 when the fit kept its unmuted start).
    ``lean``: ``"auto"``: a photo with no grain or lattice is fitted with a learned linear map of
    world (x, y) (``ModelConfig.warp``) that starts at its lean (``model.structure.photo_lean``:
    [degrees, stretch] in the result); None: never.
    ``shade``: ``"on"``: a fit on a lattice, stripes or boards gives each repeat cell its own
    hashed shade (``ModelConfig.lattice_shade``); ``"auto"``: on where the steps run on CUDA;
    ``"none"``: never.
    ``interim``: ``interim(folder, code, step, structure)`` is called once, ``interim_seconds``
    into the fit, with the best state so far written to ``folder`` (``OUTDIR/interim``: its
    ``sampler.onnx`` and tileable sampler), its code (list of floats), the step it is from and
    the structure keys of the result. That state is the start (step 0) when nothing beats it
    yet and the fit builds structure in (a lattice, grain or lean the encoder's tiles lack);
    without structure, not until a state beats the start, and not at all if none does before
    the end. The fit goes on meanwhile; an exception from ``interim`` stops it.
    ``detail_seconds``: where IMAGE is at least twice the working size, a detail stage of that
    many seconds after the fit (``model/detail.py``) writes ``OUTDIR/sampler_detail.onnx``, the
    fit with finer octaves learned on the photo at up to 4x the working size (``detail`` in the
    result and manifest: its factor, steps and probe scores; None without a stage). 0: none.
    ``wants_detail()``: asked once when the fit itself ends; False skips the stage (the service:
    another upload waits for the fit lane).
    ``run_dir``: the training run's folder (default: a temporary one). A fit whose ``run_dir``
    holds a paused run continues it, with the rest of its ``minutes``.
    ``pause()``: asked once, ``interim_seconds`` in (after the interim, if one is published): True
    stops the fit there; ``run_dir`` then holds its resumable state and the result is ``{'paused': True, 'steps',
    ...structure}`` (nothing exported). The service pauses an upload's fit so that the uploads
    queued behind it reach their interims first.
    ``start_code``: the code the fit starts from, the one its upload stores (``worker.encode``
    chooses it by style), so the probe's start is what users saw; None: the encoder's mean over
    the photo's crops (``model.train.initial_code``).
    """
    if rate not in RATES:
        raise ValueError(f"rate must be one of {', '.join(RATES)}, got {rate!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    init = Path(init_checkpoint)
    if not init.exists():
        raise FileNotFoundError(f"no space checkpoint at {init}; train one (make train) or pass --init")
    steps_on = resolve_device(device)  # (a missing GPU fails here, before any work)
    space, _ = load_checkpoint(init)
    space_cfg = space.cfg
    photo = load_exemplar(image_path, space_cfg.exemplar_short_side, quantise=False)  # as training reads it
    found = detect_structure(photo, space_cfg, grain=grain, lattice=lattice, even=even, lean=lean)
    patch = patch or PATCH
    structure = found.summary()
    # progress runs over the fit and its detail stage together (the service's estimates count both)
    share = minutes * 60 / (minutes * 60 + detail_seconds) if detail_seconds > 0 else 1.0
    fit_progress = (lambda fraction: progress(fraction * share)) if progress is not None and share < 1 else progress

    def publish(model, code, step):  # noqa: ANN001, ANN202 (train's Interim hands the best state)
        folder = out_dir / "interim"
        folder.mkdir(exist_ok=True)
        write_samplers(model.field, folder)
        interim(folder, code.reshape(-1).tolist(), step, served_structure(structure, step))
    if pause is not None and interim is None:
        raise ValueError("pause is asked at the interim's second: give an interim too")
    with contextlib.nullcontext(str(run_dir)) if run_dir else tempfile.TemporaryDirectory() as run_dir:
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        exemplar = Path(image_path)
        if found.turned:  # training reads the turned photo as it is (it is smaller than the working size)
            exemplar = Path(run_dir) / f"{Path(image_path).stem}.png"
            Image.fromarray((found.photo * 255 + 0.5).astype(np.uint8)).save(exemplar)
        cfg = fit_config(found, space_cfg, exemplar=exemplar, run_dir=run_dir, init=init, minutes=minutes,
                         patch=patch, rate=rate, seed=seed, loss=loss, device=device, quiet=quiet,
                         precision=precision, threads=threads, spectrum=spectrum,
                         shade=shade == "on" or (shade == "auto" and steps_on.type == "cuda"), start_code=start_code)
        ckpt_path = train(cfg, progress=fit_progress, pause=pause,
                          interim=Interim(interim_seconds, publish, start_counts=found.builds_structure)
                          if interim is not None else None)
        model, ckpt = load_checkpoint(ckpt_path)
        if ckpt.get("paused"):
            return {"paused": True, "steps": ckpt["step"], **structure}
    structure = served_structure(structure, (ckpt.get("probe") or {}).get("step"))
    result = write_fit_outputs(out_dir, model, ckpt, structure, init=init, space_cfg=space_cfg, patch=patch,
                               rate=rate, device=steps_on, precision=precision, spectrum=spectrum)
    detail = None
    if detail_seconds > 0 and (wants_detail is None or wants_detail()):
        detail = write_detail(out_dir, image_path, model, ckpt["code"], found, seconds=detail_seconds,
                              device=steps_on, precision=precision, seed=seed,
                              progress=(lambda f: progress(share + (1 - share) * f)) if progress is not None else None)
    if progress is not None and detail_seconds > 0:  # (no stage, or a photo under twice the working size)
        progress(1.0)
    return result | {"detail": detail}


def write_detail(out_dir: Path, image_path, model, code: torch.Tensor, found: FitStructure, *,  # noqa: ANN001
                 seconds: float, device: torch.device, precision: str, seed: int, progress=None) -> dict | None:
    """A fit's detail stage (``model.detail.fit_detail``) where its photo is at least twice the
    working size: ``OUTDIR/sampler_detail.onnx``, its tileable twin and the manifest's ``detail``
    where the stage beat its start; returns the stage's figures, or None without a stage."""
    full = load_exemplar(image_path, None, quantise=False)
    short_side = model.cfg.exemplar_short_side
    factor = detail_factor(*full.shape[:2], short_side)
    if factor < 2:
        return None
    full = resize_short_side(full, short_side * factor)  # (one resize, as the working photo's)
    if found.turned:  # the fit learned the straightened photo
        full = straighten(full, found.turned)
    grown, stats = fit_detail(model, code, full, factor, seconds=seconds, device=device,
                              precision=resolve_precision(precision, device), seed=seed, grain=found.grain,
                              photo_plane=bool(found.lattice), progress=progress)
    if stats["kept"]:
        export_sampler(grown.field, out_dir / DETAIL_SAMPLER)
        export_tileable_sampler(grown.field, out_dir / DETAIL_TILEABLE_SAMPLER)
        stats["sampler"] = DETAIL_SAMPLER
    manifest = json.loads((out_dir / "manifest.json").read_text())
    (out_dir / "manifest.json").write_text(json.dumps(manifest | {"detail": stats}, indent=2) + "\n")
    return stats


def served_structure(structure: dict, step: int | None) -> dict:
    """The structure keys of a state the fit serves from ``step``: the probe scores the unmuted
    start first, so a start it kept (step 0, an interim or the end) serves no muted octave."""
    return (structure | {"muted_octaves": 0}) if step == 0 else dict(structure)


@dataclass
class FitStructure:
    """What a fit builds in, found on its photo (``detect_structure``)."""

    photo: np.ndarray  # the photo it is fitted to: turned when its grain leant
    turned: float  # degrees the photo was turned (0: not)
    grain: str | None  # the axis the grain runs along
    stretch: float  # how much longer the noise cells are along the grain (GRAIN_STRETCH without one)
    lattice: tuple[float, float, float, float] | None  # world units
    muted: int  # coarse octaves muted (an even photo)
    lean: tuple[float, float] | None  # [degrees, stretch] the warp starts at

    @property
    def builds_structure(self) -> bool:
        """Whether the fit's start differs from the space's sampler for the photo's code."""
        return bool(self.turned or self.grain or self.lattice or self.lean)

    def summary(self) -> dict:
        """The structure keys of the fit's result and manifest."""
        return {"grain": self.grain or None, "straightened": round(self.turned, 2),
                "grain_stretch": self.stretch if self.grain else None,
                "lattice": list(self.lattice) if self.lattice else None,
                "muted_octaves": self.muted, "lean": [round(self.lean[0], 2), round(self.lean[1], 3)] if self.lean else None}


def detect_structure(photo: np.ndarray, space_cfg: ModelConfig, *, grain: str | None, lattice: str | None,
                     even: str | None, lean: str | None) -> FitStructure:
    """What ``fit_exemplar`` builds in for ``photo`` (at the working resolution), by its
    ``grain``, ``lattice``, ``even`` and ``lean`` arguments (``model/structure/`` detects)."""
    asked = grain
    grain, found = photo_structure(photo, grain, lattice)
    # A grain that leans: the photo turned so it runs along its axis (the noise stretches
    # along x or y only), and its boards looked for again on the turned photo. Boards found
    # on the photo as it is run along the axis already: wavy ripples lean locally, and the
    # savanna dunes' mean lean (11 degrees) turned their repeat out of the profile (their
    # stripes run along that lean instead: model.structure.stripes._leaning_stripes).
    turned = grain_turn(photo, grain) if not found else 0.0
    if turned:
        straight = straighten(photo, turned)
        # detected again as asked: a grain found, not asked for, gives way to wide boards or a
        # far lattice on the turned photo as on any other; one the turned photo loses is kept
        again, found = photo_structure(straight, asked, lattice)
        if found is not None and not again:
            # a lattice without grain has no axis to keep: it is fitted as the photo leans
            # (hazard stripes at 45 degrees came back upright, 62x their floor; now 1.2x)
            grain, found, turned = None, turn_lattice(found, turned), 0.0
        else:
            photo, grain = straight, again or grain
    # world units: one exemplar pixel is 1 / pixels_per_unit; image rows run along +y
    lattice = tuple(v / space_cfg.pixels_per_unit for v in found) if found else None
    stretch = grain_stretch(photo, grain) if grain else GRAIN_STRETCH  # (of the turned photo)
    muted = (coarse_octaves(space_cfg.pixels_per_unit, space_cfg.n_octaves)
             if even == "auto" and not grain and not lattice and detect_even(photo) else 0)
    lean = photo_lean(photo) if lean == "auto" and not grain and not lattice else None
    return FitStructure(photo=photo, turned=turned, grain=grain, stretch=stretch, lattice=lattice, muted=muted,
                        lean=lean)


def fit_config(found: FitStructure, space_cfg: ModelConfig, *, exemplar: Path, run_dir: str, init: Path,
               minutes: float, patch: int, rate: str, seed: int, loss: str, device: str, quiet: bool,
               precision: str, threads: int, spectrum: float, shade: bool = False,
               start_code=None) -> TrainConfig:
    """The single-mode training run of a fit: the space's architecture, the fit's rates and
    budget, and what ``detect_structure`` found."""
    return TrainConfig(
        mode="single", exemplar=str(exemplar), exemplar_as_is=bool(found.turned), out=run_dir, init=str(init),
        # the space's architecture, which --init requires
        variant=space_cfg.variant, dims=space_cfg.dims, short_side=space_cfg.exemplar_short_side,
        code_size=space_cfg.code_size, encoder_width=space_cfg.encoder_width, hidden=space_cfg.hidden,
        no_nearest=not space_cfg.nearest_input, smooth=space_cfg.smooth,
        # a space trained for colour tables fits the same way: structure under the photo's colours
        colour_normalise=space_cfg.colour_blind_encoder, isotropic_transforms=space_cfg.isotropic_transforms,
        minutes=float(minutes), patch=patch, batch=1 if found.lattice else 2, lr=FIT_LR,
        transform_lr=FIT_TRANSFORM_LR, warmup=20, decay_by_time=rate == "falling",
        seed=seed, loss=loss, ckpt_every=1_000_000, probe_every=PROBE_EVERY, device=device, quiet=quiet,
        precision=precision,
        grain=found.grain or None, grain_stretch=found.stretch, lattice=found.lattice,
        lattice_cell=bool(found.lattice), lattice_shade=bool(found.lattice) and shade,
        threads=threads or 0,
        spectrum=spectrum, mute_octaves=found.muted, warp=found.lean is not None,
        warp_start=found.lean, start_code=None if start_code is None else [float(v) for v in start_code])


def write_fit_outputs(out_dir: Path, model, ckpt: dict, structure: dict, *, init: Path,  # noqa: ANN001 (a TextureSpace)
                      space_cfg: ModelConfig, patch: int, rate: str, device: torch.device, precision: str,
                      spectrum: float) -> dict:
    """A finished fit's files in ``out_dir`` (fit.pt, the samplers, code.json, manifest.json)
    and ``fit_exemplar``'s result."""
    # Weights, config and code without the optimiser: what model.evaluate needs to compare
    # the fit with the space's encoder code on the same exemplar.
    torch.save({key: ckpt.get(key) for key in ("config", "model", "code", "step", "wall_seconds", "mode", "data",
                                               "loss", "layers", "final_loss", "probe")} | {"init": str(init)},
               out_dir / "fit.pt")
    write_samplers(model.field, out_dir)
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
        "patch": patch,
        "wall_seconds": round(ckpt["wall_seconds"], 1),
        "final_loss": ckpt.get("final_loss"),
        "probe": ckpt.get("probe"),
        "output_colour": "linear",
        **structure,
        "rate": rate,
        "device": device.type,
        "precision": "bf16" if resolve_precision(precision, device) else "fp32",
        "spectrum": spectrum,
    }
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return {"code": code, "sampler": str(out_dir / "sampler.onnx"), "version": manifest["version"],
            "steps": ckpt["step"], **structure}


def write_samplers(field, folder: Path) -> None:  # noqa: ANN001 (a TextureField)
    """A fitted field's sampler pair: ``sampler.onnx`` (Contract 1) and its tileable twin."""
    export_sampler(field, folder / "sampler.onnx")
    export_tileable_sampler(field, folder / TILEABLE_SAMPLER)


def coarse_octaves(pixels_per_unit: float, n_octaves: int, block: float = EVEN_BLOCK) -> int:
    """How many of the coarsest octaves have cells of ``block`` px or more (octave k:
    ``pixels_per_unit / 2^k`` px a cell, before its learned scale): 4 of 8 at 256 px a unit."""
    return sum(pixels_per_unit / 2**k >= block for k in range(n_octaves))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m model.fit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image")
    p.add_argument("outdir")
    p.add_argument("--init", default=str(DEFAULT_INIT), help="space checkpoint to start from")
    p.add_argument("--minutes", type=float, default=DEFAULT_MINUTES,
                   help=f"time budget in minutes (default {DEFAULT_SECONDS:g} s, the service's)")
    p.add_argument("--patch", type=int, default=None,
                   help=f"training patch side in px (default {PATCH})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--grain", choices=["x", "y", "auto", "none"], default="auto",
                   help="anisotropic exemplar: its grain runs along image x or y; auto (default): detected from "
                        "the photo (detect_grain); none: isotropic")
    p.add_argument("--lattice", choices=["auto", "none"], default="auto",
                   help="regular exemplar (bricks, tile grids, corrugation, boards): auto (default) detects its "
                        "repeat lattice, stripes or boards (model/structure/) and the decoder reads each "
                        "point's phase on it; none: off")
    p.add_argument("--loss", choices=["gram", "swd"], default="gram", help="VGG feature statistics to match")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu",
                   help="where the fit's steps run (auto: cuda when available)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--precision", choices=["auto", "bf16", "fp32"], default="auto",
                   help="arithmetic of the steps (auto: bf16 on CUDA and on CPUs with native bfloat16)")
    p.add_argument("--rate", choices=RATES, default="falling",
                   help="learning rates: falling to 10%% over --minutes (default), or constant")
    p.add_argument("--spectrum", type=float, default=0.0,
                   help="weight of the luminance spectrum loss, times the photo's Gram magnitude (0: off; "
                        "off by default: closer spectra, but grass and lattice fits got worse)")
    p.add_argument("--even", choices=["auto", "none"], default="auto",
                   help="auto (default): a photo even at large scales (model.structure.detect_even, no grain "
                        "or lattice) is fitted with its coarse noise octaves muted; none: never")
    p.add_argument("--lean", choices=["auto", "none"], default="auto",
                   help="auto (default): a photo with no grain or lattice is fitted with a learned linear map "
                        "of world x, y that starts at the photo's lean (model.structure.photo_lean: the "
                        "direction its features run and how much longer they are along it); none: never")
    p.add_argument("--shade", choices=["auto", "on", "none"], default="auto",
                   help="on: a fit on a repeat lattice, stripes or boards gives each repeat cell its own hashed "
                        "shade input (ModelConfig.lattice_shade); none: every cell alike; auto (default): on "
                        "where the fit runs on CUDA (hundreds of steps), none on the CPU, where 60-step fits "
                        "scored worse with it (docs/DECISIONS.md)")
    p.add_argument("--detail-seconds", type=float, default=DETAIL_SECONDS,
                   help="a photo at least twice the working size: seconds of the detail stage after the fit, "
                        f"finer octaves learned on the photo at up to 4x the working size (model/detail.py; "
                        f"default {DETAIL_SECONDS:g}; 0: none)")
    p.add_argument("--start-code", type=float, nargs="+",
                   help="the code to start from (as the service passes its upload's stored code; "
                        "`texspace encode` prints it); default: the encoder's mean over the photo's crops")
    args = p.parse_args(argv)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    result = fit_exemplar(args.image, args.outdir, init_checkpoint=args.init, minutes=args.minutes,
                          patch=args.patch, grain=None if args.grain == "none" else args.grain, loss=args.loss,
                          quiet=False, seed=args.seed, device=args.device, threads=args.threads,
                          precision=args.precision,
                          lattice=None if args.lattice == "none" else args.lattice, rate=args.rate,
                          spectrum=args.spectrum, even=None if args.even == "none" else args.even,
                          lean=None if args.lean == "none" else args.lean,
                          shade=args.shade, detail_seconds=args.detail_seconds, start_code=args.start_code)
    print(json.dumps({k: result[k] for k in ("version", "steps", "grain", "straightened", "grain_stretch", "lattice",
                                             "muted_octaves", "lean", "sampler", "detail")}))


if __name__ == "__main__":
    main()
