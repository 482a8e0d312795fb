"""Training on a lent GPU machine that takes at most 64 MiB of files and has no network.

    python docs/notes/gpu_pack.py pack gpu                   # here (make gpu-pack): writes gpu/, ~14 MiB
    python3 gpu/gpu_pack.py train CHECKPOINT -- TRAIN_ARGS   # there: model.train with the packed files
    python3 gpu/gpu_pack.py fit PHOTO OUTDIR -- FIT_ARGS      # there: model.fit (add --device cuda)

``pack`` writes into its folder: the VGG16 convs conv1_1..conv5_1 quantised to int8 per
output channel (the verified fp32 cache is 59 MB; the int8 features at relu1_1..relu5_1 are
within 0.2-3% of the exact ones), the training photos resized to the working resolution
(short side 256, as training loads them) in ``data/``, the validation photos so in ``val/``
(for ``fit``), and a copy of this script. ``train`` restores the
VGG weights to fp32, hands them to model.vgg in place of its cache, and runs ``model.train``
with ``--data gpu/data --init CHECKPOINT`` (its weights and code table; ``--init`` leaves
its Adam state unread). CHECKPOINT is a file in the tree that travels (``model/checkpoints/space-train.pt``:
the repository's 50 MB and the pack fit the limit, a second checkpoint does not).
``model.train`` resumes a run folder that holds a ``checkpoint.pt`` instead: copy
CHECKPOINT there first to keep its Adam state. Where OpenImageIO is missing, Pillow reads the
packed PNGs. ``fit`` runs ``model.fit`` (its CLI) with the same VGG weights; a fit writes
``fit.pt`` before its ONNX export. The shipped space's two calls: docs/notes/model-history.md, "Isotropic
transforms trained".
"""
from __future__ import annotations

import importlib.util
import io
import shutil
import sys
from pathlib import Path

import torch

VGG_CONVS = ("conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3",
             "conv4_1", "conv4_2", "conv4_3", "conv5_1")
HERE = Path(__file__).resolve().parent


def pack(out: str, data: str = "data/textures/train", short_side: int = 256, val: str = "data/textures/val") -> None:
    from PIL import Image

    from model.vgg import fetch_vgg16_weights

    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = torch.load(fetch_vgg16_weights(), weights_only=True)
    packed = {}
    for name in VGG_CONVS:
        weight = state[f"{name}.weight"]
        scale = weight.abs().amax(dim=(1, 2, 3), keepdim=True) / 127
        packed[f"{name}.weight.q"] = torch.round(weight / scale).clamp(-127, 127).to(torch.int8)
        packed[f"{name}.weight.scale"] = scale
        packed[f"{name}.bias"] = state[f"{name}.bias"]
    torch.save(packed, out_dir / "vgg16_int8.pt")
    for folder, source in (("data", data), ("val", val)):
        (out_dir / folder).mkdir(exist_ok=True)
        for photo in sorted(Path(source).glob("*.png")):
            image = Image.open(photo).convert("RGB")
            if min(image.size) > short_side:  # shrunk only, as training loads them
                image = _lanczos_short_side(image, short_side)
            image.save(out_dir / folder / photo.name, optimize=True)
    shutil.copy(__file__, out_dir / "gpu_pack.py")


def _lanczos_short_side(image, short_side: int):
    """A Pillow image resized (Lanczos) so its shorter side is ``short_side``."""
    from PIL import Image

    scale = short_side / min(image.size)
    return image.resize((round(image.width * scale), round(image.height * scale)), Image.LANCZOS)


def _pillow_reader() -> None:
    """Stand in for worker.decode where OpenImageIO is not installed (the GPU machine has
    no network to install it). The packed photos are 8-bit RGB PNGs, which Pillow decodes
    to the same values."""
    import types

    import numpy as np
    from PIL import Image

    def read_image(data: bytes, **_) -> np.ndarray:
        with Image.open(io.BytesIO(data)) as image:
            return np.asarray(image.convert("RGB"), dtype=np.float32) / 255

    def resize_short_side(image: np.ndarray, short_side: int) -> np.ndarray:
        # the packed photos are at the working resolution already; others: Pillow's Lanczos
        if min(image.shape[:2]) == short_side:
            return image
        pil = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
        return np.asarray(_lanczos_short_side(pil, short_side), dtype=np.float32) / 255

    module = types.ModuleType("worker.decode")
    module.SUFFIXES, module.read_image, module.resize_short_side = (".png",), read_image, resize_short_side
    sys.modules["worker.decode"] = module


def _use_packed_files() -> None:
    """The repository on the path, Pillow for worker.decode where needed, and the packed
    VGG weights (restored to fp32) in place of model.vgg's cache."""
    sys.path.insert(0, str(HERE.parent))  # the repository root, OUT's parent
    if importlib.util.find_spec("OpenImageIO") is None:
        _pillow_reader()
    import model.vgg as vgg

    packed = torch.load(HERE / "vgg16_int8.pt")
    state = {f"{n}.weight": packed[f"{n}.weight.q"].float() * packed[f"{n}.weight.scale"] for n in VGG_CONVS}
    state.update({f"{n}.bias": packed[f"{n}.bias"] for n in VGG_CONVS})
    vgg._cached_state = lambda: state  # the forward pass never reaches conv5_2 for relu5_1


def train(checkpoint: str, argv: list[str]) -> None:
    _use_packed_files()
    from model.train import main

    main(["--data", str(HERE / "data"), "--init", checkpoint, *argv])


def fit(photo: str, out: str, argv: list[str]) -> None:
    _use_packed_files()
    from model.fit import main

    main([photo, out, *argv])


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "pack":
        pack(*sys.argv[2:])
    elif len(sys.argv) >= 3 and sys.argv[1] == "train":
        train(sys.argv[2], [a for a in sys.argv[3:] if a != "--"])
    elif len(sys.argv) >= 4 and sys.argv[1] == "fit":
        fit(sys.argv[2], sys.argv[3], [a for a in sys.argv[4:] if a != "--"])
    else:
        sys.exit(__doc__)
