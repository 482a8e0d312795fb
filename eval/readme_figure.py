"""The README's picture: exemplar photos beside tiles synthesised from their codes.

    make readme-figure      # needs `make data` (the photos) and the shipped model
    python -m eval.readme_figure [OUT] [--fits DIR]

Each row: the exemplar at the model's working resolution (256 px crop) | native-zoom
tile 6/0/0 (256 px) at seed 1 | the same tile at seed 2, all through the service's own
code path (worker.encode.encode_texture: code + colour table; worker.tiles), so the
picture shows what the API serves for an upload before its refinement fit. With
``--fits DIR`` (``model.fit`` outputs, DIR/<photo stem>/, as ``make fits`` writes them)
the last column is tile 6/0/0 at seed 1 of the photo's fitted sampler instead, with a
colour table computed for it: what the API serves once the upload's refinement is done.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from worker.colour import linear_to_srgb8
from worker.colour_match import texture_vector
from worker.encode import encode_texture
from worker.images import read_image
from worker.photo import resize_short_side
from worker.colour_match import calibrate_texture
from worker.runtime import ModelRuntime, SamplerSession
from worker.tiles import NATIVE_ZOOM, render_tile

ROOT = Path(__file__).resolve().parents[1]
ROWS = [("data/textures/val/vpython_granite.png", "validation photo (not trained on)"),
        ("data/textures/val/miniworld_brick_wall_1.png", "validation photo"),
        ("data/textures/val/miniworld_wood_1.png", "validation photo"),
        ("data/textures/val/vpython_gravel.png", "validation photo"),
        ("data/textures/val/miniworld_grass_2.png", "validation photo"),
        ("data/textures/val/miniworld_floor_tiles_white.png", "validation photo")]


def fitted_tile(fit_dir: Path, image: np.ndarray, short_side: int, pixels_per_unit: float) -> np.ndarray:
    """Tile 6/0/0 at seed 1 of a fitted sampler, with a colour table computed for it."""
    import json

    session = SamplerSession(fit_dir / "sampler.onnx")
    code = np.asarray(json.loads((fit_dir / "code.json").read_text())["code"], np.float32)
    vector = texture_vector(code, calibrate_texture(session, code, resize_short_side(image, short_side),
                                                   curves="linear"))
    return render_tile(session, vector, 1, NATIVE_ZOOM, 0, 0, 256, pixels_per_unit=pixels_per_unit)


def main(out: str = "docs/images/exemplar-and-tile.png", fits: Path | None = None) -> None:
    runtime = ModelRuntime(ROOT / "model" / "weights")
    short_side = runtime.manifest["exemplar_short_side"]
    rows = []
    for path, _ in ROWS:
        image = read_image((ROOT / path).read_bytes(), max_pixels=1 << 26)
        code = texture_vector(*encode_texture(runtime, image))
        work = resize_short_side(image, short_side)[:256, :256]
        tiles = [linear_to_srgb8(render_tile(runtime, code, seed, NATIVE_ZOOM, 0, 0, 256)) for seed in (1, 2)]
        if fits is not None:
            tiles[1] = linear_to_srgb8(fitted_tile(Path(fits) / Path(path).stem, image, short_side,
                                                   runtime.pixels_per_unit))
        gap = np.full((256, 8, 3), 255, np.uint8)
        rows.append(np.concatenate([(work * 255 + 0.5).astype(np.uint8), gap, tiles[0], gap, tiles[1]], axis=1))
    figure = np.concatenate([np.concatenate([r, np.full((8, r.shape[1], 3), 255, np.uint8)]) for r in rows])[:-8]
    Image.fromarray(figure).save(ROOT / out)


if __name__ == "__main__":
    args = sys.argv[1:]
    fits = None
    if "--fits" in args:
        at = args.index("--fits")
        fits = Path(args[at + 1])
        del args[at:at + 2]
    main(*args, fits=fits)
