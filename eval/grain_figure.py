"""The model card's wood picture: a grain fit seen on the three axis planes.

    make grain-figure       # fits miniworld_wood_1 with --grain y, then draws this

One row: the exemplar (256 px centre crop at working resolution) | the fitted solid on
the xy plane (what tiles show) at seeds 1 and 2 | the xz plane (across the grain: end
grain) | the yz plane (along the grain, seen from the side). Rendered with the fit's own
PyTorch weights (fit.pt), which the test suite holds equal to its sampler.onnx.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from model.data import load_exemplar
from model.evaluate import centre_crop
from model.networks import load_checkpoint
from model.slices import render_slices

SIZE = 256
PANELS = [  # label, seed, plane axes (u, v) as world axis indices
    ("xy, seed 1 (tiles)", 1, (0, 1)),
    ("xy, seed 2", 2, (0, 1)),
    ("xz (across grain)", 1, (0, 2)),
    ("yz (along grain)", 1, (2, 1)),
]


def main(fit_dir: str = "runs/fits-grain/miniworld_wood_1", image: str = "data/textures/val/miniworld_wood_1.png",
         out: str = "docs/images/wood-grain.png") -> None:
    model, ckpt = load_checkpoint(Path(fit_dir) / "fit.pt")
    exemplar = load_exemplar(image, model.cfg.exemplar_short_side)
    n = len(PANELS)
    axes = torch.zeros(n, 2, 3, dtype=torch.float64)
    for k, (_, _, (u, v)) in enumerate(PANELS):
        axes[k, 0, u] = axes[k, 1, v] = 1.0
    origins = torch.full((n, 3), 0.37, dtype=torch.float64)
    seeds = torch.tensor([seed for _, seed, _ in PANELS])
    with torch.no_grad():
        slices = render_slices(model.field, ckpt["code"].expand(n, -1), seeds, origins, axes, SIZE)
    tiles = [centre_crop(exemplar, SIZE)] + list(slices.permute(0, 2, 3, 1).numpy())
    labels = ["exemplar"] + [label for label, _, _ in PANELS]
    gap, header = 4, 16
    sheet = Image.new("RGB", (len(tiles) * (SIZE + gap) - gap, SIZE + header), "white")
    draw = ImageDraw.Draw(sheet)
    for k, (tile, label) in enumerate(zip(tiles, labels)):
        sheet.paste(Image.fromarray((np.clip(tile, 0, 1) * 255).round().astype(np.uint8)), (k * (SIZE + gap), header))
        draw.text((k * (SIZE + gap) + 2, 2), label, fill="black")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:])
