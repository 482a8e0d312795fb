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

Space and single mode differ in five places, each marked ``cfg.mode``: the exemplars
(load_exemplars: a folder or one image), the codes (learned_codes: a table, one row per
exemplar, or one code), the optimiser (make_optimizer: the encoder trains in space mode
only), the step (train_step: space mode regresses the encoder onto the table), and the
probe (Probe: single mode only).
"""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np
import torch
from tqdm import tqdm

from model.config import ModelConfig
from model.data import TextureDataset, load_exemplar, sample_batch
from model.device import autocast, resolve_device, resolve_precision
from model.lattice import lattice_mean_cell, lattice_pixels, mean_cell_share
from model.networks import TextureSpace, load_checkpoint
from model.objective import Objective
from model.probe import Interim, Probe
from model.slices import lattice_partners, plane_points, random_planes, render_slices
from model.train_config import TrainConfig, parse_args
from worker.photo import encoder_crops


POSITION_EXTENT = 4.0  # world units around the origin where position-input variants train

def start_on_mean_cell(model: TextureSpace, code: torch.Tensor, share: float, rng: np.random.Generator,
                       patch: int = 64, planes: int = 4) -> None:
    """Start a fresh lattice fit drawing the photo's mean repeat cell: the decoder's output
    weights are scaled by sqrt(1 - share^2), then its mean-cell weights (the last 3 columns
    of ``from_phase``, zero until now) are set so that, to first order, its colour moves
    along the standardised cell by ``share`` of the texture's former spread: the grout and
    bond are drawn where the photo has them, dark where they are dark, from the first step,
    and the space's own texture keeps the rest of the spread. From zero weights the sign was
    left to the first noisy steps: half the 60-s fits of the validation floor tiles drew
    light grout and grey blotches in every tile, and stayed there (4-minute fits too).
    Adding the cell without making room for it gave the grill speckled metal.
    ``share``: ``mean_cell_share`` of the photo. The map is the pseudo-inverse of the mean
    Jacobian of colour with respect to the first hidden layer, on ``planes`` random
    photo-plane patches."""
    field = model.field
    device = code.device
    share = min(share, 0.99)  # (an exactly periodic photo: keep a little of the texture to steer)
    origins, axes = random_planes(planes, rng, photo_plane=True)
    points = plane_points(origins.to(device), axes.to(device), patch, field.cfg.pixels_per_unit)
    seeds = torch.from_numpy(rng.integers(0, 2**31, size=planes)).to(device)
    z = code.detach().expand(planes, -1)
    with torch.no_grad():
        spread = field(points, z, seeds).reshape(-1, 3).std(dim=0).mean()
        field.decoder.out.weight.mul_(math.sqrt(max(1.0 - share**2, 0.0)))  # room for the cell's share
    delta = torch.zeros(field.decoder.from_code.out_features, device=device, requires_grad=True)
    hook = field.decoder.from_code.register_forward_hook(lambda module, inputs, output: output + delta)
    try:
        rgb = field(points, z, seeds)  # [B,P,3] linear
        jacobian = torch.stack([torch.autograd.grad(rgb[..., k].mean(), delta, retain_graph=True)[0]
                                [:field.decoder.hidden] for k in range(3)])  # [3,H]
    finally:
        hook.remove()
    gram = jacobian @ jacobian.T
    ridge = (1e-6 * gram.trace() + 1e-12) * torch.eye(3, device=device)
    weight = (share * spread) * jacobian.T @ torch.linalg.inv(gram + ridge)
    with torch.no_grad():
        field.decoder.from_phase.weight[:, -3:] = weight


def load_exemplars(cfg: TrainConfig) -> tuple[list[str], list[np.ndarray]]:
    """Names and (H, W, 3) float32 images at ``short_side``: the one --exemplar (single mode),
    or every image in --data but the --exclude'd ones (space mode)."""
    if cfg.mode == "single":
        if not cfg.exemplar:
            raise SystemExit("--mode single needs --exemplar IMAGE")
        # unquantised, as the upload was encoded: a fit starts from the code its texture serves
        return [Path(cfg.exemplar).stem], [load_exemplar(cfg.exemplar, None if cfg.exemplar_as_is else cfg.short_side,
                                                         quantise=False)]
    dataset = TextureDataset(cfg.data, short_side=cfg.short_side)
    excluded = set(filter(None, cfg.exclude.split(",")))
    kept = [k for k, name in enumerate(dataset.names) if name not in excluded]
    return [dataset.names[k] for k in kept], [dataset.images[k] for k in kept]


