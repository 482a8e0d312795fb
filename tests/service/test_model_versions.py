"""Several model versions side by side: a texture is always served by the model that
encoded it, so shipping a new model changes neither its tiles nor their ETags."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.context import build_services
from service.main import create_app
from service.settings import PACKAGED_MODEL_DIR, Settings
from tests.helpers import brick_png


def second_model(folder: Path) -> Path:
    """A copy of the shipped model with its last sampler weights changed (a new version)."""
    onnx = pytest.importorskip("onnx", reason="onnx comes with the train extra")
    from onnx import numpy_helper

    from worker.runtime import model_version

    shutil.copytree(PACKAGED_MODEL_DIR, folder)
    graph = onnx.load(folder / "sampler.onnx")
    # the decoder's output layer: the last float matrix with 3 rows or columns (RGB)
    last = [t for t in graph.graph.initializer
            if t.data_type == onnx.TensorProto.FLOAT and len(t.dims) == 2 and 3 in t.dims and max(t.dims) > 3][-1]
    last.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(last) * 1.5 + 0.05, last.name))
    onnx.save(graph, folder / "sampler.onnx")
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest.update(version=model_version(folder), created_at="2999-01-01T00:00:00+00:00")
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def app_with(tmp_path: Path, model_dirs: list[Path]) -> TestClient:
    settings = Settings(data_dir=tmp_path / "data", model_dirs=model_dirs, log_json=False, auto_fit=False)
    return TestClient(create_app(services=build_services(settings, immediate=True)))


def test_new_model_leaves_old_textures_alone(tmp_path: Path) -> None:
    old_dir = tmp_path / "models" / "old"
    shutil.copytree(PACKAGED_MODEL_DIR, old_dir)
    new_dir = second_model(tmp_path / "models" / "new")
    photo = brick_png()
    with app_with(tmp_path, [old_dir]) as client:
        old = client.post("/v1/textures", files={"image": ("b.png", photo)}).json()
        url = f"/v1/textures/{old['id']}/tiles/6/2/-1.png?size=64"
        before = client.get(url)

    # ship the new model next to the old one: it becomes the default for new uploads
    with app_with(tmp_path, [tmp_path / "models"]) as client:
        models = client.get("/v1/models").json()
        assert {m["version"] for m in models["items"]} == {old["model_version"], models["default"]}
        assert models["default"] != old["model_version"]
        new = client.post("/v1/textures", files={"image": ("b.png", photo)}).json()
        assert new["model_version"] == models["default"]
        after = client.get(url)
        assert after.content == before.content and after.headers["etag"] == before.headers["etag"]
        new_tile = client.get(f"/v1/textures/{new['id']}/tiles/6/2/-1.png?size=64")
        assert new_tile.headers["etag"] != before.headers["etag"]
        assert not np.array_equal(new_tile.content, before.content)

    # retire the old model: its textures answer a clear 503, and it is still listed
    with app_with(tmp_path, [new_dir]) as client:
        gone = client.get(url)
        assert gone.status_code == 503 and gone.json()["type"].endswith("model-unavailable")
        listed = {m["version"]: m["loaded"] for m in client.get("/v1/models").json()["items"]}
        assert listed == {old["model_version"]: False, new["model_version"]: True}


def test_a_space_with_a_longer_code_is_served(tmp_path: Path) -> None:
    """A space whose code has 16 numbers (the shipped one has 8) encodes, stores and serves
    its textures: the service takes the code's length from the model, not from a constant."""
    torch = pytest.importorskip("torch", reason="exporting a space needs the train extra")
    from model.export import export_model
    from model.networks import ModelConfig, TextureSpace

    torch.manual_seed(0)
    folder = tmp_path / "models" / "code16"
    export_model(TextureSpace(ModelConfig(variant="ours", code_size=16)), folder, {"mode": "untrained"})
    with app_with(tmp_path, [folder]) as client:
        assert client.get("/v1/models").json()["items"][0]["manifest"]["code_size"] == 16
        created = client.post("/v1/textures", files={"image": ("b.png", brick_png())})
        assert created.status_code == 201, created.text
        texture = created.json()
        assert len(texture["code"]) == 16 and client.get(f"/v1/textures/{texture['id']}").json() == texture
        tile = client.get(f"/v1/textures/{texture['id']}/tiles/6/0/0.png?size=64")
        assert tile.status_code == 200 and tile.headers["content-type"] == "image/png"
