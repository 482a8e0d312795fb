"""Every option of a training run or fit (``TrainConfig``) and the ``python -m model.train``
flags that set them (``parse_args``): what a run is, apart from the loop that runs it
(model/train.py).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Literal, get_args

from model.config import VARIANTS, ModelConfig
from model.vgg import GATYS_LAYERS

Mode = Literal["space", "single"]
Loss = Literal["gram", "swd"]
Grain = Literal["x", "y"]
Device = Literal["auto", "cpu", "cuda"]
Precision = Literal["auto", "fp32", "bf16"]


@dataclass(kw_only=True)
class TrainConfig:
    """Every option of a run, one field per ``python -m model.train`` flag (``--short-side``
    is ``short_side``); what each means is in ``--help`` (parse_args). Checkpoints store it
    as a dict under ``"args"``, and resuming compares the model's part of it."""

    mode: Mode = "space"  # space: one decoder for many exemplars; single: fit one exemplar
    variant: str = "ours"
    dims: int = 3
    data: str = "data/textures/train"
    exemplar: str | None = None
    exemplar_as_is: bool = False
    exclude: str = "miniworld_metal_grill_2"
    out: str
    init: str | None = None
    start_code: list[float] | None = None  # single: the code to start from (None: initial_code's)
    steps: int = 100_000
    minutes: float | None = None
    batch: int = 4
    patch: int = 96
    crop: int = 128
    short_side: int = 256
    # Architecture of a space trained from scratch (with --init they must match its own):
    code_size: int = ModelConfig.code_size
    encoder_width: int = ModelConfig.encoder_width
    hidden: int = ModelConfig.hidden
    lr: float = 5e-4
    code_lr: float = 5e-3
    transform_lr: float | None = None
    warmup: int = 200
    clip: float = 1.0
    loss: Loss = "gram"
    layers: str = ",".join(GATYS_LAYERS)
    colour_weight: float = 50.0
    colour_normalise: bool = False
    isotropic_transforms: bool = False
    warp: bool = False
    warp_start: tuple[float, float] | None = None
    decay_start: int | None = None
    decay_end: int | None = None
    decay_by_time: bool = False
    oblique: float = 0.5
    no_nearest: bool = False
    smooth: bool = False
    no_rotations: bool = False
    grain: Grain | None = None
    grain_stretch: float = ModelConfig.grain_stretch  # of a grain fit (model.fit picks it: model.structure)
    lattice: tuple[float, float, float, float] | None = None
    lattice_cell: bool = False
    lattice_shade: bool = False
    seed: int = 0
    probe_every: int = 0
    spectrum: float = 0.0
    mute_octaves: int = 0
    ckpt_every: int = 200
    threads: int = 0
    device: Device = "cpu"
    precision: Precision = "auto"
    quiet: bool = False

    def __post_init__(self):
        # The CLI's choices, for configs built in code (model/fit.py) too.
        for name, allowed in (("mode", get_args(Mode)), ("variant", tuple(sorted(VARIANTS))), ("dims", (2, 3)),
                              ("loss", get_args(Loss)), ("grain", (None, *get_args(Grain))),
                              ("device", get_args(Device)), ("precision", get_args(Precision))):
            if getattr(self, name) not in allowed:
                raise SystemExit(f"{name}={getattr(self, name)!r}: choose from {', '.join(map(str, allowed))}")


