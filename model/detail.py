"""Detail octaves: a fitted texture keeps the fine detail of a photo larger than the working size.

A space and its fits work at ``exemplar_short_side`` (256 px): a 1024-px scan loses 15/16 of
its pixels, and its tiles above the native zoom are the 256-px texture magnified. A fit of such
a photo therefore ends with a detail stage (``fit_detail``), after the fit proper:

* the fitted field gets ``log2(factor)`` finer octaves (``grow_octaves``): octave k has 2^k cells
  a world unit, so at ``factor`` x the working resolution the new finest one has cells of two
  photo pixels, as the finest octave has at the working size. Their decoder columns start at
  zero, so the grown field is the fitted one, colour for colour;
* only those columns and the new octaves' transforms learn, on patches rendered at
  ``factor * pixels_per_unit`` pixels a unit against the photo read at ``factor`` x the working
  size. What the fit learned at the working size (colours, structure, scales) stays as it was;
* a probe on fixed planes at the detail scale keeps the stage only if it beats the start.

World units keep their meaning (one unit is the photo's short side), so every raster of the
texture keeps its framing: the detail shows at zooms above the native one (two zooms for
``factor`` 4), where the tiles of a fit without it are magnified.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import torch

from model.device import autocast
from model.networks import TextureSpace
from model.objective import Objective
from model.slices import random_planes, render_slices
from model.vgg import GATYS_LAYERS

#: at most this many times the working resolution (1024 px at a 256-px working size)
MAX_FACTOR = 4
# The new columns start at zero. 20-s stages on the validation grass (1024 px), style error at
# zoom 8 over the full photo's floor: 5e-3 26.6, 2e-2 27.2; training the rest of the decoder too
# (1e-3) 27.2: the frozen fit loses nothing.
DETAIL_LR = 5e-3
DETAIL_PATCH = 128  # px at the detail scale, as the fit's patches are at the working scale
COLOUR_WEIGHT = 50.0  # the fit's (model/train_config.py): the new columns may not move the colours


def detail_factor(height: int, width: int, short_side: int) -> int:
    """How many times the working size (``short_side``) a photo of height x width keeps: a power
    of two up to ``MAX_FACTOR`` that its short side reaches (1: none)."""
    factor = 1
    while factor * 2 <= MAX_FACTOR and min(height, width) >= factor * 2 * short_side:
        factor *= 2
    return factor


def grow_octaves(model: TextureSpace, count: int) -> TextureSpace:
    """The same texture with ``count`` more, finer octaves whose decoder columns are zero: it
    renders the same colours. Tensors that grow with the octaves (the transforms' head, the
    octave bases, the noise columns of the decoder; all octave-major) keep their first rows or
    columns; the new octaves' transforms start at the identity and their bases are a fresh
    field's (the bases are stored, so the grown model keeps them)."""
    grown = TextureSpace(replace(model.cfg, n_octaves=model.cfg.n_octaves + count)).to(
        next(model.parameters()).device)
    state = grown.state_dict()
    for key, value in model.state_dict().items():
        target = state[key]
        if target.shape == value.shape:
            state[key] = value.clone()
            continue
        fresh = target.clone()
        if key == "field.decoder.from_noise.weight":  # [hidden, K * per-octave]: new columns zero
            fresh.zero_()
            fresh[:, :value.shape[1]] = value
        elif key.startswith("field.translator.to_transform"):  # rows of K x D x D: new ones zero (identity)
            fresh.zero_()
            fresh[:value.shape[0]] = value
        else:  # octave_basis [K, D, D], the mix head [(K+1)*3, ...]: leading rows kept
            fresh[:value.shape[0]] = value
        state[key] = fresh
    grown.load_state_dict(state)
    return grown


