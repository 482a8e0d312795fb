"""A fit's detail sampler (model/detail.py) draws the texture above the native zoom, and only there.

The stand-in model.fit writes the shipped sampler as the fit and, when asked, a detail sampler:
the shipped space with two more octaves drawn (their decoder columns non-zero), exported here.
"""
from __future__ import annotations

import io
import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.db import session_scope
from service.keys import detail_key
from service.tables import Texture
from tests.service.helpers import upload_photo
from tests.service.test_tileable import MODEL_DIR, make_client

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def detail_sampler(tmp_path_factory) -> Path:
    from model.detail import grow_octaves
    from model.export import export_sampler, export_tileable_sampler
    from model.networks import load_checkpoint

    model, _ = load_checkpoint(MODEL_DIR / "space.pt")
    grown = grow_octaves(model, 2)
    with torch.no_grad():
        columns = grown.field.decoder.from_noise.weight
        columns[:, model.cfg.n_octaves * 3:] = torch.randn(columns.shape[0], columns.shape[1] - model.cfg.n_octaves * 3)
    path = tmp_path_factory.mktemp("detail") / "sampler_detail.onnx"
    export_sampler(grown.field, path)
    export_tileable_sampler(grown.field, path.with_name("sampler_detail_tileable.onnx"))
    return path


def fake_fit_module(detail: Path | None, asked: list) -> types.ModuleType:
    def fit_exemplar(image_path, out_dir, *, detail_seconds=0.0, **_):  # noqa: ANN001, ANN202
        asked.append(detail_seconds)
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in ("sampler.onnx", "sampler_tileable.onnx"):
            shutil.copy(MODEL_DIR / name, out_dir / name)
        stage = None
        if detail is not None:  # as model.fit reports a 1024-px photo's stage that was kept
            for name in ("sampler_detail.onnx", "sampler_detail_tileable.onnx"):
                shutil.copy(detail.with_name(name), out_dir / name)
            stage = {"factor": 4, "steps": 150, "start": 0.5, "score": 0.1, "kept": True, "sampler": "sampler_detail.onnx"}
        (out_dir / "code.json").write_text(json.dumps({"code": [0.0] * 8}))
        return {"code": [0.0] * 8, "grain": None, "lattice": None, "detail": stage}

    module = types.ModuleType("model.fit")
    module.fit_exemplar = fit_exemplar
    return module


def fitted(client, photo, monkeypatch, detail: Path | None, **body) -> tuple[dict, list]:  # noqa: ANN001
    asked: list = []
    monkeypatch.setitem(sys.modules, "model.fit", fake_fit_module(detail, asked))
    texture = upload_photo(client, photo)
    job = client.get(client.post(texture["links"]["fit"], json={"seconds": 1, **body}).json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    return client.get(job["links"]["output_texture"]).json(), asked


def tile(client, texture: dict, z: int) -> np.ndarray:  # noqa: ANN001
    res = client.get(f"/v1/textures/{texture['id']}/tiles/{z}/0/0.png")
    assert res.status_code == 200, res.text
    return np.asarray(Image.open(io.BytesIO(res.content)), np.float64)


def test_tiles_above_the_native_zoom_draw_the_detail_sampler(settings, tmp_path, photo, monkeypatch,
                                                             detail_sampler) -> None:
    monkeypatch.setattr("service.routes.jobs.torch_available", lambda: True)
    monkeypatch.setattr("service.job_kinds.torch_available", lambda: True)
    client, services = make_client(settings, tmp_path)
    with client:
        plain, asked = fitted(client, photo, monkeypatch, None)
        assert asked == [20.0]  # a fit job's detail stage by default (worker.contract.DETAIL_SECONDS)
        detailed, asked = fitted(client, photo, monkeypatch, detail_sampler, detail_seconds=5)
        assert asked == [5.0]
        with session_scope(services.sessions) as session:
            key = session.get(Texture, detailed["id"]).sampler_key
        assert services.storage.exists(detail_key(key))
        assert detailed["structure"]["detail_zoom"] == 8 and plain["structure"]["detail_zoom"] is None
        # at and below the native zoom the fit itself: the same pixels with or without detail
        for z in (5, 6):
            assert np.array_equal(tile(client, plain, z), tile(client, detailed, z))
        # above it the detail sampler: finer octaves drawn over the same texture
        for z in (7, 8):
            difference = np.abs(tile(client, plain, z) - tile(client, detailed, z)).mean()
            assert difference > 1.0, (z, difference)
        # an image region above the native zoom draws it too, one at the native zoom does not
        for z, differs in ((8, True), (6, False)):
            images = []
            for texture in (plain, detailed):
                res = client.post(texture["links"]["regions"], json={"z": z, "x0": 0, "y0": 0, "width": 64, "height": 64})
                job = client.get(res.json()["links"]["self"]).json()
                images.append(np.asarray(Image.open(io.BytesIO(client.get(job["links"]["result"]).content)), np.float64))
            assert (np.abs(images[0] - images[1]).mean() > 1.0) == differs, z
        # a tileable image above the native zoom: the detail's tileable twin, seamless
        square = {"z": 8, "x0": 0, "y0": 0, "width": 128, "height": 128, "tileable": True}
        images = []
        for texture in (plain, detailed):
            job = client.get(client.post(texture["links"]["regions"], json=square).json()["links"]["self"]).json()
            assert job["state"] == "succeeded", job
            images.append(np.asarray(Image.open(io.BytesIO(client.get(job["links"]["result"]).content)), np.float64))
        assert np.abs(images[0] - images[1]).mean() > 1.0
        inside = np.abs(np.diff(images[1], axis=1)).mean()
        assert np.abs(images[1][:, 0] - images[1][:, -1]).mean() < 2 * inside
    services.engine.dispose()


def test_a_detail_stage_longer_than_the_limit_is_422(settings, tmp_path, photo, monkeypatch) -> None:
    monkeypatch.setattr("service.routes.jobs.torch_available", lambda: True)
    client, services = make_client(settings, tmp_path)
    with client:
        texture = upload_photo(client, photo)
        res = client.post(texture["links"]["fit"], json={"seconds": 1, "detail_seconds": 121})
        assert res.status_code == 422 and res.headers["content-type"] == "application/problem+json"
        assert "detail_seconds" in res.text
    services.engine.dispose()
