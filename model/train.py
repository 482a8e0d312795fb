"""Train a texture space (or fit one exemplar) on the CPU or a CUDA GPU.

    python -m model.train --out runs/space                 # the shipped space, 3D
    python -m model.train --out runs/space-gpu --device cuda --batch 16 --patch 256
    python -m model.train --mode single --exemplar IMG --out runs/wood --minutes 5
    python -m model.train --variant perlin --out runs/perlin --steps 2000

Every step: draw exemplar crops, encode them (space mode) or use the learned code
(single mode), synthesise patches on random slice planes of the solid texture
(axis-aligned and oblique, random offsets; ``--dims 2`` keeps them on the xy plane),
and match VGG16 statistics of the exemplar (Gram matrices, or sliced Wasserstein).
Targets are computed once per exemplar from the whole image at the working
resolution. Checkpoints carry weights + config + step + RNG state, so
``--out`` an existing run resumes it, and export rebuilds the model from the file alone.
Checkpoints always hold CPU tensors, whatever ``--device`` ran the steps, so a run
started on a GPU resumes on the CPU and the other way round.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import threading
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from model.data import TextureDataset, load_exemplar, sample_batch
from model.losses import gram_loss, gram_matrices, sliced_wasserstein_loss
from model.networks import ModelConfig, TextureSpace, VARIANTS, load_checkpoint
from model.colour import compressed_moments, transfer_colour_moments
from model.slices import linear_to_srgb, random_planes, render_slices, srgb_to_linear
from model.vgg import GATYS_LAYERS, shared_vgg


POSITION_EXTENT = 4.0  # world units around the origin where position-input variants train


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m model.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", choices=["space", "single"], default="space")
    p.add_argument("--variant", choices=sorted(VARIANTS), default="ours")
    p.add_argument("--dims", type=int, choices=[2, 3], default=3)
    p.add_argument("--data", default="data/textures/train", help="folder of exemplar PNGs (space mode)")
    p.add_argument("--exemplar", help="image file (single mode)")
    p.add_argument("--exclude", default="miniworld_metal_grill_2",
                   help="comma-separated exemplar names left out of space training (the default's "
                        "regular dot grid has ~30x the Gram loss of any other photo and steers a shared decoder)")
    p.add_argument("--out", required=True, help="run folder: checkpoint, log; resumed if it exists")
    p.add_argument("--init", help="checkpoint to start from (weights only; e.g. the space for a fit)")
    p.add_argument("--steps", type=int, default=100_000, help="stop after this many steps in total")
    p.add_argument("--minutes", type=float, default=None, help="stop after this much wall time (this run)")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--patch", type=int, default=96, help="synthesised patch size (pixels)")
    p.add_argument("--crop", type=int, default=128, help="exemplar crop size fed to the encoder")
    p.add_argument("--short-side", type=int, default=256, help="exemplar working resolution")
    p.add_argument("--lr", type=float, default=5e-4)
    p.add_argument("--code-lr", type=float, default=5e-3, help="learning rate of the codes (table or single)")
    p.add_argument("--transform-lr", type=float, default=None,
                   help="learning rate of the per-octave transform head (default: --lr); a fit raises it "
                        "so the octaves can stretch into grain within minutes")
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--clip", type=float, default=1.0, help="global gradient-norm clip")
    p.add_argument("--loss", choices=["gram", "swd"], default="gram")
    p.add_argument("--layers", default=",".join(GATYS_LAYERS))
    p.add_argument("--colour-weight", type=float, default=50.0,
                   help="weight of the sRGB colour mean + covariance match (0: VGG statistics only)")
    p.add_argument("--colour-normalise", action="store_true",
                   help="judge structure only: give every synthesised patch its exemplar's colour moments "
                        "before the loss (the sampler's colour table does the same at inference), "
                        "train a colour-blind encoder; --colour-weight is then unused")
    p.add_argument("--isotropic-transforms", action="store_true",
                   help="per-octave transforms keep only their isotropic scale (|det T|^(1/D) I): no learned "
                        "stretch direction, so 2D tiles do not lean")
    p.add_argument("--decay-start", type=int, default=None,
                   help="step at which the learning rates start to fall linearly, to 10%% at --decay-end")
    p.add_argument("--decay-end", type=int, default=None, help="step at which the decay ends (default: --steps)")
    p.add_argument("--oblique", type=float, default=0.5, help="fraction of oblique slice planes")
    p.add_argument("--no-nearest", action="store_true", help="decoder gets interpolated noise only")
    p.add_argument("--smooth", action="store_true", help="smoothstep noise interpolation")
    p.add_argument("--no-rotations", action="store_true", help="exemplar crops keep their orientation")
    p.add_argument("--grain", choices=["x", "y"],
                   help="anisotropic exemplar whose grain runs along the image's x (left-right) or y (up-down): "
                        "crops keep their orientation and every slice plane contains that world axis in the same "
                        "role, so tiles on the xy plane show the grain as the exemplar does")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--probe-every", type=int, default=0,
                   help="single mode: every N steps (and at the start and end) score the exemplar on fixed "
                        "planes and seeds; the run ends on the best-scoring weights and code (0: off)")
    p.add_argument("--ckpt-every", type=int, default=200)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu",
                   help="where steps run (auto: cuda when available); checkpoints always hold CPU tensors")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def colour_moments(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image mean [N,3] and covariance [N,3,3] of sRGB pixel colours; images [N,3,H,W]."""
    flat = images.flatten(2)  # [N,3,HW]
    mean = flat.mean(dim=2)
    centred = flat - mean.unsqueeze(2)
    return mean, centred @ centred.transpose(1, 2) / flat.shape[2]


