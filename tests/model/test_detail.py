"""The detail stage: finer octaves learned on a photo above the working size (model/detail.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model.config import ModelConfig  # noqa: E402
from model.detail import detail_factor, fit_detail, grow_octaves  # noqa: E402
from model.export import export_model, export_sampler  # noqa: E402
from model.networks import TextureSpace  # noqa: E402
from worker.runtime import SamplerSession  # noqa: E402


def test_the_factor_is_the_power_of_two_the_short_side_reaches_up_to_four() -> None:
    assert detail_factor(256, 4000, 256) == 1
    assert detail_factor(511, 2000, 256) == 1
    assert detail_factor(512, 700, 256) == 2
    assert detail_factor(1023, 1023, 256) == 2
    assert detail_factor(1024, 1536, 256) == 4
    assert detail_factor(4096, 4096, 256) == 4  # (more is kept out: MAX_FACTOR)


@pytest.mark.parametrize("nearest", [False, True])
def test_a_grown_field_draws_the_same_colours_until_its_new_octaves_learn(nearest: bool) -> None:
    torch.manual_seed(0)
    model = TextureSpace(ModelConfig(nearest_input=nearest, smooth=True, isotropic_transforms=True))
    with torch.no_grad():  # a fitted translator: octaves at their own scales, not the identity
        model.field.translator.to_transform.bias.normal_(0, 0.2)
    grown = grow_octaves(model, 2)
    assert grown.cfg.n_octaves == 10 and model.cfg.n_octaves == 8
    assert torch.equal(grown.field.octave_basis[:8], model.field.octave_basis)
    points = torch.rand(1, 500, 3, dtype=torch.float64) * 50
    z, seed = torch.randn(1, 8), torch.tensor(3)
    with torch.no_grad():
        assert torch.allclose(grown.field(points, z, seed), model.field(points, z, seed), atol=1e-6)
        columns = grown.field.decoder.from_noise.weight
        columns[:, columns.shape[1] * 8 // 10:] = 0.5  # the new octaves drawn: the colours change
        assert not torch.allclose(grown.field(points, z, seed), model.field(points, z, seed), atol=1e-3)


def test_only_the_new_octaves_learn_and_the_grown_sampler_runs_on_onnx(tmp_path) -> None:
    """``detail_parameters`` leaves every weight of the fit as it was (the old octaves' columns
    and transforms included) and moves the new ones; the grown field exports to a sampler that
    ONNX Runtime runs as torch does."""
    from model.detail import detail_parameters

    torch.manual_seed(0)
    model = TextureSpace(ModelConfig(smooth=True, nearest_input=False, isotropic_transforms=True))
    before = model.state_dict()
    grown = grow_octaves(model, 2)
    optimizer = torch.optim.Adam(detail_parameters(grown, 8), lr=1e-2)
    points, z = torch.rand(1, 300, 3, dtype=torch.float64) * 9, torch.randn(1, 8)
    for step in range(3):
        optimizer.zero_grad()
        grown.field(points, z, torch.tensor(step)).square().mean().backward()
        optimizer.step()
    after = grown.state_dict()
    for name, old in before.items():
        new = after[name]
        if name == "field.decoder.from_noise.weight":  # octave-major, 3 columns an octave
            assert torch.equal(new[:, :24], old) and new[:, 24:].abs().sum() > 0
        elif name.startswith("field.translator.to_transform"):  # 9 rows (3 x 3) an octave
            assert torch.equal(new[:72], old) and not torch.equal(new[72:], torch.zeros_like(new[72:]))
        elif new.shape == old.shape:
            assert torch.equal(new, old), name
    export_sampler(grown.field, tmp_path / "sampler_detail.onnx")
    session = SamplerSession(tmp_path / "sampler_detail.onnx")
    xyz = np.random.default_rng(0).uniform(0, 3, (400, 3))
    with torch.no_grad():
        expected = grown.field(torch.from_numpy(xyz)[None], z, torch.tensor(5))[0].numpy()
    assert np.allclose(session.sample(xyz, z[0].numpy(), 5), expected, atol=1e-4)


def test_the_stage_serves_its_grown_field_only_where_it_beat_its_start(vgg) -> None:
    torch.manual_seed(0)
    model = TextureSpace(ModelConfig(smooth=True, nearest_input=False, isotropic_transforms=True))
    rng = np.random.default_rng(0)
    photo = np.full((256, 256, 3), 0.5, np.float32)
    photo[:, ::2] = 0.2  # 1-px stripes at 4x the working size: detail the working size cannot hold
    photo = np.clip(photo + rng.normal(0, 0.03, photo.shape), 0, 1).astype(np.float32)
    served, stats = fit_detail(model, torch.zeros(8), photo, 4, seconds=1.0, device=torch.device("cpu"),
                               precision=None, patch=32)
    assert stats["factor"] == 4 and stats["steps"] >= 1
    assert stats["kept"] == (stats["score"] < stats["start"])
    assert (served is not model) == stats["kept"]
    assert served.cfg.n_octaves == (10 if stats["kept"] else 8)
    with pytest.raises(ValueError, match="power of two"):
        fit_detail(model, torch.zeros(8), photo, 3, seconds=1.0, device=torch.device("cpu"), precision=None)


def test_a_fit_of_a_large_photo_writes_its_detail_sampler_and_a_small_one_none(tmp_path, vgg) -> None:
    from PIL import Image

    from model.fit import fit_exemplar

    torch.manual_seed(0)
    export_model(TextureSpace(ModelConfig(smooth=True, nearest_input=False, colour_blind_encoder=True)),
                 tmp_path / "space")
    rng = np.random.default_rng(0)
    large = (rng.random((512, 512, 3)) * 255).astype(np.uint8)
    Image.fromarray(large).save(tmp_path / "large.png")
    Image.fromarray(large[:300, :300]).save(tmp_path / "small.png")
    fits, asked = {}, []
    for name, photo, wanted in (("large", "large", True), ("small", "small", True), ("declined", "large", False)):
        seen = []
        fits[name] = fit_exemplar(tmp_path / f"{photo}.png", tmp_path / name, init_checkpoint=tmp_path / "space" / "space.pt",
                                  minutes=0.02, patch=32, grain=None, lattice=None, even=None, lean=None,
                                  detail_seconds=1.0, progress=seen.append,
                                  wants_detail=lambda wanted=wanted: asked.append(wanted) or wanted)
        assert seen == sorted(seen) and seen[-1] == pytest.approx(1.0)
    assert asked == [True, True, False]  # asked once each, when the fit itself ends
    for name in ("small", "declined"):  # under twice the working size; a stage declined (another fit waits)
        assert fits[name]["detail"] is None and not (tmp_path / name / "sampler_detail.onnx").exists()
    detail = fits["large"]["detail"]
    assert detail["factor"] == 2 and detail["steps"] >= 1
    manifest = json.loads((tmp_path / "large" / "manifest.json").read_text())
    assert manifest["detail"] == detail
    for name in ("sampler_detail.onnx", "sampler_detail_tileable.onnx"):
        assert (tmp_path / "large" / name).is_file() == bool(detail["kept"])