def detail_parameters(model: TextureSpace, old_octaves: int) -> list[torch.Tensor]:
    """The grown octaves' decoder columns and transform rows: the only tensors the detail stage
    trains (hooks zero the gradients of the rest of each tensor; everything else is frozen)."""
    for tensor in model.parameters():
        tensor.requires_grad_(False)
    field = model.field
    per_octave = field.decoder.from_noise.weight.shape[1] // model.cfg.n_octaves
    columns = torch.zeros_like(field.decoder.from_noise.weight)
    columns[:, old_octaves * per_octave:] = 1
    d = model.cfg.dims
    head = field.translator.to_transform
    rows = torch.zeros(head.weight.shape[0], 1, dtype=head.weight.dtype, device=head.weight.device)
    rows[old_octaves * d * d:] = 1
    trained = [(field.decoder.from_noise.weight, columns), (head.weight, rows), (head.bias, rows[:, 0])]
    for tensor, mask in trained:
        tensor.requires_grad_(True)
        tensor.register_hook(lambda grad, mask=mask: grad * mask)
    return [tensor for tensor, _ in trained]


def fit_detail(model: TextureSpace, code: torch.Tensor, photo: np.ndarray, factor: int, *, seconds: float,
               device: torch.device, precision: torch.dtype | None, seed: int = 0,
               grain: str | None = None, photo_plane: bool = False, patch: int = DETAIL_PATCH,
               progress=None) -> tuple[TextureSpace, dict]:  # noqa: ANN001
    """Grow the fitted ``model`` by ``log2(factor)`` octaves and train them for ``seconds`` on
    ``photo`` (sRGB (H, W, 3) float32 at ``factor`` x the working size). ``grain`` and
    ``photo_plane`` (a lattice fit) draw the planes as the fit drew them; ``patch``: their side in
    pixels. Returns the grown model (or ``model`` itself where the stage did not beat its start on
    the probe) and ``{'factor', 'steps', 'start', 'score', 'kept'}``; ``progress(fraction)`` after
    each step."""
    count = int(round(math.log2(factor)))
    if factor < 2 or 2 ** count != factor:
        raise ValueError(f"factor must be a power of two >= 2, got {factor}")
    old = model.cfg.n_octaves
    grown = grow_octaves(model, count).to(device)
    grown.eval()
    ppu = grown.cfg.pixels_per_unit * factor
    objective = Objective([photo], tuple(GATYS_LAYERS), "gram", COLOUR_WEIGHT, grown.cfg.colour_blind_encoder,
                          device, precision=precision)
    optimizer = torch.optim.Adam(detail_parameters(grown, old), lr=DETAIL_LR)
    z = code.reshape(1, -1).to(device).detach()
    rng = np.random.default_rng(seed)
    planes = dict(oblique_fraction=0.5, dims=grown.cfg.dims, grain=grain, photo_plane=photo_plane)
    probe_origins, probe_axes = random_planes(2, np.random.default_rng(12345), extent=1000.0, **planes)
    probe_seeds = torch.tensor([7, 8], dtype=torch.int64, device=device)

    def probe() -> float:  # the objective on fixed planes at twice the patch, as the fit's probe
        with torch.no_grad(), autocast(device, precision):
            patches = render_slices(grown.field, z.expand(2, -1), probe_seeds, probe_origins.to(device),
                                    probe_axes.to(device), patch * 2, pixels_per_unit=ppu).float()
        return float(objective(patches, np.zeros(2, dtype=np.int64)))

    start = probe()
    steps, began, spent = 0, time.monotonic(), 0.0
    while spent < seconds:
        for group in optimizer.param_groups:  # falling to 10% over the budget, as the fit's rates
            group["lr"] = DETAIL_LR * (1.0 - 0.9 * min(1.0, spent / seconds))
        origins, axes = random_planes(1, rng, extent=1000.0, **planes)
        seeds = torch.from_numpy(rng.integers(0, 2**31, size=1)).to(device)
        with autocast(device, precision):
            synth = render_slices(grown.field, z, seeds, origins.to(device), axes.to(device), patch,
                                  pixels_per_unit=ppu).float()
        loss = objective(synth, np.zeros(1, dtype=np.int64))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        steps += 1
        spent = time.monotonic() - began
        if progress is not None:
            progress(min(1.0, spent / seconds))
    score = probe()
    for tensor in grown.parameters():
        tensor.requires_grad_(False)
    kept = score < start
    stats = {"factor": factor, "steps": steps, "start": round(start, 6), "score": round(score, 6), "kept": kept}
    return (grown if kept else model), stats