class Objective:
    """VGG statistics of the exemplars, computed once; loss of synthesised patches.

    ``colour_weight`` adds the squared error of the patch's mean colour and colour
    covariance to the exemplar's. The Gram loss alone let a 6000-step space settle on
    wrong hues (olive wood, blue-grey marble) whose deeper-layer statistics matched.
    """

    def __init__(self, images: list[np.ndarray], layers: tuple[str, ...], kind: str, colour_weight: float = 0.0,
                 colour_normalise: bool = False, device: torch.device | str = "cpu"):
        self.vgg = shared_vgg(layers, device)  # one per device: moving the shared one would move it for all
        self.kind = kind
        self.colour_weight = 0.0 if colour_normalise else colour_weight
        self.colour_normalise = colour_normalise
        self.targets = []  # per exemplar: Grams (gram) or features (swd)
        self.colours = []  # per exemplar: (mean [1,3], covariance [1,3,3])
        self.compressed = []  # per exemplar: compressed-colour (mean [1,3], covariance [1,3,3])
        with torch.no_grad():
            for image in images:
                tensor = torch.from_numpy(image.transpose(2, 0, 1).copy())[None].to(device)
                feats = self.vgg(tensor)
                self.targets.append(gram_matrices(feats) if kind == "gram" else feats)
                self.colours.append(colour_moments(tensor))
                self.compressed.append(compressed_moments(srgb_to_linear(tensor)))

    def __call__(self, synth: torch.Tensor, indices: np.ndarray) -> torch.Tensor:
        if self.colour_normalise:
            mean = torch.cat([self.compressed[k][0] for k in indices])
            covariance = torch.cat([self.compressed[k][1] for k in indices])
            synth = linear_to_srgb(transfer_colour_moments(srgb_to_linear(synth), mean, covariance))
        feats = self.vgg(synth)
        losses = []
        means, covariances = colour_moments(synth)
        for b, k in enumerate(indices):
            one = {name: value[b : b + 1] for name, value in feats.items()}
            if self.kind == "gram":
                losses.append(gram_loss(one, self.targets[k]))
            else:
                losses.append(sliced_wasserstein_loss(one, self.targets[k]))
            if self.colour_weight:
                mean, covariance = self.colours[k]
                colour = (means[b] - mean[0]).square().sum() + (covariances[b] - covariance[0]).square().sum()
                losses[-1] = losses[-1] + self.colour_weight * colour
        return torch.stack(losses).mean()


