"""Choose the by-example baseline's triangle size: its style error over the photo's floor
(``eval.style_floor``) for several triangle edges, per photo and as the median.

    make tune-by-example
    python -m eval.tune_by_example --exemplars data/textures/val --out docs/eval/quality/by_example_tuning.md

The tiles are the quality protocol's (``eval/quality.py``): 256 px at plane pixels
(x, y) * 256 for (x, y) in {0, 1}^2, seeds 1 and 2, the photo at the working size (short
side 256: one plane pixel per photo pixel).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from eval.by_example import by_example_tile, gaussianise
from eval.style_floor import crop_errors, photo_floor, style_ratio
from worker.images import read_image
from worker.photo import resize_short_side

EDGES = (16.0, 24.0, 32.0, 48.0, 64.0, 80.0, 96.0)
TILE, SHORT_SIDE, MAX_PIXELS = 256, 256, 1 << 26
POSITIONS, SEEDS = ((0, 0), (1, 0), (0, 1), (1, 1)), (1, 2)  # as eval/quality.py


def ratios(photo: np.ndarray, edges: tuple[float, ...]) -> tuple[float, list[float | None]]:
    """photo (H, W, 3) at the working size -> (its floor, by-example error / floor per edge)."""
    floor = photo_floor(photo)
    example = gaussianise(photo)
    out = []
    for edge in edges:
        tiles = np.stack([by_example_tile(example, TILE, TILE, (x * TILE, y * TILE), seed, triangle_edge=edge)
                          for seed in SEEDS for x, y in POSITIONS])
        out.append(style_ratio(float(crop_errors(tiles, floor).mean()), floor.floor))
    return floor.floor, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--exemplars", type=Path, default=Path("data/textures/val"))
    parser.add_argument("--out", type=Path, default=Path("docs/eval/quality/by_example_tuning.md"))
    parser.add_argument("--edges", type=float, nargs="+", default=list(EDGES))
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    edges = tuple(args.edges)
    rows, start = {}, time.perf_counter()
    for path in sorted(p for p in args.exemplars.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")):
        photo = resize_short_side(read_image(path.read_bytes(), max_pixels=MAX_PIXELS), SHORT_SIDE)
        rows[path.stem] = ratios(photo, edges)
        print(path.stem, f"floor {rows[path.stem][0]:.4f}", [f"{r:.2f}" for r in rows[path.stem][1]], flush=True)
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    medians = [float(np.median([r[1][i] for r in rows.values() if r[1][i] is not None])) for i in range(len(edges))]
    lines = ["# By-example baseline: triangle edge", "",
             "Style error over the photo's floor (eval/style_floor.py) of by-example noise "
             "(eval/by_example.py) per triangle edge in pixels at the working size (short side 256), "
             f"tiles as make quality's ({len(POSITIONS) * len(SEEDS)} tiles, 4 crops of 128 px each). "
             f"{time.perf_counter() - start:.0f} s.", "",
             "| photo | floor | " + " | ".join(f"edge {e:g}" for e in edges) + " |", "|---" * (len(edges) + 2) + "|"]
    lines += [f"| {name} | {floor:.4f} | " + " | ".join(fmt(v) for v in values) + " |"
              for name, (floor, values) in rows.items()]
    lines.append("| **median** | | " + " | ".join(f"**{m:.2f}**" for m in medians) + " |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
