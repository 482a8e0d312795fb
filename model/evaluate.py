"""Compare variants on a folder of exemplars with the paper's metrics.

    python -m model.evaluate --checkpoint-dir runs --exemplars data/textures/val --out runs/eval
    python -m model.evaluate --checkpoint runs/ours/checkpoint.pt --exemplars data/textures/val
    python -m model.evaluate --group smooth=runs/ablation/smooth --group nearest=runs/ablation/nearest

For every checkpoint (its variant read from the checkpoint), every exemplar and every
domain -- ``2d`` (the xy tile plane, z = 0), ``3d_axis`` (xy, xz, yz slices at random
offsets) and ``3d_oblique`` (randomly rotated slices) -- it synthesises patches for
several seeds on the same fixed planes and measures:

* style error: Gram L2 (``losses.gram_loss`` with the fixed per-layer weights) between a
  synthesised patch and the exemplar; the target is the Gram of the whole exemplar at the
  checkpoint's working resolution, the same target training uses; lower is better;
* diversity: ``losses.feature_distance`` between patches of seeds i != j on the same
  plane (VGG feature distance); higher is better;
* success: diversity x (max style error - style error), the max taken over the variants
  compared on that exemplar and domain (the paper's combined score).

A space checkpoint encodes each exemplar (mean code over fixed crops); a single-exemplar
fit is evaluated only on the exemplar it was fitted to (matched by file stem). Planar
(``dims=2``) models have no 3D domains. Writes ``results.json``, ``results.md`` and image
grids ``grid_2d.png`` / ``grid_3d_oblique.png`` (exemplar | each variant at 2 seeds).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from model.data import load_exemplar, sample_batch
from model.losses import feature_distance, gram_loss, gram_matrices
from model.networks import TextureSpace, load_checkpoint
from model.slices import fixed_planes, render_slices
from model.vgg import GATYS_LAYERS, shared_vgg
from worker.decode import SUFFIXES

DOMAINS = ("2d", "3d_axis", "3d_oblique")
GRID_DOMAINS = ("2d", "3d_oblique")


@dataclass(frozen=True)
class EvalSettings:
    patch: int = 128  # synthesised patch size, pixels (one pixel = one exemplar pixel)
    seeds: int = 3  # seeds per plane; diversity averages all pairs i != j
    planes: int = 2  # planes per domain
    code_crops: int = 8  # exemplar crops averaged into a space model's code
    plane_seed: int = 0  # fixes planes, crops and seeds: every variant sees the same ones


@dataclass
class Candidate:
    """One checkpoint under evaluation."""

    label: str
    path: Path
    model: TextureSpace
    mode: str  # "space" or "single"
    fitted_to: str | None  # exemplar stem of a single-exemplar fit
    code: torch.Tensor | None  # its learned code [1, 8]
    step: int


def find_checkpoints(directory: Path) -> list[Path]:
    """Every ``*.pt`` checkpoint under ``directory`` (sorted; recursive)."""
    paths = sorted(p for p in Path(directory).rglob("*.pt") if p.is_file())
    if not paths:
        raise FileNotFoundError(f"no *.pt checkpoints under {directory}")
    return paths


def load_candidates(paths: Sequence[Path], labels: Sequence[str | None] | None = None) -> list[Candidate]:
    """Load checkpoints; labels are variant names, made unique with the run folder.

    Single-exemplar fits are labelled ``<variant>-fit`` and share one label across
    exemplars (each is evaluated only on its own), so a table shows one fit column.
    ``labels`` (one per path, None for the default) names a group of runs instead.
    """
    loaded = []
    for path, given in zip(paths, labels or [None] * len(paths)):
        model, ckpt = load_checkpoint(path)
        mode = ckpt.get("mode", "space")
        fitted = ckpt.get("data", [None])[0] if mode == "single" else None
        code = ckpt.get("code")
        label = given or (f"{model.cfg.variant}-fit" if mode == "single" else model.cfg.variant)
        loaded.append(Candidate(label, Path(path), model, mode, fitted, code, int(ckpt.get("step", 0))))
    keys = [(c.label, c.fitted_to) for c in loaded]
    for candidate in loaded:
        if keys.count((candidate.label, candidate.fitted_to)) > 1:
            candidate.label = f"{candidate.label}:{candidate.path.parent.name}/{candidate.path.stem}"
    return loaded


def exemplar_code(model: TextureSpace, image: np.ndarray, crops: int, rng: np.random.Generator) -> torch.Tensor:
    """Encoder code of an exemplar (H, W, 3) float32: mean over random 128 crops -> [1, 8]."""
    size = min(128, *image.shape[:2])
    batch = sample_batch([image], crops, size, rng, flips=False, rotations=False)
    with torch.no_grad():
        return model.encode(torch.from_numpy(batch) * 2 - 1).mean(0, keepdim=True)


def domain_planes(domain: str, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed planes of a domain: origins float64 [n, 3], axes float64 [n, 2, 3]."""
    if domain == "2d":
        origins, axes = fixed_planes("axis", 3 * n, seed)
        keep = torch.arange(0, 3 * n, 3)  # every third fixed plane is xy
        origins, axes = origins[keep].clone(), axes[keep]
        origins[:, 2] = 0.0  # the tile plane
        return origins, axes
    return fixed_planes("axis" if domain == "3d_axis" else "oblique", n, seed)


