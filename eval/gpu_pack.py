"""Training on a lent GPU machine that takes at most 64 MiB of files and has no network.

    python -m eval.gpu_pack pack gpu [OPTIONS]                # here (make gpu-pack): writes gpu/
    python3 gpu/gpu_pack.py train [CHECKPOINT] -- TRAIN_ARGS  # there: model.train with the packed files
    python3 gpu/gpu_pack.py slim CHECKPOINT OUT               # there: the run's checkpoint, small enough to come back
    python3 gpu/gpu_pack.py fit PHOTO OUTDIR -- FIT_ARGS      # there: model.fit (add --device cuda)

``pack`` writes into its folder: the VGG16 convs conv1_1..conv5_1 quantised to int8 per
output channel and xz-compressed (``vgg16_int8.pt.xz``, 7.7 MB; the verified fp32 cache is
59 MB; the int8 features at relu1_1..relu5_1 are within 0.2-3% of the exact ones), the
training photos at the working resolution (short side 256, as training loads them) in
``data/``, validation photos so in ``val/`` (for ``fit``), ``manifest.json`` (what was
packed) and a copy of this script. Options (``pack --help``): ``--corpus default|large``
(data/textures or data/textures-large), ``--licences all|non-gpl|KIND,...`` (the index's
``licence_kind``), ``--quality Q`` (0: PNG, lossless; else JPEG at Q, 4:2:0), ``--max-long``
(centre crop of the long side at the working resolution), ``--photo-mib`` (a size bound:
photos are taken one family at a time, round robin, until the next would not fit, so a
bounded pack still spans every family it can) and ``--val N`` (at most N validation photos,
counted in that bound first). The same options give the same pack, photo for photo: a run
resumes only on the photos it started with (``train`` checks).

``train`` restores the VGG weights to fp32, hands them to model.vgg in place of its cache,
and runs ``model.train`` with ``--data gpu/data`` and, given a CHECKPOINT, ``--init
CHECKPOINT`` (its weights and code table; ``--init`` leaves its Adam state unread);
without one a new space starts (or the run in ``--out`` resumes). Where OpenImageIO is
missing (the GPU machine), Pillow reads the packed PNGs and JPEGs (``GPU_PACK_PILLOW=1``
forces that here). ``slim`` writes a checkpoint to carry back and forth between calls:
parameters as float16, Adam's moments dropped (buffers, code table rows, step, schedule and
RNG states kept), 2.8 MB for the shipped architecture instead of 16.7: a full checkpoint
does not fit beside the tree, the VGG and the photos. A resumed slim run restarts Adam's
moments (as ``--init`` does) and goes on from its step. ``fit`` runs ``model.fit`` (its
CLI) with the same VGG weights; a fit writes ``fit.pt`` before its ONNX export. The shipped
space's runs: the model card's "The shipped space"; the large corpus's recipe: docs/DATA.md,
"Training on a lent GPU".
"""
from __future__ import annotations

import argparse
import importlib.util
import io
import json
import lzma
import os
import shutil
import sys
from collections import defaultdict
from pathlib import Path

import torch

VGG_CONVS = ("conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3",
             "conv4_1", "conv4_2", "conv4_3", "conv5_1")
VGG_FILE = "vgg16_int8.pt.xz"
CORPORA = {"default": "data/textures", "large": "data/textures-large"}
GPL_KIND = "GPL art"
HERE = Path(__file__).resolve().parent
MIB = 2**20


