"""The README's picture: exemplar photos beside tiles synthesised from their codes.

    make readme-figure      # needs `make data` (the photos) and the shipped model

Each row: the exemplar at the model's working resolution (256 px crop) | native-zoom
tile 6/0/0 (256 px) at seed 1 | the same tile at seed 2, all through the service's own
code path (worker.images.encode_texture: code + colour table; worker.tiles), so the
picture shows what the API serves for an upload before its refinement fit.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from worker.colour import linear_to_srgb8
from worker.colour_match import texture_vector
from worker.images import encode_texture, read_image, resize_short_side
from worker.runtime import ModelRuntime
from worker.tiles import NATIVE_ZOOM, render_tile

ROOT = Path(__file__).resolve().parents[1]
ROWS = [("data/textures/val/vpython_granite.png", "validation photo (not trained on)"),
        ("data/textures/val/miniworld_brick_wall_1.png", "validation photo"),
        ("data/textures/val/miniworld_wood_1.png", "validation photo"),
        ("data/textures/val/vpython_gravel.png", "validation photo"),
        ("data/textures/train/miniworld_grass_1.png", "training photo")]


def main(out: str = "docs/images/exemplar-and-tile.png") -> None:
    runtime = ModelRuntime(ROOT / "model" / "weights")
    rows = []
    for path, _ in ROWS:
        image = read_image((ROOT / path).read_bytes(), max_pixels=1 << 26)
        code = texture_vector(*encode_texture(runtime, image))
        work = resize_short_side(image, runtime.manifest["exemplar_short_side"])[:256, :256]
        tiles = [linear_to_srgb8(render_tile(runtime, code, seed, NATIVE_ZOOM, 0, 0, 256)) for seed in (1, 2)]
        gap = np.full((256, 8, 3), 255, np.uint8)
        rows.append(np.concatenate([(work * 255 + 0.5).astype(np.uint8), gap, tiles[0], gap, tiles[1]], axis=1))
    figure = np.concatenate([np.concatenate([r, np.full((8, r.shape[1], 3), 255, np.uint8)]) for r in rows])[:-8]
    Image.fromarray(figure).save(ROOT / out)


if __name__ == "__main__":
    main(*sys.argv[1:])