def synthesise(candidate: Candidate, z: torch.Tensor, domain: str, settings: EvalSettings) -> torch.Tensor:
    """Patches [seeds, planes, 3, patch, patch] sRGB in [0, 1] on the domain's planes."""
    origins, axes = domain_planes(domain, settings.planes, settings.plane_seed)
    n_seeds, n_planes = settings.seeds, settings.planes
    seeds = torch.arange(n_seeds, dtype=torch.int64).repeat_interleave(n_planes)
    with torch.no_grad():
        images = render_slices(
            candidate.model.field, z.expand(n_seeds * n_planes, -1), seeds,
            origins.repeat(n_seeds, 1), axes.repeat(n_seeds, 1, 1), settings.patch,
        )
    return images.reshape(n_seeds, n_planes, 3, settings.patch, settings.patch)


def measure(patches: torch.Tensor, targets: dict[str, torch.Tensor], vgg) -> tuple[float, float]:
    """(mean style error, mean diversity) of patches [S, P, 3, H, W] against Gram targets."""
    n_seeds, n_planes = patches.shape[:2]
    with torch.no_grad():
        features = vgg(patches.reshape(n_seeds * n_planes, *patches.shape[2:]))
        style = gram_loss(features, targets, reduction="none").mean().item()
        first, second = np.triu_indices(n_seeds, k=1)  # seed pairs i < j (symmetric)
        rows_a = torch.from_numpy((first[:, None] * n_planes + np.arange(n_planes)).ravel())
        rows_b = torch.from_numpy((second[:, None] * n_planes + np.arange(n_planes)).ravel())
        diversity = feature_distance(
            {k: v[rows_a] for k, v in features.items()}, {k: v[rows_b] for k, v in features.items()}
        ).mean().item()
    return style, diversity


def add_success(results: list[dict]) -> None:
    """success = diversity x (max style error - style error), max per exemplar and domain."""
    worst: dict[tuple[str, str], float] = {}
    for row in results:
        key = (row["exemplar"], row["domain"])
        worst[key] = max(worst.get(key, -np.inf), row["style_error"])
    for row in results:
        row["success"] = row["diversity"] * (worst[(row["exemplar"], row["domain"])] - row["style_error"])


def evaluate(
    candidates: Sequence[Candidate], exemplar_paths: Sequence[Path], settings: EvalSettings = EvalSettings(),
    layers: tuple[str, ...] = GATYS_LAYERS,
) -> tuple[dict, dict]:
    """Metrics for every (candidate, exemplar, domain).

    Returns (report, images): report is JSON-ready ``{"settings", "checkpoints",
    "results": [rows], "summary"}``; images maps (exemplar, label, domain) to the
    patches of seeds 0 and 1 on the first plane, and (exemplar, None, None) to the
    exemplar's centre crop, all (patch, patch, 3) float32, for ``write_grid``.
    """
    vgg = shared_vgg(layers)
    results, images = [], {}
    for path in exemplar_paths:
        name = Path(path).stem
        loaded: dict[int, np.ndarray] = {}  # working resolution -> exemplar
        for candidate in candidates:
            if candidate.mode == "single" and candidate.fitted_to != name:
                continue
            short_side = candidate.model.cfg.exemplar_short_side
            if short_side not in loaded:
                loaded[short_side] = load_exemplar(path, short_side)
            exemplar = loaded[short_side]
            rng = np.random.default_rng(settings.plane_seed)
            z = candidate.code if candidate.code is not None else exemplar_code(
                candidate.model, exemplar, settings.code_crops, rng)
            with torch.no_grad():
                targets = gram_matrices(vgg(torch.from_numpy(exemplar.transpose(2, 0, 1).copy())[None]))
            if (name, None, None) not in images:
                images[(name, None, None)] = centre_crop(exemplar, settings.patch)
            domains = DOMAINS if candidate.model.cfg.dims == 3 else ("2d",)
            for domain in domains:
                patches = synthesise(candidate, z, domain, settings)
                style, diversity = measure(patches, targets, vgg)
                results.append({"exemplar": name, "variant": candidate.label, "domain": domain,
                                "style_error": style, "diversity": diversity})
                images[(name, candidate.label, domain)] = patches[:2, 0].permute(0, 2, 3, 1).numpy()
    add_success(results)
    report = {
        "settings": {**asdict(settings), "layers": list(layers)},
        "checkpoints": [{"label": c.label, "path": str(c.path), "variant": c.model.cfg.variant, "mode": c.mode,
                         "dims": c.model.cfg.dims, "step": c.step, "fitted_to": c.fitted_to}
                        for c in candidates],
        "results": results,
        "summary": summarise(results),
        "checks": checks(results),
    }
    return report, images