def parse_args(argv=None, description: str | None = None) -> TrainConfig:
    """The TrainConfig of ``python -m model.train``'s flags; ``description``: its ``--help`` text."""
    # Defaults live in TrainConfig only: a flag not given stays out of the namespace.
    p = argparse.ArgumentParser(prog="python -m model.train", description=description, argument_default=argparse.SUPPRESS,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", choices=get_args(Mode))
    p.add_argument("--variant", choices=sorted(VARIANTS))
    p.add_argument("--dims", type=int, choices=[2, 3])
    p.add_argument("--data", help="folder of exemplar PNGs (space mode)")
    p.add_argument("--exemplar", help="image file (single mode)")
    p.add_argument("--exemplar-as-is", action="store_true",
                   help="read --exemplar at its own size, already at the working resolution (a fit's straightened photo)")
    p.add_argument("--exclude",
                   help="comma-separated exemplar names left out of space training (the default's "
                        "regular dot grid has ~30x the Gram loss of any other photo and steers a shared decoder)")
    p.add_argument("--out", required=True, help="run folder: checkpoint, log; resumed if it exists")
    p.add_argument("--init", help="checkpoint to start from (weights only; e.g. the space for a fit)")
    p.add_argument("--start-code", type=float, nargs="+",
                   help="single mode with --init: the code to start from (an upload's stored code); "
                        "default: the encoder's mean over the exemplar's crops")
    p.add_argument("--steps", type=int, help="stop after this many steps in total")
    p.add_argument("--minutes", type=float, help="stop after this much wall time (this run)")
    p.add_argument("--batch", type=int)
    p.add_argument("--patch", type=int, help="synthesised patch size (pixels)")
    p.add_argument("--crop", type=int, help="exemplar crop size fed to the encoder")
    p.add_argument("--short-side", type=int, help="exemplar working resolution")
    p.add_argument("--code-size", type=int, help="length of a texture's code z (a new space; --init: its own)")
    p.add_argument("--encoder-width", type=int,
                   help="channels of the encoder's stem; its stages widen to 8x that (weights grow as its square)")
    p.add_argument("--hidden", type=int, help="width of the decoder's hidden layers")
    p.add_argument("--lr", type=float)
    p.add_argument("--code-lr", type=float, help="learning rate of the codes (table or single)")
    p.add_argument("--transform-lr", type=float,
                   help="learning rate of the per-octave transform head (default: --lr); a fit raises it "
                        "so the octaves can stretch into grain within minutes")
    p.add_argument("--warmup", type=int)
    p.add_argument("--clip", type=float, help="global gradient-norm clip")
    p.add_argument("--loss", choices=get_args(Loss))
    p.add_argument("--layers")
    p.add_argument("--colour-weight", type=float,
                   help="weight of the sRGB colour mean + covariance match (0: VGG statistics only)")
    p.add_argument("--colour-normalise", action="store_true",
                   help="judge structure only: give every synthesised patch its exemplar's colour moments "
                        "before the loss (the sampler's colour table does the same at inference), "
                        "train a colour-blind encoder; --colour-weight is then unused")
    p.add_argument("--isotropic-transforms", action="store_true",
                   help="per-octave transforms keep only their isotropic scale (|det T|^(1/D) I): no learned "
                        "stretch direction, so 2D tiles do not lean")
    p.add_argument("--warp", action="store_true",
                   help="learn a linear map of world x, y before the noise (a fit's lean, ModelConfig.warp)")
    p.add_argument("--warp-start", type=float, nargs=2, metavar=("DEGREES", "STRETCH"),
                   help="the warp's start: features STRETCH times longer along DEGREES from +x towards +y "
                        "(default: the identity)")
    p.add_argument("--decay-start", type=int,
                   help="step at which the learning rates start to fall linearly, to 10%% at --decay-end")
    p.add_argument("--decay-end", type=int, help="step at which the decay ends (default: --steps)")
    p.add_argument("--decay-by-time", action="store_true",
                   help="with --minutes: the rates fall linearly to 10%% over the run's wall time")
    p.add_argument("--oblique", type=float, help="fraction of oblique slice planes")
    p.add_argument("--no-nearest", action="store_true", help="decoder gets interpolated noise only")
    p.add_argument("--smooth", action="store_true", help="smoothstep noise interpolation")
    p.add_argument("--no-rotations", action="store_true", help="exemplar crops keep their orientation")
    p.add_argument("--grain", choices=get_args(Grain),
                   help="anisotropic exemplar whose grain runs along the image's x (left-right) or y (up-down): "
                        "crops keep their orientation and every slice plane contains that world axis in the same "
                        "role, so tiles on the xy plane show the grain as the exemplar does")
    p.add_argument("--grain-stretch", type=float,
                   help="with --grain: how much longer every noise cell is along the grain (model.fit picks 8 or "
                        "16 from the photo: model.structure.grain_stretch)")
    p.add_argument("--lattice", type=lambda text: tuple(float(v) for v in text.split(",")),
                   help="regular exemplar (bricks, tiles): its repeat lattice, two vectors in world units "
                        "'ax,ay,bx,by' in the xy plane (model.fit detects it); the decoder also reads each "
                        "point's phase on it, and every slice is an xy plane in the photo's orientation; single "
                        "mode: patches come in pairs whole lattice steps apart (Objective's pair contrast)")
    p.add_argument("--mute-octaves", type=int,
                   help="silence the N coarsest noise octaves (mute_coarse_octaves; model.fit sets it for photos "
                        "even at large scales)")
    p.add_argument("--lattice-cell", action="store_true",
                   help="with --lattice: the decoder also reads the exemplar's mean repeat cell at each point's "
                        "phase (lattice_mean_cell; model.fit turns it on for every lattice fit)")
    p.add_argument("--lattice-shade", action="store_true",
                   help="with --lattice: the decoder also reads each repeat cell's own hashed shade "
                        "(ModelConfig.lattice_shade; model.fit turns it on for every lattice fit)")
    p.add_argument("--seed", type=int)
    p.add_argument("--probe-every", type=int,
                   help="single mode: every N steps (and at the start and end) score the exemplar on fixed "
                        "planes and seeds; the run ends on the best-scoring weights and code (0: off)")
    p.add_argument("--spectrum", type=float,
                   help="weight of the radial log power spectrum loss on each patch's luminance, times the "
                        "exemplar's Gram magnitude (model.losses.gram_energy; 0: off)")
    p.add_argument("--ckpt-every", type=int)
    p.add_argument("--threads", type=int, help="torch threads (0: torch default)")
    p.add_argument("--precision", choices=get_args(Precision),
                   help="arithmetic of the VGG loss and the decoder's matrix products: bf16 autocast (Gram "
                        "matrices, noise and optimiser stay float32/64) or fp32; auto (default): bf16 on CUDA "
                        "and on CPUs with native bfloat16 instructions (resolve_precision)")
    p.add_argument("--device", choices=get_args(Device),
                   help="where steps run (auto: cuda when available); checkpoints always hold CPU tensors")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return TrainConfig(**vars(p.parse_args(argv)))