def build(args) -> tuple[TextureSpace, torch.nn.Parameter | None, dict]:
    cfg = ModelConfig(variant=args.variant, dims=args.dims, nearest_input=not args.no_nearest,
                      smooth=args.smooth, exemplar_short_side=args.short_side, grain=args.grain,
                      colour_blind_encoder=args.colour_normalise, isotropic_transforms=args.isotropic_transforms)
    model = TextureSpace(cfg)
    state = {}
    if args.init:
        init, ckpt = load_checkpoint(args.init)
        # A grain fit starts from an isotropic space: the stretch is a fixed input transform;
        # a colour-normalised run may start from a space whose encoder still read colour.
        if init.cfg.to_dict() | {"grain": cfg.grain, "colour_blind_encoder": cfg.colour_blind_encoder,
                                 "isotropic_transforms": cfg.isotropic_transforms} != cfg.to_dict():
            raise SystemExit(f"--init config {init.cfg.to_dict()} differs from this run's {cfg.to_dict()}")
        model.load_state_dict(init.state_dict())
        state["init"] = str(args.init)
        state["init_codes"] = ckpt.get("codes")  # a space's learned code table, if it has one
    code = torch.nn.Parameter(torch.zeros(1, cfg.code_size)) if args.mode == "single" else None
    return model, code, state


def initial_code(model: TextureSpace, image: np.ndarray, crop: int, rng) -> torch.Tensor:
    """The encoder's code for an exemplar: mean over a few crops."""
    crops = sample_batch([image], 8, crop, rng, flips=False, rotations=False)
    device = next(model.parameters()).device
    with torch.no_grad():
        return model.encode(torch.from_numpy(crops).to(device) * 2 - 1).mean(0, keepdim=True)


def resolve_device(name: str) -> torch.device:
    """``auto`` | ``cpu`` | ``cuda`` -> a torch device; ``cuda`` without CUDA is an error."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda: this torch build or machine has no CUDA device (use cpu or auto)")
        # TF32 convolutions and matmuls: the VGG loss dominates a step, and its Gram targets
        # need no more than TF32's 10-bit mantissa. The noise stays exact int64 arithmetic.
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    return torch.device(name)


def to_cpu(value):
    """A copy of nested dicts / lists of tensors with every tensor on the CPU (checkpoints)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: to_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_cpu(v) for v in value)
    return value


def learning_rate(step: int, base: float, warmup: int, decay: tuple[int, int] | None = None) -> float:
    """Linear warm-up over ``warmup`` steps; then, with ``decay = (start, end)``, a linear
    fall to 10% between those steps (the GPU space's loss went flat at a constant rate)."""
    rate = base * min(1.0, (step + 1) / max(1, warmup))
    if decay is not None and step > decay[0]:
        rate *= 1.0 - 0.9 * min(1.0, (step - decay[0]) / max(1, decay[1] - decay[0]))
    return rate