def build(cfg: TrainConfig, mean_cell: np.ndarray | None = None) -> tuple[TextureSpace, torch.Tensor | None]:
    """The model, with --init's weights when given, and --init's learned code table (None
    when it has none). Draws from torch's RNG (weight init), so it comes right after seeding.
    ``mean_cell``: a lattice fit's ``lattice_mean_cell`` of its photo."""
    model_cfg = ModelConfig(variant=cfg.variant, dims=cfg.dims, code_size=cfg.code_size,
                            encoder_width=cfg.encoder_width, hidden=cfg.hidden, nearest_input=not cfg.no_nearest,
                            smooth=cfg.smooth, exemplar_short_side=cfg.short_side, grain=cfg.grain,
                            grain_stretch=cfg.grain_stretch,
                            colour_blind_encoder=cfg.colour_normalise, isotropic_transforms=cfg.isotropic_transforms,
                            warp=cfg.warp, lattice=cfg.lattice,
                            lattice_shade=cfg.lattice_shade and cfg.lattice is not None,
                            lattice_cell=mean_cell.shape[:2] if mean_cell is not None else None)
    model = TextureSpace(model_cfg)
    if mean_cell is not None:
        model.field.lattice_mean_cell.copy_(torch.from_numpy(mean_cell))
    if not cfg.init:
        return model, None
    init, ckpt = load_checkpoint(cfg.init)
    # A grain fit starts from an isotropic space: the stretch is a fixed input transform;
    # a lattice fit adds phase inputs (zero weights; setup starts the mean cell's: start_on_mean_cell);
    # a colour-normalised run may start from a space whose encoder still read colour.
    if init.cfg.to_dict() | {"grain": model_cfg.grain, "grain_stretch": model_cfg.grain_stretch,
                             "colour_blind_encoder": model_cfg.colour_blind_encoder,
                             "isotropic_transforms": model_cfg.isotropic_transforms,
                             "warp": model_cfg.warp,
                             "lattice": model_cfg.lattice, "lattice_cell": model_cfg.lattice_cell,
                             "lattice_shade": model_cfg.lattice_shade} != model_cfg.to_dict():
        raise SystemExit(f"--init config {init.cfg.to_dict()} differs from this run's {model_cfg.to_dict()}")
    missing, unexpected = model.load_state_dict(init.state_dict(), strict=False)
    new = {"field.decoder.from_phase.weight"} if model_cfg.lattice and not init.cfg.lattice else set()
    new |= {"field.lattice_mean_cell"} if model_cfg.lattice_cell and not init.cfg.lattice_cell else set()
    new |= {"field.warp"} if model_cfg.warp and not init.cfg.warp else set()
    if unexpected or set(missing) != new:
        raise SystemExit(f"--init weights do not fit this model: missing {missing}, unexpected {unexpected}")
    if model.field.warp is not None and cfg.warp_start:
        model.field.warp.data.copy_(lean_warp(*cfg.warp_start) - torch.eye(2, dtype=torch.float64))
    return model, ckpt.get("codes")  # a space's learned code table, if it has one


def lean_warp(degrees: float, stretch: float) -> torch.Tensor:
    """float64 [2,2]: the map of world (x, y) under which the noise, and so every feature,
    is ``stretch`` times longer along the direction ``degrees`` from +x towards +y (world y
    runs down the photo's rows, so the angle is the photo's, as ``photo_lean`` measures it)."""
    u = torch.tensor([np.cos(np.radians(degrees)), np.sin(np.radians(degrees))], dtype=torch.float64)
    return torch.eye(2, dtype=torch.float64) + (1.0 / stretch - 1.0) * torch.outer(u, u)