def pack(out: str, corpus: str = "default", licences: str = "all", quality: int = 0, max_long: int | None = None,
         photo_mib: float | None = None, val: int | None = None, short_side: int = 256,
         add_default: bool = False) -> dict:
    """Write the pack (module docstring) into ``out``; returns its manifest. ``add_default``:
    the default corpus's photos too (PNG at the working size, outside ``photo_mib``): its
    training photos in ``data/`` (a space fine-tuned on a large corpus keeps what it knew) and
    its validation photos in ``fitval/`` (GPU fits of the photos ``make quality`` measures)."""
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / VGG_FILE).write_bytes(_quantised_vgg())
    source = Path(CORPORA.get(corpus, corpus))
    index = json.loads((source / "index.json").read_text())
    budget = photo_mib * MIB if photo_mib is not None else float("inf")
    manifest = {"corpus": str(source), "licences": licences, "quality": quality, "max_long": max_long,
                "photo_mib": photo_mib, "short_side": short_side, "splits": {}}
    for folder, split, limit in (("val", "val", val), ("data", "train", None)):  # val first: it is capped
        entries = licence_filter(index["exemplars"], licences)
        entries = family_round_robin([e for e in entries if e["split"] == split])[:limit]
        (out_dir / folder).mkdir(exist_ok=True)
        written, used = [], 0
        for entry in entries:
            encoded = encode_photo(source / entry["path"], short_side, max_long, quality)
            if used + len(encoded) > budget:
                break  # stop at the first that does not fit: the same options give the same photos
            suffix = ".png" if quality == 0 else ".jpg"
            (out_dir / folder / (entry["name"] + suffix)).write_bytes(encoded)
            written.append(entry)
            used += len(encoded)
        budget -= used
        manifest["splits"][folder] = {
            "photos": len(written), "of": len(entries), "bytes": used,
            "families": len({e.get("family") for e in written}),
            "licence_kinds": _counts(licence_kind(e) for e in written),
            "names": [e["name"] for e in written]}
    if add_default:
        default = Path(CORPORA["default"])
        for folder, split in (("data", "train"), ("fitval", "val")):
            (out_dir / folder).mkdir(exist_ok=True)
            photos = sorted((default / split).glob("*.png"))
            for photo in photos:
                (out_dir / folder / photo.name).write_bytes(encode_photo(photo, short_side, None, 0))
            manifest["splits"][f"default {split}"] = {"photos": len(photos), "folder": folder,
                                                      "names": [photo.stem for photo in photos]}
    shutil.copy(__file__, out_dir / "gpu_pack.py")
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def _quantised_vgg() -> bytes:
    """The VGG16 convs int8 per output channel, torch.save'd and xz-compressed: the int8
    weights have about 6 bits of entropy, so xz takes 10.0 MB to 7.7 MB, losslessly."""
    from model.vgg import fetch_vgg16_weights

    state = torch.load(fetch_vgg16_weights(), weights_only=True)
    packed = {}
    for name in VGG_CONVS:
        weight = state[f"{name}.weight"]
        scale = weight.abs().amax(dim=(1, 2, 3), keepdim=True) / 127
        packed[f"{name}.weight.q"] = torch.round(weight / scale).clamp(-127, 127).to(torch.int8)
        packed[f"{name}.weight.scale"] = scale
        packed[f"{name}.bias"] = state[f"{name}.bias"]
    buffer = io.BytesIO()
    torch.save(packed, buffer)
    return lzma.compress(buffer.getvalue(), preset=9 | lzma.PRESET_EXTREME)


def licence_kind(entry: dict) -> str:
    """An index entry's licence kind: the large corpus records it; the default corpus's
    index has the licence alone, mapped as model.corpus maps it."""
    if entry.get("licence_kind"):
        return entry["licence_kind"]
    from model.corpus import LICENCES

    return LICENCES.get(entry.get("licence"), "unknown")


def licence_filter(entries: list[dict], licences: str) -> list[dict]:
    """``all``; ``non-gpl`` (every kind but GPL art); or a comma-separated list of kinds
    (``public domain,attribution``)."""
    if licences == "all":
        return list(entries)
    if licences == "non-gpl":
        return [e for e in entries if licence_kind(e) != GPL_KIND]
    kinds = {kind.strip() for kind in licences.split(",")}
    return [e for e in entries if licence_kind(e) in kinds]


def family_round_robin(entries: list[dict]) -> list[dict]:
    """The entries ordered one family at a time (families and photos by name): the first
    photo of every family, then every second, ...; a prefix of it spans the most families."""
    families = defaultdict(list)
    for entry in sorted(entries, key=lambda e: e["name"]):
        families[entry.get("family") or entry["name"]].append(entry)
    rounds = defaultdict(list)  # round k: the k-th photo of each family, families by name
    for family in sorted(families):
        for k, entry in enumerate(families[family]):
            rounds[k].append(entry)
    return [entry for k in sorted(rounds) for entry in rounds[k]]