def train(args, progress=None) -> Path:
    """Run (or resume) training; ``progress(fraction)`` is called after every step."""
    device = resolve_device(args.device)  # first: a missing GPU fails before any loading
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"

    if args.mode == "single":
        if not args.exemplar:
            raise SystemExit("--mode single needs --exemplar IMAGE")
        names, images = [Path(args.exemplar).stem], [load_exemplar(args.exemplar, args.short_side)]
    else:
        dataset = TextureDataset(args.data, short_side=args.short_side)
        excluded = set(filter(None, args.exclude.split(",")))
        kept = [k for k, name in enumerate(dataset.names) if name not in excluded]
        names, images = [dataset.names[k] for k in kept], [dataset.images[k] for k in kept]
    crop = min(args.crop, *(min(im.shape[:2]) for im in images))

    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    model, code, meta = build(args)
    model.to(device)
    if code is not None:
        code = torch.nn.Parameter(code.data.to(device))
    if code is not None and args.init:
        code.data.copy_(initial_code(model, images[0], crop, rng))
    # Space mode learns one code per exemplar (an auto-decoder table) that the synthesis
    # uses, and trains the encoder to predict those codes from crops. Gradients reach
    # each code directly; through the encoder alone they were too weak, and a CPU-hours
    # space ignored the code and collapsed to one texture.
    if code is None:
        code_table = torch.nn.Parameter((torch.randn(len(images), model.cfg.code_size, generator=torch.Generator()
                                                     .manual_seed(args.seed)) * 0.5).to(device))
        init_codes = meta.get("init_codes")
        if init_codes is not None and tuple(init_codes.shape) == tuple(code_table.shape):
            code_table.data.copy_(init_codes)  # warm start: the decoder knows these codes
        codes = code_table
    else:
        code_table, codes = None, code
    synthesis_params = list(model.field.parameters()) + [codes]
    # Group order is part of the checkpoint format (resuming needs the same groups), so
    # the transform head gets its own group only when it has its own learning rate.
    head = list(model.field.translator.to_transform.parameters()) if args.transform_lr else []
    head_ids = {id(t) for t in head}
    params = [{"params": [t for t in model.field.parameters() if id(t) not in head_ids], "base_lr": args.lr},
              {"params": [codes], "base_lr": args.code_lr}]
    if head:
        params.append({"params": head, "base_lr": args.transform_lr})
    if code_table is not None:
        params.append({"params": list(model.encoder.parameters()), "base_lr": args.lr})
    optimizer = torch.optim.Adam(params, lr=args.lr)

    step, wall, history = 0, 0.0, []
    if ckpt_path.exists():  # resume
        ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if "optimizer" not in ckpt:
            raise SystemExit(f"{ckpt_path} holds weights only (an exported space.pt?), not a training "
                             "checkpoint: start a new --out with --init FILE instead")
        saved = ModelConfig(**ckpt["config"]).to_dict()  # (fills fields added since it was written)
        if saved != model.cfg.to_dict():
            changed = sorted(k for k in saved if saved[k] != model.cfg.to_dict().get(k))
            raise SystemExit(f"{ckpt_path} was trained with other settings ({', '.join(changed)}); resume it "
                             "with the same flags, or start a new --out with --init")
        model.load_state_dict(ckpt["model"])
        base_lrs = [group["base_lr"] for group in optimizer.param_groups]
        optimizer.load_state_dict(ckpt["optimizer"])  # casts the (CPU) moments to each parameter's device
        for group, base_lr in zip(optimizer.param_groups, base_lrs):  # this run's rates, not the saved ones
            group["base_lr"] = base_lr
        codes.data.copy_(ckpt["code"] if code is not None else ckpt["codes"])
        step, wall = ckpt["step"], ckpt.get("wall_seconds", 0.0)
        rng.bit_generator.state = ckpt["numpy_rng"]
        torch.set_rng_state(ckpt["torch_rng"])
        print(f"resumed {ckpt_path} at step {step}")

    # Position-input baselines (mlp, oursP) only work near the origin they saw in training;
    # noise-only models are trained everywhere, which is what makes them infinite.
    extent = POSITION_EXTENT if model.cfg.flags.position else 1000.0
    objective = Objective(images, tuple(args.layers.split(",")), args.loss, args.colour_weight,
                          args.colour_normalise, device)
    log = (out / "log.jsonl").open("a")

    extra = {}  # more checkpoint fields (the probe's choice)

    def save():
        ckpt = {
            "config": model.cfg.to_dict(), "model": to_cpu(model.state_dict()),
            "optimizer": to_cpu(optimizer.state_dict()),
            "step": step, "wall_seconds": wall, "numpy_rng": rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(), "mode": args.mode, "data": names,
            "loss": args.loss, "layers": args.layers, "args": vars(args),
            "final_loss": float(np.mean(history[-50:])) if history else None,
        }
        ckpt.update(extra)
        if code is not None:
            ckpt["code"] = to_cpu(code)
        else:
            ckpt["codes"] = to_cpu(code_table)
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save(ckpt, tmp)
        tmp.replace(ckpt_path)

    # A fit keeps its best state, scored by its own objective on fixed planes and seeds (not
    # the random ones of training, whose loss is too noisy to compare). A short fit at a
    # fit's learning rate can first move away from a code that already matched well.
    probe = None
    if args.probe_every and code is not None:
        probe_origins, probe_axes = random_planes(4, np.random.default_rng(12345), oblique_fraction=args.oblique,
                                                  dims=args.dims, extent=extent, grain=args.grain)
        probe_origins, probe_axes = probe_origins.to(device), probe_axes.to(device)
        probe_seeds = torch.arange(4, dtype=torch.int64, device=device) + 7

        def probe_score() -> float:
            with torch.no_grad():
                patches = render_slices(model.field, code.expand(4, -1), probe_seeds, probe_origins, probe_axes,
                                        args.patch * 2)
                return float(objective(patches, np.zeros(4, dtype=np.int64)))

        def snapshot() -> dict:
            return {"model": {k: v.detach().clone() for k, v in model.state_dict().items()},
                    "code": code.detach().clone(), "step": step}

        probe = {"score": probe_score(), "state": snapshot()}
        log.write(json.dumps({"step": step, "probe": round(probe["score"], 5)}) + "\n")

        def probe_update() -> None:
            score = probe_score()
            log.write(json.dumps({"step": step, "probe": round(score, 5)}) + "\n")
            if score < probe["score"]:
                probe.update(score=score, state=snapshot())

    stop = {"now": False}
    if threading.current_thread() is threading.main_thread():  # a job thread cannot own signals
        signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    started = time.monotonic()
    timed = bool(args.minutes)
    deadline = started + args.minutes * 60 if timed else math.inf
    total = args.steps
    # A run bounded by time (a fit) shows seconds of its budget, not steps out of --steps,
    # whose default (100,000) would promise an ETA of hours.
    bar = (tqdm(total=round(args.minutes * 60), disable=args.quiet, dynamic_ncols=True, unit="s",
                bar_format="{l_bar}{bar}| {n:.0f}/{total} s [{elapsed}<{remaining}{postfix}]") if timed
           else tqdm(total=total, initial=step, disable=args.quiet, dynamic_ncols=True, unit="step"))
    model.train()
    try:
        while step < total and time.monotonic() < deadline and not stop["now"]:
            t0 = time.monotonic()
            crops, indices = sample_batch(images, args.batch, crop, rng, return_indices=True,
                                          rotations=not (args.no_rotations or args.grain))
            if code_table is not None:
                z = code_table[torch.from_numpy(indices).to(device)]
                if args.colour_normalise:  # a colour-blind encoder also ignores tone curves
                    crops = crops ** rng.uniform(0.7, 1.4, (len(crops), 1, 1, 1)).astype(np.float32)
                predicted = model.encode(torch.from_numpy(crops).to(device) * 2 - 1)
                encoder_loss = (predicted - z.detach()).square().mean()
            else:
                z = code.expand(args.batch, -1)
                encoder_loss = torch.zeros((), device=device)
            origins, axes = random_planes(args.batch, rng, oblique_fraction=args.oblique, dims=args.dims,
                                          extent=extent, grain=args.grain)
            origins, axes = origins.to(device), axes.to(device)
            seeds = torch.from_numpy(rng.integers(0, 2**31, size=args.batch)).to(device)
            synth = render_slices(model.field, z, seeds, origins, axes, args.patch)
            loss = objective(synth, indices)

            decay = (args.decay_start, args.decay_end or total) if args.decay_start is not None else None
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(step, group["base_lr"], args.warmup, decay)
            optimizer.zero_grad(set_to_none=True)
            (loss + encoder_loss).backward()
            # Clip the synthesis gradients only: the encoder's regression loss is separate.
            grad_norm = torch.nn.utils.clip_grad_norm_(synthesis_params, args.clip)
            optimizer.step()

            step += 1
            wall += time.monotonic() - t0
            history.append(loss.item())
            # Output spread across the batch: a collapse to flat colour shows as ~0 here.
            spread = float(synth.detach().std(dim=(2, 3)).mean())
            elapsed = time.monotonic() - started
            bar.set_postfix(step=step, loss=f"{np.mean(history[-20:]):.3f}", std=f"{spread:.3f}", refresh=False)
            bar.update(min(bar.total, elapsed) - bar.n if timed else 1)
            log.write(json.dumps({"step": step, "loss": round(loss.item(), 5), "std": round(spread, 4),
                                  "encoder": round(encoder_loss.item(), 5),
                                  "grad": round(float(grad_norm), 4), "wall": round(wall, 1)}) + "\n")
            if progress is not None:
                by_time = elapsed / (deadline - started) if timed else 0.0
                progress(min(1.0, max(step / total, by_time)))
            if probe is not None and step % args.probe_every == 0:
                probe_update()
            if step % args.ckpt_every == 0:
                save()
                log.flush()
    finally:
        bar.close()
        if probe is not None:
            if step % args.probe_every:
                probe_update()
            best = probe["state"]
            model.load_state_dict(best["model"])
            code.data.copy_(best["code"])
            extra["probe"] = {"score": probe["score"], "step": best["step"]}
        save()
        log.close()
    return ckpt_path


def main(argv=None):
    args = parse_args(argv)
    path = train(args)
    print(f"checkpoint: {path}")


if __name__ == "__main__":
    main()