def initial_code(model: TextureSpace, image: np.ndarray, crop: int) -> torch.Tensor:
    """The encoder's code for an exemplar as an upload gets it: the mean over the same grid of
    crops (``worker.photo.encoder_crops``, the image already at its working size). A fit then
    starts from the code its texture serves, so its probe's "never worse than the start" holds
    for what users saw. With 8 random crops instead, a 60-s grass fit that kept its start still
    scored 0.0144 against the served code's 0.0137 (the codes 0.1 apart). Single mode reads its
    photo unquantised (``load_exemplar``), as the upload was encoded."""
    crops = encoder_crops(image, short_side=min(image.shape[:2]), size=crop)
    device = next(model.parameters()).device
    with torch.no_grad():
        return model.encode(torch.from_numpy(crops).to(device)).mean(0, keepdim=True)


def learned_codes(cfg: TrainConfig, model: TextureSpace, images: list[np.ndarray], crop: int,
                  init_codes: torch.Tensor | None) -> torch.nn.Parameter:
    """The codes the synthesis reads, learned directly (on the model's device).

    single: one code [1, code_size]; zeros, or with --init ``start_code`` (the code an upload
    stores: ``worker.encode`` chooses it among the encoder's codes) or else the encoder's mean
    code for the exemplar (``initial_code``).
    space: one code per exemplar [N, code_size], an auto-decoder table: N(0, 0.5^2) from
    --seed (a generator of its own), or --init's table where it has the same shape (warm
    start: the decoder knows these codes). With --init on other photos (a larger corpus) the
    table starts at --init's encoder codes of them (``initial_code``): codes the decoder
    already renders as those photos, where random rows would first undo what it learned.
    The encoder is trained to predict them from crops.
    Gradients reach each code directly; through the encoder alone they were too weak, and
    a CPU-hours space ignored the code and collapsed to one texture.
    """
    device = next(model.parameters()).device
    if cfg.mode == "single":
        code = torch.nn.Parameter(torch.zeros(1, model.cfg.code_size).to(device))
        if cfg.init and cfg.start_code is not None:
            if len(cfg.start_code) != model.cfg.code_size:
                raise SystemExit(f"--start-code has {len(cfg.start_code)} numbers; the space's codes have "
                                 f"{model.cfg.code_size}")
            code.data.copy_(torch.tensor(cfg.start_code, dtype=torch.float32).reshape(1, -1))
        elif cfg.init:
            code.data.copy_(initial_code(model, images[0], crop))
        return code
    table = torch.nn.Parameter((torch.randn(len(images), model.cfg.code_size,
                                            generator=torch.Generator().manual_seed(cfg.seed)) * 0.5).to(device))
    if init_codes is not None and tuple(init_codes.shape) == tuple(table.shape):
        table.data.copy_(init_codes)
    elif cfg.init:
        table.data.copy_(torch.cat([initial_code(model, image, crop) for image in images]))
    return table


def make_optimizer(cfg: TrainConfig, model: TextureSpace, codes: torch.nn.Parameter) -> torch.optim.Adam:
    """Adam over the field, the codes, (with --transform-lr) the transform head and (space
    mode) the encoder; each group carries its ``base_lr`` for the schedule."""
    # Group order is part of the checkpoint format (resuming needs the same groups), so
    # the transform head gets its own group only when it has its own learning rate.
    # (a lattice fit's phase weights, new to it, move as fast as the transforms)
    phase = model.field.decoder.from_phase if model.field.decoder is not None else None
    warp = model.field.warp  # (a fit's lean moves as fast as the transforms too)
    head = [*model.field.translator.to_transform.parameters(), *(phase.parameters() if phase is not None else ()),
            *([warp] if warp is not None else ())] if cfg.transform_lr else []
    head_ids = {id(t) for t in head}
    groups = [{"params": [t for t in model.field.parameters() if id(t) not in head_ids], "base_lr": cfg.lr},
              {"params": [codes], "base_lr": cfg.code_lr}]
    if head:
        groups.append({"params": head, "base_lr": cfg.transform_lr})
    if cfg.mode == "space":
        groups.append({"params": list(model.encoder.parameters()), "base_lr": cfg.lr})
    return torch.optim.Adam(groups, lr=cfg.lr)