def summarise(results: Sequence[dict]) -> dict:
    """Mean of each metric over exemplars: {domain: {label: {metric: value, "n": count}}}."""
    summary: dict = {}
    for row in results:
        summary.setdefault(row["domain"], {}).setdefault(row["variant"], []).append(row)
    return {
        domain: {
            label: {metric: float(np.mean([r[metric] for r in rows])) for metric in ("style_error", "diversity", "success")}
            | {"n": len(rows)}
            for label, rows in by_label.items()
        }
        for domain, by_label in summary.items()
    }


def checks(results: Sequence[dict]) -> dict:
    """The acceptance figures (the model card's targets), per label: the lowest diversity over exemplars and
    domains, oblique / axis mean style error, and for every ``X-fit`` label the exemplars
    where the fit's style error beats X's (encoder code) in each domain."""
    by_label: dict[str, list[dict]] = {}
    for row in results:
        by_label.setdefault(row["variant"], []).append(row)
    out: dict = {}
    for label, rows in by_label.items():
        entry = {"min_diversity": min(r["diversity"] for r in rows)}
        axis = [r["style_error"] for r in rows if r["domain"] == "3d_axis"]
        oblique = [r["style_error"] for r in rows if r["domain"] == "3d_oblique"]
        if axis and oblique:
            entry["oblique_over_axis"] = float(np.mean(oblique) / np.mean(axis))
        base = label[: -len("-fit")] if label.endswith("-fit") else None
        if base in by_label:
            reference = {(r["exemplar"], r["domain"]): r["style_error"] for r in by_label[base]}
            entry["fit_better"] = {}
            for domain in dict.fromkeys(r["domain"] for r in rows):
                pairs = [(r["style_error"], reference[(r["exemplar"], domain)]) for r in rows
                         if r["domain"] == domain and (r["exemplar"], domain) in reference]
                entry["fit_better"][domain] = [sum(fit < space for fit, space in pairs), len(pairs)]
        out[label] = entry
    return out


def centre_crop(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) -> (size, size, 3) centre crop (edge-padded if the image is smaller)."""
    height, width = image.shape[:2]
    if min(height, width) < size:
        image = np.pad(image, ((0, max(0, size - height)), (0, max(0, size - width)), (0, 0)), mode="edge")
        height, width = image.shape[:2]
    top, left = (height - size) // 2, (width - size) // 2
    return image[top : top + size, left : left + size]


def report_labels(report: dict) -> list[str]:
    """The report's column labels, in checkpoint order, once each."""
    return list(dict.fromkeys(entry["label"] for entry in report["checkpoints"]))


def to_markdown(report: dict) -> str:
    """Summary tables per domain plus per-exemplar style errors."""
    lines = ["# Evaluation", "", "Style error: Gram L2, lower is better. Diversity: VGG distance between",
             "seeds, higher is better. Success: diversity x (max style error - style error).", ""]
    labels = report_labels(report)
    if len(labels) < 2:
        lines += ["Only one variant: success is 0 by definition (it compares variants).", ""]
    for domain, by_label in report["summary"].items():
        lines += [f"## {domain}", "", "| variant | style error | diversity | success | exemplars |", "|---|---|---|---|---|"]
        for label, m in by_label.items():
            lines.append(f"| {label} | {m['style_error']:.4f} | {m['diversity']:.4f} | {m['success']:.4f} | {m['n']} |")
        lines.append("")
    lines += ["## Checks", "", "| variant | lowest diversity | oblique / axis style error | fit better than encoder code |",
              "|---|---|---|---|"]
    for label, entry in report["checks"].items():
        ratio = f"{entry['oblique_over_axis']:.2f}" if "oblique_over_axis" in entry else "-"
        better = ", ".join(f"{d}: {k}/{n}" for d, (k, n) in entry.get("fit_better", {}).items()) or "-"
        lines.append(f"| {label} | {entry['min_diversity']:.4f} | {ratio} | {better} |")
    lines.append("")
    exemplars = list(dict.fromkeys(row["exemplar"] for row in report["results"]))
    for domain in report["summary"]:
        cells = {(r["exemplar"], r["variant"]): r for r in report["results"] if r["domain"] == domain}
        lines += [f"### Style error per exemplar, {domain}", "", "| exemplar | " + " | ".join(labels) + " |",
                  "|---" * (len(labels) + 1) + "|"]
        for name in exemplars:
            values = [f"{cells[(name, label)]['style_error']:.4f}" if (name, label) in cells else "-" for label in labels]
            lines.append(f"| {name} | " + " | ".join(values) + " |")
        lines.append("")
    return "\n".join(lines)


