"""Texture losses and the paper's metrics on VGG16 features.

Layer weighting (the same for every exemplar): each layer's Gram MSE is divided by
``GRAM_SCALE[layer]``, the median over the training photos of the mean squared entry
of that layer's Gram matrix (128x128 crops at short side 256; ``measure_layer_scales``
reproduces the table). Gram magnitudes differ by ~1e8 between layers, and by ~1000x
between photos of the same layer: normalising by each photo's own Gram (per-photo
weights) made bland photos dominate a shared decoder and collapsed a prototype to
flat grey (a prototype, 18 minutes in). A fixed, corpus-level constant per layer
balances the layers without ever re-weighting one photo against another: a
high-contrast photo simply has a larger loss, as it should.

Features of the sliced Wasserstein loss and of ``vgg_distance`` are normalised the
same way by ``FEATURE_SCALE[layer]`` (median mean squared activation), because the
projection of a feature vector on a random unit direction has second moment equal to
the mean squared activation over channels.

Tensors: features are dicts ``{layer: (N, C, H, W) float32}`` from ``VGG16Features``;
Grams are ``{layer: (N, C, C)}``. A target with batch 1 is broadcast over N.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from model.vgg import GATYS_LAYERS, VGG16Features, shared_vgg

Features = Mapping[str, torch.Tensor]

# Measured by measure_layer_scales on data/textures/train (32 photos x 8 crops of
# 128 px at short side 256, rng seed 0, max pooling), rounded to 2 significant digits.
GRAM_SCALE = {
    "relu1_1": 8.5e5, "relu1_2": 3.3e8, "relu2_1": 9.9e8, "relu2_2": 1.8e9, "relu3_1": 2.9e9,
    "relu3_2": 5.2e9, "relu3_3": 1.2e9, "relu4_1": 7.0e8, "relu4_2": 5.5e7, "relu4_3": 5.5e5,
    "relu5_1": 3.1e5, "relu5_2": 1.1e4, "relu5_3": 11.0,
}
FEATURE_SCALE = {
    "relu1_1": 1.3e3, "relu1_2": 2.5e4, "relu2_1": 4.3e4, "relu2_2": 8.2e4, "relu3_1": 1.0e5,
    "relu3_2": 1.2e5, "relu3_3": 7.1e4, "relu4_1": 4.9e4, "relu4_2": 1.5e4, "relu4_3": 1.6e3,
    "relu5_1": 8.8e2, "relu5_2": 1.7e2, "relu5_3": 5.3,
}


def _check_layers(layers: Sequence[str], table: Mapping[str, float]) -> None:
    missing = [name for name in layers if name not in table]
    if missing:
        raise ValueError(f"no scale for layers {missing}; pass layer_weights explicitly")


def default_layer_weights(layers: Sequence[str] = GATYS_LAYERS) -> dict[str, float]:
    """Gram-loss weights ``1 / (n_layers * GRAM_SCALE)``: a Gram error as large as a
    typical Gram costs about 1 in total, spread evenly over the layers."""
    _check_layers(layers, GRAM_SCALE)
    return {name: 1.0 / (len(layers) * GRAM_SCALE[name]) for name in layers}


def default_feature_weights(layers: Sequence[str] = GATYS_LAYERS) -> dict[str, float]:
    """Per-layer weights ``1 / (n_layers * FEATURE_SCALE)`` for feature distances."""
    _check_layers(layers, FEATURE_SCALE)
    return {name: 1.0 / (len(layers) * FEATURE_SCALE[name]) for name in layers}


def gram_matrix(features: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) -> (N, C, C) Gram matrix divided by H * W (as the paper's code)."""
    n, c, h, w = features.shape
    flat = features.reshape(n, c, h * w)
    return flat @ flat.transpose(1, 2) / (h * w)


def gram_matrices(features: Features) -> dict[str, torch.Tensor]:
    """Gram matrix of every layer: ``{layer: (N, C, C)}``."""
    return {name: gram_matrix(value) for name, value in features.items()}


def target_grams(exemplars: torch.Tensor, vgg: VGG16Features | None = None) -> dict[str, torch.Tensor]:
    """Gram targets of exemplar images (N, 3, H, W) sRGB [0, 1], without autograd.

    Compute once per exemplar and pass to ``gram_loss`` (the exemplar never changes).
    """
    vgg = vgg or shared_vgg()
    with torch.no_grad():
        return gram_matrices(vgg(exemplars))