@dataclass
class Run:
    """A run in progress: what setup() builds, resume() restores, train_step() advances
    and save() writes. ``codes`` is the single code (single mode) or the table (space)."""

    cfg: TrainConfig
    device: torch.device
    out: Path
    names: list[str]  # exemplar names, in the order of ``images`` (and of the table's rows)
    images: list[np.ndarray]
    crop: int  # --crop, or less where an exemplar is smaller
    model: TextureSpace
    codes: torch.nn.Parameter
    optimizer: torch.optim.Adam
    rng: np.random.Generator  # every random draw of the steps
    extent: float  # world units around the origin where slice planes are drawn
    objective: Objective | None = None  # built after a resume (train)
    precision: torch.dtype | None = None  # autocast dtype of the decoder and VGG (None: float32)
    log: TextIO | None = None  # log.jsonl, open while train() runs
    step: int = 0
    wall: float = 0.0  # seconds spent in steps, over all runs of this checkpoint
    history: list[float] = field(default_factory=list)  # this run's step losses
    probe: dict | None = None  # the probe's choice {'score', 'step'}, once it made one
    # A fit that pauses (train's ``pause``) and resumes: the seconds of its budget spent before
    # this run, the probe's best state so far ({'score', 'model', 'code', 'step'}) and whether
    # the checkpoint is a pause (no best state restored: it holds the training state).
    budget_spent: float = 0.0
    probe_best: dict | None = None
    paused: bool = False

    @property
    def ckpt_path(self) -> Path:
        return self.out / "checkpoint.pt"


def setup(cfg: TrainConfig) -> Run:
    """Device, exemplars, model, codes and optimiser of a fresh run, seeded by --seed."""
    device = resolve_device(cfg.device)  # first: a missing GPU fails before any loading
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    names, images = load_exemplars(cfg)
    crop = min(cfg.crop, *(min(im.shape[:2]) for im in images))

    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    mean_cell = None
    if cfg.lattice and cfg.lattice_cell:
        mean_cell = lattice_mean_cell(images[0], lattice_pixels(cfg.lattice))
    model, init_codes = build(cfg, mean_cell)
    model.to(device)
    codes = learned_codes(cfg, model, images, crop, init_codes)
    # a fit's cell weights are still zero (its space has no lattice): start them on the mean cell
    if mean_cell is not None and cfg.mode == "single" and not model.field.decoder.from_phase.weight[:, -3:].any():
        start_on_mean_cell(model, codes, mean_cell_share(images[0], lattice_pixels(cfg.lattice)), rng)
    # Position-input baselines (mlp, oursP) only work near the origin they saw in training;
    # noise-only models are trained everywhere, which is what makes them infinite.
    extent = POSITION_EXTENT if model.cfg.flags.position else 1000.0
    return Run(cfg=cfg, device=device, out=out, names=names, images=images, crop=crop, model=model, codes=codes,
               optimizer=make_optimizer(cfg, model, codes), rng=rng, extent=extent,
               precision=resolve_precision(cfg.precision, device))


def resume(run: Run, path: Path) -> None:
    """Continue the training checkpoint at ``path``: weights, Adam moments, codes, step, wall
    time and both RNG states. Refuses weights-only files and other model settings."""
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if "optimizer" not in ckpt:
        raise SystemExit(f"{path} holds weights only (an exported space.pt?), not a training "
                         "checkpoint: start a new --out with --init FILE instead")
    saved = ModelConfig(**ckpt["config"]).to_dict()  # (fills fields added since it was written)
    if saved != run.model.cfg.to_dict():
        changed = sorted(k for k in saved if saved[k] != run.model.cfg.to_dict().get(k))
        raise SystemExit(f"{path} was trained with other settings ({', '.join(changed)}); resume it "
                         "with the same flags, or start a new --out with --init")
    run.model.load_state_dict(ckpt["model"])
    base_lrs = [group["base_lr"] for group in run.optimizer.param_groups]
    run.optimizer.load_state_dict(ckpt["optimizer"])  # casts the (CPU) moments to each parameter's device
    for group, base_lr in zip(run.optimizer.param_groups, base_lrs):  # this run's rates, not the saved ones
        group["base_lr"] = base_lr  # (and older checkpoints' groups have none)
    run.codes.data.copy_(ckpt["code"] if run.cfg.mode == "single" else ckpt["codes"])
    run.step, run.wall = ckpt["step"], ckpt.get("wall_seconds", 0.0)
    run.budget_spent, run.probe_best = ckpt.get("budget_seconds", 0.0), ckpt.get("probe_best")
    run.rng.bit_generator.state = ckpt["numpy_rng"]
    torch.set_rng_state(ckpt["torch_rng"])
    print(f"resumed {path} at step {run.step}")


