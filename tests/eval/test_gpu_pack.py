"""eval/gpu_pack.py's stand-in for worker.decode, used on a GPU machine without
OpenImageIO: it must give model.data every name it imports, and the same pixels.

A missing name there costs a lent GPU machine's start (a call once died on
``resize_short_side``), so it is checked here, where it is cheap."""
from __future__ import annotations

import ast
import importlib.util
import io
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("torch", reason="eval/gpu_pack.py imports torch (the train extra)")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def real():
    import worker.decode

    return worker.decode


@pytest.fixture
def stand_in(monkeypatch, real):
    """worker.decode as the GPU machine sees it; the real module comes back afterwards."""
    import worker

    # it imports a fresh worker.decode over a stand-in OpenImageIO: the real ones come back after
    monkeypatch.delitem(sys.modules, "worker.decode")
    monkeypatch.setitem(sys.modules, "OpenImageIO", sys.modules["OpenImageIO"])
    monkeypatch.setattr(worker, "decode", real)
    spec = importlib.util.spec_from_file_location("gpu_pack", ROOT / "eval" / "gpu_pack.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module._pillow_reader()
    assert sys.modules["worker.decode"] is not real
    return sys.modules["worker.decode"]


def _png(rgb8: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(rgb8).save(buffer, format="PNG")
    return buffer.getvalue()


@pytest.mark.parametrize("user", ["data.py", "evaluate.py"])
def test_stand_in_has_every_name_model_imports(stand_in, user):
    tree = ast.parse((ROOT / "model" / user).read_text())
    names = {alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
             and node.module == "worker.decode" for alias in node.names}
    assert names, f"model/{user} no longer imports worker.decode: update this test"
    assert not [name for name in names if not hasattr(stand_in, name)]


def test_stand_in_reads_as_worker_decode_for_the_same_resize(stand_in):
    from worker.photo import resize_short_side  # (the real one, over the stand-in reader)

    rng = np.random.default_rng(0)
    packed = rng.integers(0, 256, (256, 320, 3), dtype=np.uint8)  # a packed photo: short side 256
    read = stand_in.read_image(_png(packed))
    np.testing.assert_array_equal(read, packed.astype(np.float32) / 255)
    assert resize_short_side(read, 256) is read  # already at the working resolution

    smooth = (np.stack(np.meshgrid(np.linspace(0, 1, 640), np.linspace(0, 1, 512)), -1) * 200 + 20).astype(np.uint8)
    photo = np.concatenate([smooth, smooth[..., :1]], axis=-1)  # 512 x 640, not yet resized
    ours = resize_short_side(stand_in.read_image(_png(photo)), 256)
    theirs = resize_short_side(photo.astype(np.float32) / 255, 256)
    assert ours.shape == theirs.shape == (256, 320, 3)
    assert np.abs(ours - theirs).max() <= 2 / 255