def encode_photo(path: Path, short_side: int, max_long: int | None, quality: int) -> bytes:
    """A photo at the working resolution as file bytes: shrunk (Lanczos, never enlarged, as
    training loads it) so its short side is ``short_side``, its long side centre-cropped to
    ``max_long`` (or the same proportion of a photo smaller than that), then PNG
    (``quality`` 0) or JPEG at ``quality``."""
    from PIL import Image

    image = Image.open(path).convert("RGB")
    if min(image.size) > short_side:
        image = _lanczos_short_side(image, short_side)
    if max_long:
        longest = round(max_long * min(image.size) / short_side)
        width, height = min(image.width, longest), min(image.height, longest)
        left, top = (image.width - width) // 2, (image.height - height) // 2
        image = image.crop((left, top, left + width, top + height))
    buffer = io.BytesIO()
    if quality == 0:
        image.save(buffer, "PNG", optimize=True)
    else:
        image.save(buffer, "JPEG", quality=quality, optimize=True)
    return buffer.getvalue()


def _counts(values) -> dict:  # noqa: ANN001
    counts = defaultdict(int)
    for value in values:
        counts[value] += 1
    return dict(sorted(counts.items()))


def _lanczos_short_side(image, short_side: int):
    """A Pillow image resized (Lanczos) so its shorter side is ``short_side``."""
    from PIL import Image

    scale = short_side / min(image.size)
    return image.resize((round(image.width * scale), round(image.height * scale)), Image.LANCZOS)


def _pillow_reader() -> None:
    """Where OpenImageIO is not installed (the GPU machine has no network to install it):
    worker.decode imported over a stand-in OpenImageIO module (it uses the library only
    inside its decoder), with Pillow's decoder in place of ``read_image``. worker.photo
    (the Lanczos resize, the encoder's crops) is the real one. The packed
    photos are 8-bit RGB PNGs or JPEGs, which Pillow decodes as OpenImageIO does (JPEG:
    both through libjpeg)."""
    import types

    import numpy as np
    from PIL import Image

    sys.modules["OpenImageIO"] = types.ModuleType("OpenImageIO")  # (also here with GPU_PACK_PILLOW=1)
    import worker.decode as decode

    def read_image(data: bytes, **_) -> np.ndarray:
        with Image.open(io.BytesIO(data)) as image:
            return np.asarray(image.convert("RGB"), dtype=np.float32) / 255

    decode.read_image = read_image  # (model.data, imported after this, binds it)


def _use_packed_files() -> None:
    """The repository on the path, Pillow for worker.decode where needed, and the packed
    VGG weights (restored to fp32) in place of model.vgg's cache."""
    sys.path.insert(0, str(HERE.parent))  # the repository root, OUT's parent
    if importlib.util.find_spec("OpenImageIO") is None or os.environ.get("GPU_PACK_PILLOW"):
        _pillow_reader()
    import model.vgg as vgg

    packed = torch.load(io.BytesIO(lzma.decompress((HERE / VGG_FILE).read_bytes())))
    state = {f"{n}.weight": packed[f"{n}.weight.q"].float() * packed[f"{n}.weight.scale"] for n in VGG_CONVS}
    state.update({f"{n}.bias": packed[f"{n}.bias"] for n in VGG_CONVS})
    vgg._cached_state = lambda: state  # the forward pass never reaches conv5_2 for relu5_1


def _check_resume(argv: list[str]) -> None:
    """A run folder's checkpoint must have been trained on this pack's photos: a pack made
    with other options would give its code table's rows to other photos without a word."""
    out = next((argv[k + 1] for k, arg in enumerate(argv[:-1]) if arg == "--out"), None)
    checkpoint = Path(out or "", "checkpoint.pt")
    if not out or not checkpoint.exists():
        return
    trained = set(torch.load(checkpoint, map_location="cpu", weights_only=False).get("data") or ())
    packed = {p.stem for p in (HERE / "data").iterdir()}
    if trained - packed or len(packed - trained) > 1:  # (one: the default --exclude)
        raise SystemExit(f"{checkpoint} was trained on other photos than {HERE / 'data'} "
                         f"({len(trained - packed)} missing here, {len(packed - trained)} new): "
                         "make the pack again with the options it was made with (gpu/manifest.json)")


def train(checkpoint: str | None, argv: list[str]) -> None:
    _use_packed_files()
    _check_resume(argv)
    from model.train import main

    main(["--data", str(HERE / "data"), *(["--init", checkpoint] if checkpoint else []), *argv])