def learning_rate(step: int, base: float, warmup: int, decay: tuple[int, int] | None = None,
                  time_done: float | None = None) -> float:
    """Linear warm-up over ``warmup`` steps; then, with ``decay = (start, end)``, a linear
    fall to 10% between those steps (the GPU space's loss went flat at a constant rate).
    ``time_done``, the share of a timed run's wall time spent, makes the same fall over the
    whole run instead: a fit does not know how many steps its minutes will hold."""
    rate = base * min(1.0, (step + 1) / max(1, warmup))
    if decay is not None and step > decay[0]:
        rate *= linear_fall((step - decay[0]) / max(1, decay[1] - decay[0]))
    if time_done is not None:
        rate *= linear_fall(time_done)
    return rate


def linear_fall(done: float) -> float:
    """The factor of a linear decay ``done`` (0..1, clamped) of the way from 1 to 0.1."""
    return 1.0 - 0.9 * min(1.0, max(0.0, done))


def train_step(run: Run, time_done: float | None = None) -> dict[str, float]:
    """One optimiser step on a fresh random batch. Returns its synthesis loss, the output
    spread ``std`` (a collapse to flat colour shows as ~0), the encoder's loss, the
    gradient norm before clipping and the decoder's learning rate (``time_done``: see
    learning_rate; --decay-by-time).

    Draws from ``run.rng`` in this order (a seed's losses depend on it): crops and their
    exemplars (single mode too, which uses only the indices), tone curves (space mode with
    --colour-normalise), slice planes, noise seeds.
    """
    cfg, model, device = run.cfg, run.model, run.device
    t0 = time.monotonic()
    crops, indices = sample_batch(run.images, cfg.batch, run.crop, run.rng, return_indices=True,
                                  rotations=not (cfg.no_rotations or cfg.grain or cfg.lattice))
    if cfg.mode == "space":  # each crop's code from the table; the encoder learns to predict it
        z = run.codes[torch.from_numpy(indices).to(device)]
        if cfg.colour_normalise:  # a colour-blind encoder also ignores tone curves
            crops = crops ** run.rng.uniform(0.7, 1.4, (len(crops), 1, 1, 1)).astype(np.float32)
        predicted = model.encode(torch.from_numpy(crops).to(device) * 2 - 1)
        encoder_loss = (predicted - z.detach()).square().mean()
    else:  # single: the one code for the whole batch; the encoder is not trained
        z = run.codes.expand(cfg.batch, -1)
        encoder_loss = torch.zeros((), device=device)
    origins, axes = random_planes(cfg.batch, run.rng, oblique_fraction=cfg.oblique, dims=cfg.dims,
                                  extent=run.extent, grain=cfg.grain, photo_plane=bool(cfg.lattice))
    seeds = torch.from_numpy(run.rng.integers(0, 2**31, size=cfg.batch)).to(device)
    pairs = run.objective.pairs and cfg.mode == "single"
    if pairs:  # each patch and its lattice partner (Objective's pair contrast)
        origins = torch.cat([origins, lattice_partners(origins, cfg.lattice, run.rng)])
        axes, seeds, z, indices = axes.repeat(2, 1, 1), seeds.repeat(2), z.repeat(2, 1), np.tile(indices, 2)
    with autocast(run.device, run.precision):  # the decoder's matrix products (the noise is float64/int32: untouched)
        synth = render_slices(model.field, z, seeds, origins.to(device), axes.to(device), cfg.patch).float()
    loss = run.objective(synth, indices, pairs=pairs)

    decay = (cfg.decay_start, cfg.decay_end or cfg.steps) if cfg.decay_start is not None else None
    for group in run.optimizer.param_groups:
        group["lr"] = learning_rate(run.step, group["base_lr"], cfg.warmup, decay, time_done)
    run.optimizer.zero_grad(set_to_none=True)
    (loss + encoder_loss).backward()
    # Clip the synthesis gradients only: the encoder's regression loss is separate.
    grad_norm = torch.nn.utils.clip_grad_norm_(list(model.field.parameters()) + [run.codes], cfg.clip)
    run.optimizer.step()

    run.step += 1
    run.wall += time.monotonic() - t0
    run.history.append(loss.item())
    spread = float(synth.detach().std(dim=(2, 3)).mean())
    return {"loss": loss.item(), "std": spread, "encoder": encoder_loss.item(), "grad": float(grad_norm),
            "lr": run.optimizer.param_groups[0]["lr"]}


