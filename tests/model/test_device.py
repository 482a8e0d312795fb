"""Device selection: --device picks where steps run; checkpoints hold CPU tensors whatever ran them."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

from model.fit import fit_exemplar, main as fit_main  # noqa: E402
from model.networks import ModelConfig, TextureSpace, load_checkpoint  # noqa: E402
from model.device import resolve_device  # noqa: E402
from model.objective import Objective  # noqa: E402
from model.train import main as train_main  # noqa: E402
from model.vgg import shared_vgg  # noqa: E402

TINY = ["--patch", "32", "--batch", "1", "--short-side", "128", "--crop", "64", "--quiet",
        "--layers", "relu1_1,relu2_1"]


@pytest.fixture
def brick_png(tmp_path, skimage_textures):
    path = tmp_path / "brick.png"
    Image.fromarray((skimage_textures["brick"][::4, ::4] * 255).astype(np.uint8)).save(path)  # 128 x 128
    return path


@pytest.fixture
def no_cuda(monkeypatch):
    """A machine without CUDA, whatever this one has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def tensors(value):
    """Every tensor in nested dicts / lists / tuples (a checkpoint)."""
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from tensors(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from tensors(item)


def test_auto_trains_and_saves_cpu_tensors(tmp_path, brick_png, vgg):
    # auto is cuda where there is one; either way the file must load and export on a CPU machine
    out = tmp_path / "run"
    train_main(["--mode", "single", "--exemplar", str(brick_png), "--out", str(out), "--steps", "2",
                "--device", "auto"] + TINY)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)  # no map_location
    found = list(tensors(ckpt))
    assert ckpt["step"] == 2 and ckpt["args"]["device"] == "auto"
    assert any(t.shape == (1, 8) for t in tensors(ckpt["optimizer"]["state"]))  # Adam moments of the code
    assert found and {t.device.type for t in found} == {"cpu"}
    load_checkpoint(out / "checkpoint.pt")


def test_cuda_without_cuda_exits_clearly(tmp_path, brick_png, no_cuda):
    out = tmp_path / "run"
    with pytest.raises(SystemExit, match="no CUDA device"):
        train_main(["--mode", "single", "--exemplar", str(brick_png), "--out", str(out), "--steps", "1",
                    "--device", "cuda"] + TINY)
    assert not (out / "checkpoint.pt").exists()
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("cpu") == torch.device("cpu")


def test_a_checkpoint_resumes_on_another_device_setting(tmp_path, brick_png, vgg):
    out = tmp_path / "run"
    common = ["--mode", "single", "--exemplar", str(brick_png), "--out", str(out)] + TINY
    train_main(common + ["--steps", "2", "--device", "cpu"])
    before = torch.load(out / "checkpoint.pt", weights_only=False)
    train_main(common + ["--steps", "3", "--device", "auto"])  # the GPU where there is one
    after = torch.load(out / "checkpoint.pt", weights_only=False)
    assert after["step"] == 3 and {t.device.type for t in tensors(after)} == {"cpu"}
    changed = [k for k, v in after["model"].items() if not torch.equal(v, before["model"][k])]
    assert "field.decoder.out.weight" in changed  # it trained on from the saved state
    assert len((out / "log.jsonl").read_text().splitlines()) == 3


def test_an_exported_space_is_not_resumed(tmp_path, brick_png):
    out = tmp_path / "run"
    out.mkdir()
    torch.save({"config": ModelConfig().to_dict(), "model": TextureSpace(ModelConfig()).state_dict()},
               out / "checkpoint.pt")
    with pytest.raises(SystemExit, match="--init"):
        train_main(["--mode", "single", "--exemplar", str(brick_png), "--out", str(out), "--steps", "1"] + TINY)


def test_fit_passes_the_device_on(tmp_path, brick_png, no_cuda):
    space = tmp_path / "space.pt"
    torch.save({"config": ModelConfig().to_dict(), "model": TextureSpace(ModelConfig()).state_dict()}, space)
    with pytest.raises(SystemExit, match="no CUDA device"):
        fit_exemplar(brick_png, tmp_path / "fit", init_checkpoint=space, minutes=0.01, device="cuda")
    with pytest.raises(SystemExit, match="no CUDA device"):
        fit_main([str(brick_png), str(tmp_path / "fit"), "--init", str(space), "--device", "cuda"])


def test_objective_gets_its_own_vgg_per_device(brick_png, vgg):
    layers = ("relu1_1", "relu2_1")
    assert shared_vgg(layers) is shared_vgg(layers, "cpu") is shared_vgg(layers, torch.device("cpu"))
    image = np.asarray(Image.open(brick_png), dtype=np.float32) / 255.0
    objective = Objective([image], layers, "gram", colour_weight=50.0, device="cpu")
    assert objective.vgg is shared_vgg(layers)
    assert {t.device.type for t in objective.vgg.state_dict().values()} == {"cpu"}