def slim(checkpoint: str, out: str) -> None:
    """``checkpoint`` (model.train's) with its float32 parameters as float16 and no Adam
    moments, written to ``out``: what comes back from a call and is carried into the next
    (model.train resumes it; loading casts the parameters back). Buffers (the fixed octave
    rotations, a fit's mean cell) stay exact: they are not relearnt."""
    sys.path.insert(0, str(HERE.parent))
    from model.networks import ModelConfig, TextureSpace

    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    parameters = {name for name, _ in TextureSpace(ModelConfig(**ckpt["config"])).named_parameters()}
    ckpt["model"] = {name: value.half() if name in parameters and value.dtype == torch.float32 else value
                     for name, value in ckpt["model"].items()}
    for key in ("codes", "code"):
        if key in ckpt:
            ckpt[key] = ckpt[key].half()
    ckpt["optimizer"] = {**ckpt["optimizer"], "state": {}}  # groups kept: resume loads them
    ckpt["slim"] = True
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(out).with_suffix(".tmp")
    torch.save(ckpt, tmp)
    tmp.replace(out)


def fit(photo: str, out: str, argv: list[str]) -> None:
    _use_packed_files()
    from model.fit import main

    main([photo, out, *argv])


def _pack_cli(argv: list[str]) -> None:
    p = argparse.ArgumentParser(prog="gpu_pack.py pack", description="write the pack (module docstring)")
    p.add_argument("out")
    p.add_argument("--corpus", default="default", help="default | large | a folder with index.json")
    p.add_argument("--licences", default="all", help="all | non-gpl | comma-separated licence kinds")
    p.add_argument("--quality", type=int, default=0, help="0: PNG (lossless); 1-100: JPEG quality")
    p.add_argument("--max-long", type=int, help="centre-crop the long side to this at the working resolution")
    p.add_argument("--photo-mib", type=float, help="bound on the photos' bytes (train + val), MiB")
    p.add_argument("--val", type=int, help="at most this many validation photos")
    p.add_argument("--add-default", action="store_true",
                   help="the default corpus's training photos in data/ too, its validation photos in fitval/")
    args = p.parse_args(argv)
    manifest = pack(args.out, args.corpus, args.licences, args.quality, args.max_long, args.photo_mib, args.val,
                    add_default=args.add_default)
    for folder, split in manifest["splits"].items():
        if "of" not in split:  # (--add-default's)
            print(f"{folder}: {split['photos']} photos in {split['folder']}/")
            continue
        print(f"{folder}: {split['photos']} of {split['of']} photos, {split['families']} families, "
              f"{split['bytes'] / MIB:.2f} MiB, {split['licence_kinds']}")
    total = sum(p.stat().st_size for p in Path(args.out).rglob("*") if p.is_file())
    print(f"pack: {total / MIB:.2f} MiB in {args.out}")
    tree = _tracked_bytes()
    if tree is not None:  # what the device tool sends besides the carried paths (64 MiB in all)
        print(f"tree (tracked files) {tree / MIB:.2f} MiB + pack = {(tree + total) / MIB:.2f} MiB of 64; "
              "a slim checkpoint carried too adds 2.7 MiB (shipped widths)")


def _tracked_bytes() -> int | None:
    """Bytes of the repository's tracked files (None outside a git checkout)."""
    import subprocess

    try:
        names = subprocess.run(["git", "ls-files", "-z"], capture_output=True, check=True).stdout.split(b"\0")
    except (OSError, subprocess.CalledProcessError):
        return None
    return sum(os.path.getsize(n) for n in names if n and os.path.isfile(n))


if __name__ == "__main__":
    command, rest = (sys.argv[1], sys.argv[2:]) if len(sys.argv) > 1 else ("", [])
    before, after = (rest[:rest.index("--")], rest[rest.index("--") + 1:]) if "--" in rest else (rest, [])
    if command == "pack" and rest:
        _pack_cli(rest)
    elif command == "train" and len(before) <= 1:
        train(before[0] if before else None, after)
    elif command == "slim" and len(rest) == 2:
        slim(*rest)
    elif command == "fit" and len(before) == 2:
        fit(before[0], before[1], after)
    else:
        sys.exit(__doc__)