def _reduce(per_sample: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return per_sample.mean()
    if reduction == "none":
        return per_sample
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def gram_loss(
    features: Features, targets: Mapping[str, torch.Tensor],
    layer_weights: Mapping[str, float] | None = None, reduction: str = "mean",
) -> torch.Tensor:
    """Weighted Gram MSE between synthesised features and target Grams.

    features : ``{layer: (N, C, H, W)}`` of the synthesised images.
    targets : ``{layer: (N or 1, C, C)}`` precomputed Grams (see ``target_grams``), or
        ``{layer: (N or 1, C, H', W')}`` target features (Grams taken here).
    layer_weights : per-layer weights, default ``default_layer_weights(layers)``;
        the same for every exemplar.
    Returns the mean over the batch, or (N,) per sample with ``reduction="none"``.
    """
    weights = layer_weights if layer_weights is not None else default_layer_weights(tuple(features))
    total = 0.0
    for name, value in features.items():
        target = targets[name]
        if target.ndim == 4:
            target = gram_matrix(target)
        difference = gram_matrix(value) - target
        total = total + weights[name] * difference.square().mean(dim=(1, 2))
    return _reduce(total, reduction)


def _resample_sorted(values: torch.Tensor, length: int) -> torch.Tensor:
    """(..., P) sorted values -> (..., length) by linear interpolation of quantiles."""
    size = values.shape[-1]
    if size == length:
        return values
    position = ((torch.arange(length, dtype=values.dtype, device=values.device) + 0.5) * size / length - 0.5)
    position = position.clamp(0, size - 1)
    low = position.floor().long()
    high = (low + 1).clamp(max=size - 1)
    fraction = position - low
    return values[..., low] * (1 - fraction) + values[..., high] * fraction


def random_directions(channels: int, n_directions: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(channels, n_directions) float32 random unit vectors (uniform on the sphere)."""
    directions = torch.randn(channels, n_directions, generator=generator)
    return directions / directions.norm(dim=0, keepdim=True)


def sliced_wasserstein_loss(
    features_a: Features, features_b: Features, n_directions: int = 32,
    generator: torch.Generator | None = None, layer_weights: Mapping[str, float] | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Sliced Wasserstein distance between feature distributions (Heitz et al. 2021).

    Per layer, both feature sets (N, C, H, W) and (N or 1, C, H', W') are projected on
    the same ``n_directions`` random unit directions, sorted over pixels and compared
    by MSE; when H'W' != HW, b's sorted projections are resampled to HW values
    (quantile matching). New directions every call unless ``generator`` is seeded.
    Zero for identical features and invariant to any permutation of pixels.
    Returns the batch mean, or (N,) with ``reduction="none"``.
    """
    weights = layer_weights if layer_weights is not None else default_feature_weights(tuple(features_a))
    total = 0.0
    for name, a in features_a.items():
        b = features_b[name]
        n, c = a.shape[:2]
        directions = random_directions(c, n_directions, generator).to(a)
        projected_a = torch.einsum("ncp,cd->ndp", a.reshape(n, c, -1), directions).sort(dim=-1).values
        projected_b = torch.einsum("ncp,cd->ndp", b.reshape(b.shape[0], c, -1), directions).sort(dim=-1).values
        projected_b = _resample_sorted(projected_b, projected_a.shape[-1])
        total = total + weights[name] * (projected_a - projected_b).square().mean(dim=(1, 2))
    return _reduce(total, reduction)


def gram_energy(grams: Mapping[str, torch.Tensor]) -> float:
    """An exemplar's Gram magnitude under the default layer weights, ``sum_l w_l mean(G_l^2)``
    (the Gram loss of all-zero Grams against it), from its Grams ``{layer: (1, C, C)}``
    (``target_grams``). About 1 for a typical training photo; 0.17 for the validation
    concrete, 35 for the gravel."""
    weights = default_layer_weights(tuple(grams))
    return float(sum(weights[name] * gram.square().mean() for name, gram in grams.items()))


def style_error(
    images: torch.Tensor, exemplars: torch.Tensor, vgg: VGG16Features | None = None,
    layer_weights: Mapping[str, float] | None = None,
) -> torch.Tensor:
    """The paper's similarity metric: Gram L2 (weighted MSE) between images and exemplars.

    images (N, 3, H, W) and exemplars (N or 1, 3, H', W'), sRGB in [0, 1]; sizes may
    differ. Returns (N,) float32, lower is more similar. No autograd.
    """
    vgg = vgg or shared_vgg()
    with torch.no_grad():
        return gram_loss(vgg(images), target_grams(exemplars, vgg), layer_weights, reduction="none")


def feature_distance(
    features_a: Features, features_b: Features, layer_weights: Mapping[str, float] | None = None,
) -> torch.Tensor:
    """Weighted mean squared difference of two same-size feature dicts, (N,) per pair."""
    weights = layer_weights if layer_weights is not None else default_feature_weights(tuple(features_a))
    total = 0.0
    for name, a in features_a.items():
        total = total + weights[name] * (a - features_b[name]).square().mean(dim=(1, 2, 3))
    return total


def vgg_distance(
    images_a: torch.Tensor, images_b: torch.Tensor, vgg: VGG16Features | None = None,
    layer_weights: Mapping[str, float] | None = None,
) -> torch.Tensor:
    """Diversity metric: weighted mean squared VGG feature difference, per pair.

    images_a, images_b : (N, 3, H, W) sRGB in [0, 1], same size. Returns (N,) float32;
    0 for identical images, about 2 for unrelated images of similar statistics.
    """
    if images_a.shape != images_b.shape:
        raise ValueError(f"shapes differ: {tuple(images_a.shape)} vs {tuple(images_b.shape)}")
    vgg = vgg or shared_vgg()
    with torch.no_grad():
        return feature_distance(vgg(images_a), vgg(images_b), layer_weights)


def measure_layer_scales(
    vgg: VGG16Features, images: Sequence[np.ndarray], crop: int = 128, crops_per_image: int = 8, seed: int = 0,
) -> tuple[dict[str, float], dict[str, float]]:
    """Median over images of the mean squared Gram entry and mean squared activation.

    images : (H, W, 3) float32 exemplars. Returns ``(gram_scale, feature_scale)`` per
    layer of ``vgg``; how ``GRAM_SCALE`` and ``FEATURE_SCALE`` were obtained.
    """
    from model.data import sample_batch

    rng = np.random.default_rng(seed)
    gram_values: dict[str, list[float]] = {name: [] for name in vgg.layers}
    feature_values: dict[str, list[float]] = {name: [] for name in vgg.layers}
    with torch.no_grad():
        for image in images:
            crops = torch.from_numpy(sample_batch([image], crops_per_image, crop, rng))
            for name, value in vgg(crops).items():
                gram_values[name].append(gram_matrix(value).square().mean().item())
                feature_values[name].append(value.square().mean().item())
    median = lambda values: float(np.median(values))  # noqa: E731
    return ({k: median(v) for k, v in gram_values.items()}, {k: median(v) for k, v in feature_values.items()})


SPECTRUM_BINS = 16  # radial bands, log-spaced from one cycle per patch to the Nyquist frequency
LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709 weights (on sRGB values: a perceptual proxy)


def log_power_spectrum(images: torch.Tensor, bins: int = SPECTRUM_BINS) -> torch.Tensor:
    """Radially averaged log10 power spectrum of the luminance of square images (N, 3, S, S):
    (N, bands), mean removed and a Hann window applied first; bands that hold no frequency of
    an S-px image are left out (one of 16 at 64 px, none from 128 px). Differentiable.

    Why: Gram statistics say which local features occur, not how their energy spreads over
    scales; a fit could draw pixel speckle and slow blotches where the photo has stones of one
    size, and the Gram loss barely objects (Liu, Gousseau and Xia 2016 add a spectrum
    constraint for this reason)."""
    size = images.shape[-1]
    luminance = torch.einsum("nchw,c->nhw", images, torch.tensor(LUMINANCE, dtype=images.dtype, device=images.device))
    window = torch.hann_window(size, periodic=False, dtype=images.dtype, device=images.device)
    centred = (luminance - luminance.mean(dim=(1, 2), keepdim=True)) * window[:, None] * window[None, :]
    power = torch.fft.rfft2(centred).abs().square()  # (N, S, S // 2 + 1)
    index, counts = _radial_bins(size, bins, images.device)
    sums = torch.zeros(len(images), bins, dtype=images.dtype, device=images.device)
    sums.index_add_(1, index.reshape(-1), power.reshape(len(images), -1))
    held = counts > 0
    return torch.log10(sums[:, held] / counts[held] + 1e-12)


def _radial_bins(size: int, bins: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """For an rfft2 of side ``size``: each frequency's band (0..bins-1; the DC term and the
    corners past Nyquist go to the nearest band) and each band's count (some 0 below 128 px)."""
    fy = torch.fft.fftfreq(size, device=device)[:, None]
    fx = torch.fft.rfftfreq(size, device=device)[None, :]
    radius = torch.sqrt(fy.square() + fx.square()).clamp(1.0 / size, 0.5)
    edges = torch.logspace(np.log10(1.0 / size), np.log10(0.5), bins + 1, device=device)
    index = (torch.bucketize(radius, edges[1:-1], right=True)).clamp(0, bins - 1)
    counts = torch.bincount(index.reshape(-1), minlength=bins)
    return index, counts


def spectrum_target(image: np.ndarray, size: int, crops: int = 64, seed: int = 0) -> torch.Tensor:
    """The photo's log10 power per band (bands,) for patches of ``size``: the mean power of
    ``crops`` random crops (H, W, 3 float32 sRGB), then the log (Welch's method)."""
    rng = np.random.default_rng(seed)
    h, w = image.shape[:2]
    size = min(size, h, w)
    rows, cols = rng.integers(0, h - size + 1, crops), rng.integers(0, w - size + 1, crops)
    batch = np.stack([image[r:r + size, c:c + size] for r, c in zip(rows, cols)]).transpose(0, 3, 1, 2)
    power = 10 ** log_power_spectrum(torch.from_numpy(np.ascontiguousarray(batch)).float())
    return torch.log10(power.mean(dim=0))


def spectrum_loss(images: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared log10 band-power difference between each image and ``target`` (bands,) or
    one per image (N, bands), of the same image size (``spectrum_target``): (N,)."""
    return (log_power_spectrum(images) - target.to(images)).square().mean(dim=1)