def log_line(run: Run, stats: dict[str, float]) -> str:
    """A step's log.jsonl line."""
    return json.dumps({"step": run.step, "loss": round(stats["loss"], 5), "std": round(stats["std"], 4),
                       "encoder": round(stats["encoder"], 5), "grad": round(stats["grad"], 4),
                       "lr": float(f"{stats['lr']:.4g}"), "wall": round(run.wall, 1)}) + "\n"


class Budget:
    """When a run stops (--steps in total, --minutes of this run's wall time) and its progress bar.

    A run bounded by time (a fit) shows seconds of its budget, not steps out of --steps,
    whose default (100,000) would promise an ETA of hours.
    """

    def __init__(self, cfg: TrainConfig, step: int, spent: float = 0.0):
        # ``spent``: seconds of the budget used before this run (a fit resumed after a pause:
        # its minutes are its whole budget, and its rates fall over all of it)
        self.started, self.total, self.timed = time.monotonic() - spent, cfg.steps, bool(cfg.minutes)
        self.deadline = self.started + cfg.minutes * 60 if self.timed else math.inf
        self.bar = (tqdm(total=round(cfg.minutes * 60), initial=round(spent), disable=cfg.quiet, dynamic_ncols=True,
                         unit="s", bar_format="{l_bar}{bar}| {n:.0f}/{total} s [{elapsed}<{remaining}{postfix}]")
                    if self.timed
                    else tqdm(total=self.total, initial=step, disable=cfg.quiet, dynamic_ncols=True, unit="step"))

    def left(self, step: int) -> bool:
        return step < self.total and time.monotonic() < self.deadline

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def time_done(self) -> float:
        """The share of a timed run's wall time spent (0 for a run bounded by steps)."""
        return min(1.0, (time.monotonic() - self.started) / (self.deadline - self.started)) if self.timed else 0.0

    def advance(self, run: Run, stats: dict[str, float]) -> float:
        """Show a step on the bar; returns the fraction of the run done (by steps or by time)."""
        elapsed = time.monotonic() - self.started
        self.bar.set_postfix(step=run.step, loss=f"{np.mean(run.history[-20:]):.3f}", std=f"{stats['std']:.3f}",
                             refresh=False)
        self.bar.update(min(self.bar.total, elapsed) - self.bar.n if self.timed else 1)
        return min(1.0, max(run.step / self.total, self.time_done()))

    def close(self) -> None:
        self.bar.close()


