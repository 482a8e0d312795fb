"""ModelRuntime / SamplerSession / ModelRegistry against the real model export."""
import json
import shutil

import numpy as np
import pytest

from worker.errors import InvalidParameter, ModelInvalid, ModelNotFound
from worker.runtime import ModelRegistry, ModelRuntime, SamplerSession, model_version


def test_manifest_and_version(runtime, model_dir):
    assert runtime.version == model_version(model_dir)
    assert runtime.manifest["output_colour"] == "linear"
    assert runtime.pixels_per_unit > 0
    assert runtime.ready()


def test_encode_shape(runtime):
    crops = np.random.default_rng(0).uniform(-1, 1, (3, 3, 128, 128)).astype(np.float32)
    z = runtime.encode(crops)
    assert z.shape == (3, 8) and z.dtype == np.float32 and np.isfinite(z).all()
    with pytest.raises(InvalidParameter):
        runtime.encode(crops[:, :, :64])


def test_sample_shapes_chunking_and_determinism(runtime, code):
    pts = np.random.default_rng(1).uniform(-50, 50, (1000, 3))
    a = runtime.sample(pts, code, 7)
    assert a.shape == (1000, 3) and a.dtype == np.float32
    assert np.isfinite(a).all() and a.min() >= 0 and a.max() <= 1
    small = SamplerSession(runtime.sampler.path, chunk=97)          # 11 chunks, last one short
    assert np.array_equal(small.sample(pts, code, 7), a)
    assert np.array_equal(runtime.sample(pts, code[None], 7), a)   # (1, 8) == (8,)
    per_point = np.repeat(code[None], len(pts), axis=0)
    assert np.allclose(runtime.sample(pts, per_point, 7), a, atol=1e-6)
    assert not np.allclose(runtime.sample(pts, code, 8), a)        # seed matters


def test_sample_rejects_bad_shapes(runtime, code):
    with pytest.raises(InvalidParameter):
        runtime.sample(np.zeros((4, 2)), code, 0)
    with pytest.raises(InvalidParameter):
        runtime.sample(np.zeros((4, 3)), np.zeros((3, 8), np.float32), 0)


def test_registry_versions_default_and_fitted_lru(model_dir, tmp_path):
    registry = ModelRegistry([model_dir])
    version = registry.default.version
    assert registry.get(version) is registry.default is registry.get(None)
    with pytest.raises(ModelNotFound):
        registry.get("0000000000000000")
    fitted = tmp_path / "fit.onnx"
    shutil.copy(model_dir / "sampler.onnx", fitted)
    session = registry.fitted_sampler(fitted)
    assert registry.fitted_sampler(fitted) is session               # opened once
    assert registry.ready()


def test_registry_finds_model_dirs_in_a_parent_folder(model_dir, tmp_path):
    copy = tmp_path / "models" / "a"
    shutil.copytree(model_dir, copy)
    assert list(ModelRegistry([tmp_path / "models"]).models) == [ModelRuntime(copy).version]
    with pytest.raises(ModelNotFound):
        ModelRegistry([tmp_path / "nothing"])


def test_broken_manifest_is_refused(model_dir, tmp_path):
    shutil.copytree(model_dir, tmp_path / "m")
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    del manifest["pixels_per_unit"]
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelInvalid, match="pixels_per_unit"):
        ModelRuntime(tmp_path / "m")
