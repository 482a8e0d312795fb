"""Gram and sliced Wasserstein losses, and the paper's metrics."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model.data import sample_batch  # noqa: E402
from model.losses import (  # noqa: E402
    GRAM_SCALE,
    default_layer_weights,
    gram_loss,
    gram_matrices,
    gram_matrix,
    sliced_wasserstein_loss,
    style_error,
    target_grams,
    vgg_distance,
)


def random_features(seed: int, n: int = 2, size: int = 8) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return {
        "relu1_1": torch.rand(n, 4, size, size, generator=generator),
        "relu2_1": torch.rand(n, 6, size // 2, size // 2, generator=generator),
    }


def test_gram_matrix_is_normalised_outer_product():
    features = torch.rand(3, 5, 4, 6, dtype=torch.float64)
    flat = features.numpy().reshape(3, 5, 24)
    expected = np.einsum("ncp,ndp->ncd", flat, flat) / 24
    np.testing.assert_allclose(gram_matrix(features).numpy(), expected, rtol=1e-12)
    constant = torch.full((1, 2, 7, 7), 3.0)
    assert torch.allclose(gram_matrix(constant), torch.full((1, 2, 2), 9.0))  # size-independent


def test_gram_loss_weights_targets_and_reduction():
    features, other = random_features(0), random_features(1)
    weights = {"relu1_1": 2.0, "relu2_1": 0.5}
    targets = gram_matrices(other)
    per_sample = gram_loss(features, targets, weights, reduction="none")
    expected = sum(
        w * (gram_matrix(features[k]) - targets[k]).square().mean(dim=(1, 2)) for k, w in weights.items()
    )
    assert per_sample.shape == (2,)
    assert torch.allclose(per_sample, expected)
    assert gram_loss(features, targets, weights).item() == pytest.approx(expected.mean().item(), rel=1e-6)
    # feature targets give the same loss as precomputed Grams; identical features give 0
    assert torch.allclose(gram_loss(features, other, weights, reduction="none"), per_sample)
    assert gram_loss(features, gram_matrices(features), weights).item() == 0.0
    # a batch-1 target broadcasts over the batch
    single = {k: v[:1] for k, v in targets.items()}
    broadcast = gram_loss(features, single, weights, reduction="none")
    assert broadcast[0].item() == pytest.approx(per_sample[0].item(), rel=1e-6)


def test_default_weights_are_fixed_per_layer_not_per_photo():
    weights = default_layer_weights(("relu1_1", "relu3_1", "relu5_1"))
    assert weights["relu1_1"] == pytest.approx(1 / (3 * GRAM_SCALE["relu1_1"]))
    # Brighter (higher-contrast) targets raise the loss: no per-photo renormalisation.
    features = {"relu1_1": torch.zeros(1, 4, 4, 4)}
    target = {"relu1_1": torch.ones(1, 4, 4, 4)}
    low = gram_loss(features, target, {"relu1_1": 1.0})
    high = gram_loss(features, {"relu1_1": 2 * target["relu1_1"]}, {"relu1_1": 1.0})
    assert high.item() == pytest.approx(16 * low.item())
    with pytest.raises(ValueError, match="no scale"):
        default_layer_weights(("conv1_1",))


@pytest.mark.slow
def test_gram_loss_decreases_when_optimising_an_image(vgg, skimage_textures):
    rng = np.random.default_rng(3)
    exemplar = torch.from_numpy(sample_batch([skimage_textures["gravel"]], 1, 64, rng))
    targets = target_grams(exemplar, vgg)
    image = torch.full((1, 3, 64, 64), 0.5) + 0.05 * torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    image.requires_grad_(True)
    optimiser = torch.optim.Adam([image], lr=0.02)
    losses = []
    for _ in range(8):
        optimiser.zero_grad()
        loss = gram_loss(vgg(image.clamp(0, 1)), targets)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses


def test_sliced_wasserstein_zero_identical_permutation_invariant_positive_otherwise():
    features, other = random_features(0), random_features(1)
    weights = {"relu1_1": 1.0, "relu2_1": 1.0}

    def swd(a, b):
        return sliced_wasserstein_loss(a, b, 16, torch.Generator().manual_seed(5), weights, reduction="none")

    assert torch.all(swd(features, features) == 0)
    permuted = {}
    for name, value in features.items():
        n, c, h, w = value.shape
        order = torch.randperm(h * w, generator=torch.Generator().manual_seed(9))
        permuted[name] = value.reshape(n, c, h * w)[:, :, order].reshape(n, c, h, w)
    assert torch.allclose(swd(features, permuted), torch.zeros(2), atol=1e-12)
    different = swd(features, other)
    assert torch.all(different > 1e-3)
    assert torch.equal(different, swd(features, other))  # seeded directions: deterministic


def test_sliced_wasserstein_compares_distributions_across_sizes():
    features = random_features(0)
    weights = {"relu1_1": 1.0, "relu2_1": 1.0}
    # 2x nearest upsampling repeats each value 4 times: same distribution, 4x the pixels
    upsampled = {k: v.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3) for k, v in features.items()}
    same = sliced_wasserstein_loss(features, upsampled, 16, torch.Generator().manual_seed(1), weights)
    shifted = {k: v + 0.2 for k, v in upsampled.items()}
    far = sliced_wasserstein_loss(features, shifted, 16, torch.Generator().manual_seed(1), weights)
    assert same.item() < 1e-10
    assert far.item() > 1e-3
    # a batch-1 target broadcasts; gradients reach the synthesised features
    a = {k: v.clone().requires_grad_(True) for k, v in features.items()}
    loss = sliced_wasserstein_loss(a, {k: v[:1] for k, v in other_features().items()}, 8, layer_weights=weights)
    loss.backward()
    assert all(v.grad.abs().sum() > 0 for v in a.values())


def other_features() -> dict[str, torch.Tensor]:
    return random_features(4, n=1, size=16)


@pytest.mark.slow
def test_metrics_style_error_and_vgg_distance(vgg, skimage_textures):
    rng = np.random.default_rng(11)
    brick = torch.from_numpy(sample_batch([skimage_textures["brick"]], 2, 64, rng, rotations=False))
    grass = torch.from_numpy(sample_batch([skimage_textures["grass"]], 1, 64, rng, rotations=False))
    images = torch.cat([brick[:1], grass])
    errors = style_error(images, brick[1:], vgg)
    assert errors.shape == (2,) and errors[0] < errors[1]
    distance = vgg_distance(images, torch.cat([brick[1:], brick[1:]]), vgg)
    assert distance.shape == (2,) and torch.all(distance > 0)
    assert torch.allclose(vgg_distance(images, images, vgg), torch.zeros(2))
    assert torch.allclose(distance, vgg_distance(torch.cat([brick[1:], brick[1:]]), images, vgg))
    with pytest.raises(ValueError, match="shapes differ"):
        vgg_distance(images, brick[:1, :, :32, :32], vgg)


def test_log_power_spectrum_finds_a_stripe_period_and_is_flat_for_white_noise():
    from model.losses import SPECTRUM_BINS, _radial_bins, log_power_spectrum

    size = 64
    rows = torch.arange(size, dtype=torch.float32)
    stripes = (0.5 + 0.4 * torch.sin(2 * np.pi * rows / 8))[None, None, :, None].expand(1, 3, size, size)
    spectrum = log_power_spectrum(stripes)[0]
    fy = torch.fft.fftfreq(size)[:, None].expand(size, size // 2 + 1)
    fx = torch.fft.rfftfreq(size)[None, :].expand(size, size // 2 + 1)
    index, counts = _radial_bins(size, SPECTRUM_BINS, "cpu")
    band = index[(fy == 1 / 8) & (fx == 0)][0]  # the band of 1/8 cycles per pixel, among the non-empty ones
    assert len(spectrum) == int((counts > 0).sum()) and spectrum.argmax() == (counts[:band] > 0).sum()
    noise = torch.rand(16, 1, size, size, generator=torch.Generator().manual_seed(0)).expand(-1, 3, -1, -1)
    flat = torch.log10((10 ** log_power_spectrum(noise)).mean(dim=0))
    assert flat[2:].max() - flat[2:].min() < 0.3  # white: the same power in every band (the lowest few hold few terms)


def test_spectrum_loss_tells_a_blurred_photo_from_its_own_crops(skimage_textures):
    from model.losses import spectrum_loss, spectrum_target

    image = skimage_textures["gravel"]
    target = spectrum_target(image, 64)
    crops = torch.from_numpy(sample_batch([image], 8, 64, np.random.default_rng(1)))
    blurred = torch.nn.functional.avg_pool2d(crops, 3, stride=1, padding=1, count_include_pad=False)
    own, smooth = spectrum_loss(crops, target).mean(), spectrum_loss(blurred, target).mean()
    assert own < 0.2 and smooth > 4 * own  # (one 64-px crop's periodogram is noisy: ~0.1)
    blurred.requires_grad_(True)
    spectrum_loss(blurred, target).sum().backward()
    assert torch.isfinite(blurred.grad).all() and blurred.grad.abs().sum() > 0