def write_grid(images: dict, labels: Sequence[str], domain: str, path: Path, patch: int) -> None:
    """PNG grid: one row per exemplar, columns exemplar | each variant at seeds 0 and 1."""
    exemplars = [key[0] for key in images if key[1] is None]
    header, gap = 14, 2
    columns = 1 + 2 * len(labels)
    sheet = Image.new("RGB", (columns * (patch + gap), len(exemplars) * (patch + gap) + header), "white")
    draw = ImageDraw.Draw(sheet)
    draw.text((2, 1), "exemplar", fill="black")
    for j, label in enumerate(labels):
        draw.text((2 + (1 + 2 * j) * (patch + gap), 1), f"{label} (seeds 0, 1)", fill="black")
    for i, name in enumerate(exemplars):
        y = header + i * (patch + gap)
        tiles = [images[(name, None, None)]]
        for label in labels:
            pair = images.get((name, label, domain))
            tiles += list(pair) if pair is not None else [None, None]
        for j, tile in enumerate(tiles):
            if tile is not None:
                pixels = np.clip(np.round(tile * 255), 0, 255).astype(np.uint8)
                sheet.paste(Image.fromarray(pixels), (j * (patch + gap), y))
        draw.rectangle((0, y, min(patch, 6 * len(name) + 3), y + 11), fill="white")
        draw.text((2, y), name, fill="black")
    sheet.save(path)


def write_report(report: dict, images: dict, out: Path) -> None:
    """results.json, results.md and grid_<domain>.png into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "results.md").write_text(to_markdown(report))
    for domain in GRID_DOMAINS:
        if any(key[2] == domain for key in images):
            write_grid(images, report_labels(report), domain, out / f"grid_{domain}.png", report["settings"]["patch"])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m model.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint-dir", type=Path, help="evaluate every *.pt under this folder")
    parser.add_argument("--checkpoint", type=Path, action="append", default=[], help="a checkpoint (repeatable)")
    parser.add_argument("--group", action="append", default=[], metavar="LABEL=DIR",
                        help="every *.pt under DIR, shown as one column LABEL (e.g. fits of one setting)")
    parser.add_argument("--exemplars", type=Path, default=Path("data/textures/val"), help="folder of exemplar images")
    parser.add_argument("--out", type=Path, default=Path("runs/eval"))
    parser.add_argument("--patch", type=int, default=EvalSettings.patch)
    parser.add_argument("--seeds", type=int, default=EvalSettings.seeds)
    parser.add_argument("--planes", type=int, default=EvalSettings.planes)
    parser.add_argument("--plane-seed", type=int, default=EvalSettings.plane_seed,
                        help="draws the planes and the code crops; another value measures the metrics' spread")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    args = parser.parse_args(argv)
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 (diversity compares seeds i != j)")
    paths = list(args.checkpoint) + (find_checkpoints(args.checkpoint_dir) if args.checkpoint_dir else [])
    labels: list[str | None] = [None] * len(paths)
    for group in args.group:
        label, sep, directory = group.partition("=")
        if not sep or not label:
            parser.error(f"--group wants LABEL=DIR, got {group!r}")
        found = find_checkpoints(Path(directory))
        paths += found
        labels += [label] * len(found)
    if not paths:
        parser.error("give --checkpoint-dir, --checkpoint or --group")
    exemplars = sorted(p for p in args.exemplars.iterdir() if p.suffix.lower() in SUFFIXES)
    if not exemplars:
        parser.error(f"no exemplar images in {args.exemplars}")
    if args.threads:
        torch.set_num_threads(args.threads)
    settings = EvalSettings(patch=args.patch, seeds=args.seeds, planes=args.planes, plane_seed=args.plane_seed)
    report, images = evaluate(load_candidates(paths, labels), exemplars, settings)
    write_report(report, images, args.out)
    print(to_markdown(report).split("### ")[0])
    print(f"wrote {args.out}/results.json, results.md, grids")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
