"""docs/API.md's bake picture: a brick wall fitted on its repeat lattice, on a sphere.

    make triplanar-figure    # fits miniworld_brick_wall_1 for 60 s, then draws this

Two spheres (0.75 world units in radius, seen from 34 degrees above, lit from the upper
left): the fitted solid itself at each surface point (``projection=solid``: the photo's
xy pattern drawn through z shows as rings of mortar on top) and the triplanar projection a
bake uses for lattice fits by default (``worker/triplanar.py``). Every pixel comes from the
fit's sampler.onnx through the worker with the colour table an upload gets, as a bake's do.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from worker.colour import linear_to_srgb
from worker.colour_match import calibrate_texture, texture_vector
from worker.images import read_image
from worker.photo import resize_short_side
from worker.runtime import ModelRuntime, SamplerSession
from worker.triplanar import sample_triplanar

SIZE, RADIUS, TILT, SEED = 384, 0.75, 0.6, 1
LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


def sphere_view(size: int, tilt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The visible hemisphere of a unit sphere in an orthographic view: (inside mask (S, S),
    view-space normals (N, 3), world normals (N, 3), y up, turned by ``tilt`` about x)."""
    j, i = np.mgrid[0:size, 0:size]
    x, y = (i + 0.5) / size * 2 - 1, 1 - (j + 0.5) / size * 2
    inside = x * x + y * y < 1
    view = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], -1)[inside]
    turn = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    return inside, view, view @ turn


def main(fit_dir: str = "runs/fits/miniworld_brick_wall_1", image: str = "data/textures/val/miniworld_brick_wall_1.png",
         out: str = "docs/images/triplanar.png") -> None:
    fit = Path(fit_dir)
    sampler = SamplerSession(fit / "sampler.onnx")
    code = np.asarray(json.loads((fit / "code.json").read_text())["code"], np.float32)
    short_side = ModelRuntime(Path("model/weights")).short_side  # the space the fit started from
    photo = read_image(Path(image).read_bytes(), max_pixels=1 << 26)
    vector = texture_vector(code, calibrate_texture(sampler, code, resize_short_side(photo, short_side),
                                                   curves="linear"))
    inside, view, normals = sphere_view(SIZE, TILT)
    points, shade = normals * RADIUS, np.clip(view @ LIGHT, 0.2, 1.0)[:, None]
    panels = []
    for rgb in (sampler.sample(points, vector, SEED), sample_triplanar(sampler, points, normals, vector, SEED)):
        panel = np.ones((SIZE, SIZE, 3), np.float32)
        panel[inside] = linear_to_srgb(rgb * shade)
        panels.append(panel)
    picture = (np.clip(np.concatenate(panels, axis=1), 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(picture).save(out, optimize=True)
    print(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
