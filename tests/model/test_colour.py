"""model/colour.py: the sampler's colour stage and training's colour-moment transfer."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model.colour import (  # noqa: E402
    FLOOR, KNOTS, apply_colour, colour_size, compressed_moments, identity_colour, transfer_colour_moments,
)
from model.networks import Encoder  # noqa: E402


def test_identity_table_is_a_no_op():
    torch.manual_seed(0)  # (unseeded, one draw in a few came within rounding of the bound)
    rgb = torch.rand(2, 500, 3)
    out = apply_colour(rgb, identity_colour().expand(2, -1))
    assert torch.allclose(out, rgb, atol=2e-6)
    assert identity_colour().shape == (colour_size(KNOTS),)


def test_curves_are_read_like_numpy_interp():
    # A table with A = B = identity and one curve per channel: the stage is the curve,
    # read by linear interpolation on its grid and held constant beyond it.
    rng = np.random.default_rng(0)
    knots = 16
    start, step = np.array([0.3, 0.4, 0.5]), np.array([0.04, 0.03, 0.02])
    values = np.sort(rng.uniform(0.3, 1.0, (3, knots)), axis=1)
    eye = np.eye(3).ravel()
    table = torch.tensor(np.concatenate([eye, start, step, values.ravel(), eye]), dtype=torch.float32)[None]
    rgb = torch.rand(1, 4000, 3, dtype=torch.float32)
    out = apply_colour(rgb, table)[0].numpy()
    compressed = np.sqrt(np.sqrt(rgb[0].numpy().astype(np.float64) + FLOOR))
    expect = np.stack([np.interp(compressed[:, c], start[c] + step[c] * np.arange(knots), values[c])
                       for c in range(3)], axis=1)
    assert np.abs(out - np.clip(expect**4 - FLOOR, 0, 1)).max() < 1e-5


def test_transfer_gives_the_target_moments_and_gradients():
    torch.manual_seed(0)
    images = (torch.rand(3, 3, 32, 32) ** 2).requires_grad_(True)
    target = torch.rand(3, 3, 24, 24) * torch.tensor([0.9, 0.5, 0.2]).view(1, 3, 1, 1)
    mean, covariance = compressed_moments(target)
    moved = transfer_colour_moments(images, mean, covariance)
    got_mean, got_covariance = compressed_moments(moved)
    assert torch.allclose(got_mean, mean, atol=2e-3)
    assert torch.allclose(got_covariance, covariance, rtol=0.02, atol=5e-4)  # clipped to [0, 1]: near, not exact
    moved.square().sum().backward()
    assert torch.isfinite(images.grad).all() and images.grad.abs().sum() > 0


def test_transfer_keeps_a_near_grey_targets_faint_colour():
    """A grey patch whose colour noise has ~1e-6 variance in compressed colour (a near-grey
    fit's raw output) is given the target's faint chroma in full: a fixed ridge of 1e-6
    had given it ~0.7x the target's chroma spread."""
    torch.manual_seed(1)
    grey = 0.15 + 0.5 * torch.rand(1, 1, 64, 64, dtype=torch.float64)
    images = (grey + 1.5e-3 * torch.randn(1, 3, 64, 64, dtype=torch.float64)).clamp(0, 1)
    target = (0.1 + 0.4 * torch.rand(1, 1, 48, 48, dtype=torch.float64) + 0.01 * torch.randn(1, 3, 48, 48,
                                                                                              dtype=torch.float64))
    mean, covariance = compressed_moments(target.clamp(0, 1))
    got = compressed_moments(transfer_colour_moments(images, mean, covariance))[1][0]
    # the spread across the channels (chroma): the variance of R - B and of R - 2G + B
    for w in (torch.tensor([1.0, 0.0, -1.0]), torch.tensor([1.0, -2.0, 1.0])):
        w = w.double()
        assert float(w @ got @ w / (w @ covariance[0] @ w)) == pytest.approx(1.0, abs=0.03)


def test_colour_blind_encoder_ignores_per_channel_tone():
    torch.manual_seed(1)
    encoder = Encoder(colour_blind=True).eval()
    image = torch.rand(2, 3, 64, 64) * 2 - 1
    recoloured = image * torch.tensor([0.5, 1.2, 0.8]).view(1, 3, 1, 1) + torch.tensor([0.3, -0.2, 0.1]).view(1, 3, 1, 1)
    with torch.no_grad():
        assert torch.allclose(encoder(image), encoder(recoloured), atol=1e-3)
        seeing = Encoder(colour_blind=False).eval()
        seeing.load_state_dict(encoder.state_dict())  # same layout: either warm-starts the other
        assert not torch.allclose(seeing(image), seeing(recoloured), atol=1e-3)
