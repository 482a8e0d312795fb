"""worker/shader.py without a GPU: the emitter reads the right numbers out of the sampler
(hash constants, lattice maps, code biases). The shader itself is run against the ONNX
sampler in headless Chromium by tests/browser/test_shader.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker import shader
from worker.colour_match import identity_colour
from worker.errors import InvalidParameter

SAMPLER = Path(__file__).resolve().parents[2] / "model" / "weights" / "sampler.onnx"


def test_hash_constants_are_the_graphs():
    assert all(shader.hash_constants_in_graph(SAMPLER).values()), shader.hash_constants_in_graph(SAMPLER)


def test_noise_kind_is_read_from_each_graph(tmp_path):
    # A texture stored before the multiply hash (2026-11-26) keeps its own noise in its shader.
    pytest.importorskip("torch", reason="exporting a sampler needs the train extra")
    from tests.helpers import export_mask_noise_sampler

    old = tmp_path / "sampler.onnx"
    export_mask_noise_sampler(old)
    assert shader.sampler_weights(SAMPLER).fields == "multiply"
    assert shader.sampler_weights(old).fields == "mask"
    vector = np.concatenate([np.zeros(8, np.float32), identity_colour(216)])
    new_text, old_text = (shader.emit_shader(p, vector, "texspace_t", "glsl") for p in (SAMPLER, old))
    assert "0xa54ff53bu" in new_text and "h & 0x7feu" not in new_text
    assert "h & 0x7feu" in old_text and "0xa54ff53bu" not in old_text


def test_code_width_is_read_with_either_translator(tmp_path, monkeypatch):
    # Samplers exported since 2026-11-27 run the translator in float64: their graph casts z
    # and folds the first weight into a nameless float64 initializer. Stored ones read z in
    # float32 through "translator.body.0.weight". Both must give the emitter the code width.
    torch = pytest.importorskip("torch", reason="exporting a sampler needs the train extra")
    from model.export import export_sampler
    from model.networks import ModelConfig, TextureSpace, Translator, _determinant

    def float32_forward(self, z):  # Translator.forward as exported before 2026-11-27
        k, d = self.cfg.n_octaves, self.cfg.dims
        h = self.body(z)
        transforms = torch.eye(d) + self.to_transform(h).reshape(-1, k, d, d)
        scale = _determinant(transforms.to(torch.float64)).abs().clamp_min(1e-12) ** (1.0 / d)
        return self.to_extended(h), scale[..., None, None] * torch.eye(d, dtype=torch.float64), None

    torch.manual_seed(2)
    field = TextureSpace(ModelConfig(nearest_input=False, smooth=True, isotropic_transforms=True)).field
    export_sampler(field, tmp_path / "new.onnx")
    monkeypatch.setattr(Translator, "forward", float32_forward)
    export_sampler(field, tmp_path / "stored.onnx")
    named = [any(k.endswith("translator.body.0.weight") for k in shader._read_graph(p.read_bytes()).initializers)
             for p in (tmp_path / "new.onnx", tmp_path / "stored.onnx")]
    assert named == [False, True]  # each way of reading the width is exercised
    for name in ("new.onnx", "stored.onnx"):
        assert shader.sampler_weights(tmp_path / name).code_size == 8


def test_lattice_maps_are_affine_and_isotropic():
    z = np.random.default_rng(1).normal(size=8).astype(np.float32)
    c = shader.texture_constants(SAMPLER, np.concatenate([z, identity_colour(216)]))
    assert c.matrices.shape == (8, 3, 3) and c.offsets.shape == (8, 3) and c.biases.shape == (4 * 128 + 3,)
    # isotropic transforms times rotations times 2^k: M M^T = (s_k 2^k)^2 I
    for k, m in enumerate(c.matrices):
        gram = m @ m.T
        assert np.allclose(gram, gram[0, 0] * np.eye(3), rtol=1e-9, atol=1e-9 * gram[0, 0])
        assert 0.1 < np.sqrt(gram[0, 0]) / 2.0**k < 10.0
    assert np.all((c.offsets >= 0) & (c.offsets < 1))  # model/networks.py: octave_offset ~ U[0, 1)


@pytest.mark.parametrize("language", shader.LANGUAGES)
def test_emitted_text_defines_the_function(language):
    vector = np.concatenate([np.zeros(8, np.float32), identity_colour(216)])
    text = shader.emit_shader(SAMPLER, vector, "texspace_abc", language)
    signature = "vec3 texspace_abc(vec3 p, uint seed)" if language == "glsl" else "fn texspace_abc(p: vec3<f32>, seed: u32)"
    assert signature in text and "0x7feb352du" in text and "__" not in text
    helper = ("vec3 texspace_abc_triplanar(vec3 p, vec3 n, uint seed)" if language == "glsl"
              else "fn texspace_abc_triplanar(p: vec3<f32>, n: vec3<f32>, seed: u32)")
    assert helper in text and "37.25" in text and "74.5" in text  # worker/triplanar.py's depths
    assert text.count("{") == text.count("}")


def test_names_and_languages_are_checked():
    assert shader.shader_name("0f3a-b__c") == "texspace_0f3a_b_c"
    with pytest.raises(InvalidParameter):
        shader.emit_shader(SAMPLER, np.zeros(8, np.float32), "texspace_x", "hlsl")
    with pytest.raises(InvalidParameter):
        shader.emit_shader(SAMPLER, np.zeros(8, np.float32), "bad__name", "glsl")