def to_cpu(value):
    """A copy of nested dicts / lists of tensors with every tensor on the CPU (checkpoints)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: to_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_cpu(v) for v in value)
    return value


def save(run: Run) -> None:
    """Write the training checkpoint (CPU tensors) atomically: a crash never leaves half a file."""
    cfg = run.cfg
    ckpt = {
        "config": run.model.cfg.to_dict(), "model": to_cpu(run.model.state_dict()),
        "optimizer": to_cpu(run.optimizer.state_dict()),
        "step": run.step, "wall_seconds": run.wall, "numpy_rng": run.rng.bit_generator.state,
        "torch_rng": torch.get_rng_state(), "mode": cfg.mode, "data": run.names,
        "loss": cfg.loss, "layers": cfg.layers, "args": asdict(cfg),
        "final_loss": float(np.mean(run.history[-50:])) if run.history else None,
    }
    if run.probe is not None:
        ckpt["probe"] = run.probe
    if run.paused:  # resumable: the training state above, and the best state apart from it
        ckpt.update(paused=True, budget_seconds=run.budget_spent, probe_best=to_cpu(run.probe_best))
    ckpt["code" if cfg.mode == "single" else "codes"] = to_cpu(run.codes)
    tmp = run.ckpt_path.with_suffix(".tmp")
    torch.save(ckpt, tmp)
    tmp.replace(run.ckpt_path)


def mute_coarse_octaves(model: TextureSpace, count: int) -> None:
    """Silence the ``count`` coarsest noise octaves: their columns of the decoder's noise
    weights are zeroed and a gradient hook keeps them zero (Adam then never moves them), so
    the field varies only at the finer octaves' scales. The sampler graph is unchanged: a
    muted octave is still computed and multiplied by zeros. For photos even at large scales
    (``model.structure.detect_even``), whose fits otherwise keep the space's blotches."""
    if count <= 0 or model.field.decoder is None or model.field.decoder.from_noise is None:
        return
    weight = model.field.decoder.from_noise.weight  # [hidden, K * per-octave channels], octave-major
    columns = count * (weight.shape[1] // model.cfg.n_octaves)
    keep = torch.ones_like(weight)
    keep[:, :columns] = 0
    with torch.no_grad():
        weight.mul_(keep)
    weight.register_hook(lambda grad: grad * keep)


def train(cfg: TrainConfig, progress=None, interim: Interim | None = None, pause=None) -> Path:  # noqa: ANN001
    """Run (or resume) training; ``progress(fraction)`` is called after every step.
    ``interim``: a fit's first result, published from its probe while it goes on (``Interim``;
    single mode with ``--probe-every`` only). ``pause()``: asked once, at the interim's second
    (after it is published, if it is); True ends the run there with a resumable checkpoint (``"paused": True``: the
    training state, the seconds of the budget spent, the probe's best state apart), which
    ``train`` on the same ``--out`` continues, so that queued fits can reach their interims first."""
    run = setup(cfg)
    if run.ckpt_path.exists():
        resume(run, run.ckpt_path)
    # After the resume: the VGG's first construction in a process draws from torch's RNG.
    run.objective = Objective(run.images, tuple(cfg.layers.split(",")), cfg.loss, cfg.colour_weight,
                              cfg.colour_normalise, run.device, lattice_px=lattice_pixels(cfg.lattice),
                              spectrum_weight=cfg.spectrum, precision=run.precision)
    run.log = (run.out / "log.jsonl").open("a")
    probe = Probe(run) if cfg.probe_every and cfg.mode == "single" else None  # a fit keeps its best state
    # after the probe's first score: a fit whose muted steps never beat its start ends on the start
    mute_coarse_octaves(run.model, cfg.mute_octaves)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():  # a job thread cannot own signals
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    budget = Budget(cfg, run.step, run.budget_spent if cfg.mode == "single" else 0.0)
    run.model.train()
    ended = False  # the loop ran out or was stopped, rather than raising (a canceled fit's progress hook)
    try:
        while budget.left(run.step) and not stop.is_set():
            stats = train_step(run, budget.time_done() if cfg.decay_by_time else None)
            fraction = budget.advance(run, stats)
            run.log.write(log_line(run, stats))
            if progress is not None:
                progress(fraction)
            due = interim is not None and interim.due(budget.elapsed())
            if probe is not None and (run.step % cfg.probe_every == 0 or (due and not interim.done)):
                probe.update()
                if interim is not None and not interim.done:
                    interim.offer(probe, budget.elapsed())
            # at the interim's second, published or not (a start that stays best and holds no
            # structure has none): a fit that went on held the uploads behind it for its whole budget
            if due and pause is not None and pause():
                run.paused = True
                break
            if run.step % cfg.ckpt_every == 0:
                save(run)
                run.log.flush()
        ended = True
    finally:
        budget.close()
        if run.paused:
            run.budget_spent, run.probe_best = budget.elapsed(), probe.saved_best()
        elif probe is not None and ended:  # (a fit that raised ends now: no last score for a result nobody takes)
            if run.step % cfg.probe_every:  # the state after the last score
                probe.update()
            run.probe = probe.restore_best()
        save(run)
        run.log.close()
    return run.ckpt_path


def main(argv=None):
    path = train(parse_args(argv, description=__doc__))
    print(f"checkpoint: {path}")


if __name__ == "__main__":
    main()
