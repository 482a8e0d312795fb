"""Tileable regions through the API: the option, its 422 and 409 refusals, and
fitted textures (whose fit stores a tileable sampler beside its sampler).

The fit is a stand-in ``model.fit`` (as in tests/service/helpers.py) that writes the shipped
samplers, with or without the tileable one (a fit from before tileable textures).
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
from fastapi.testclient import TestClient
from PIL import Image

from service.container import tileable_key
from service.context import build_services
from service.db import session_scope
from service.main import create_app
from service.tables import Texture
from tests.service.helpers import upload_photo
from worker.errors import FeatureUnavailable

MODEL_DIR = Path(__file__).resolve().parents[2] / "model" / "weights"
FILES = ("manifest.json", "encoder.onnx", "sampler.onnx", "sampler_tileable.onnx")
SQUARE = {"z": 6, "x0": 0, "y0": 0, "width": 128, "height": 128, "tileable": True}


def fake_fit_module(tileable: bool) -> types.ModuleType:
    def fit_exemplar(image_path, out_dir, *, init_checkpoint=None, minutes=4.0, progress=None,  # noqa: ANN001, ANN202
                     threads=0, grain="auto", lattice="auto", even="auto", lean="auto", interim=None, interim_seconds=60.0,
                     **_):
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        shutil.copy(MODEL_DIR / "sampler.onnx", out_dir / "sampler.onnx")
        if tileable:
            shutil.copy(MODEL_DIR / "sampler_tileable.onnx", out_dir / "sampler_tileable.onnx")
        (out_dir / "code.json").write_text(json.dumps({"code": [0.0] * 8}))
        return {"code": [0.0] * 8, "grain": None, "lattice": None}

    module = types.ModuleType("model.fit")
    module.fit_exemplar = fit_exemplar
    return module


def make_client(settings, tmp_path: Path, *, model_tileable: bool = True):
    if not all((MODEL_DIR / f).is_file() for f in FILES):
        pytest.skip(f"no model export with a tileable sampler in {MODEL_DIR}")
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    for name in FILES[:3] + (FILES[3:] if model_tileable else ()):
        (model_dir / name).symlink_to(MODEL_DIR / name)
    (model_dir / "space.pt").write_bytes(b"stand-in: the fake fit never reads it")
    settings.model_dirs = [model_dir]
    services = build_services(settings, immediate=True)
    return TestClient(create_app(services=services)), services


@pytest.fixture
def api(settings, tmp_path, monkeypatch):
    monkeypatch.setattr("service.routes.jobs.torch_available", lambda: True)
    monkeypatch.setattr("service.job_kinds.torch_available", lambda: True)
    client, services = make_client(settings, tmp_path)
    with client:
        yield client, services
    services.engine.dispose()


def fitted_texture(client, photo, monkeypatch, *, tileable: bool) -> dict:
    """Upload ``photo`` and fit it with the stand-in model.fit, which writes a tileable
    sampler or, like fits from before tileable textures, none; the fitted texture."""
    monkeypatch.setitem(sys.modules, "model.fit", fake_fit_module(tileable=tileable))
    texture = upload_photo(client, photo)
    fit = client.get(client.post(texture["links"]["fit"], json={"seconds": 1}).json()["links"]["self"]).json()
    assert fit["state"] == "succeeded", fit
    return client.get(fit["links"]["output_texture"]).json()


def region(client, texture, **body) -> dict:
    res = client.post(texture["links"]["regions"], json=body)
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    return job


def result(client, job) -> bytes:
    return client.get(job["links"]["result"]).content


def seam_ratio(png: bytes) -> float:
    """Mean |difference| across the wrap over that across the interior columns."""
    image = np.asarray(Image.open(io.BytesIO(png)), dtype=np.float32)
    interior = np.abs(np.diff(image, axis=1)).mean()
    return float(np.abs(image[:, 0] - image[:, -1]).mean() / interior)


def test_tileable_region_repeats_and_plain_does_not(api, photo) -> None:
    client, _ = api
    texture = upload_photo(client, photo)
    job = region(client, texture, **SQUARE)
    assert job["params"]["tileable"] is True
    png = result(client, job)
    assert Image.open(io.BytesIO(png)).size == (128, 128)
    # the next period along x and y is the same image: no seam when tiled
    assert result(client, region(client, texture, **{**SQUARE, "x0": 128, "y0": -256})) == png
    plain = result(client, region(client, texture, **{**SQUARE, "tileable": False}))
    assert plain != png
    # across the wrap, the tileable image changes as between neighbouring columns (0.79 with
    # the brick photo's code); the plain one jumps (1.87: its texture is finer than the seam)
    assert seam_ratio(png) < 1.2 and seam_ratio(plain) > 1.5


def test_tileable_with_derived_maps(api, photo) -> None:
    import zipfile

    client, _ = api
    texture = upload_photo(client, photo)
    job = region(client, texture, **SQUARE, format="exr", maps=["normal"])
    with zipfile.ZipFile(io.BytesIO(result(client, job))) as z:
        stem = f"{job['result']['filename'][:-4]}"
        assert stem.endswith("_region_z6_128px_seed0_tileable"), stem
        assert sorted(z.namelist()) == [f"{stem}_basecolor.exr", f"{stem}_normal.png"]


@pytest.mark.parametrize("change", [{"height": 64}, {"plane": "xz"}, {"format": "pyramid"}])
def test_tileable_shapes_it_cannot_make_are_422(api, photo, change) -> None:
    client, _ = api
    texture = upload_photo(client, photo)
    res = client.post(texture["links"]["regions"], json={**SQUARE, **change})
    assert res.status_code == 422, res.text
    assert res.headers["content-type"] == "application/problem+json"
    assert "tileable" in res.json()["detail"]
    assert client.post(texture["links"]["regions"], json={**SQUARE, **change, "tileable": False}).status_code == 202


def test_tileable_above_the_native_zoom(api, photo) -> None:
    client, _ = api
    texture = upload_photo(client, photo)
    job = region(client, texture, **{**SQUARE, "z": 7, "width": 256, "height": 256})
    image = np.asarray(Image.open(io.BytesIO(result(client, job))), np.float64)
    assert image.shape[:2] == (256, 256) and "_z7_256px_" in job["result"]["filename"]
    # no seam: the wrap's step is like the steps inside
    inside = np.abs(np.diff(image, axis=1)).mean()
    assert np.abs(image[:, 0] - image[:, -1]).mean() < 2 * inside


def test_tileable_over_the_region_limit_is_413(api, photo) -> None:
    client, services = api
    texture = upload_photo(client, photo)
    side = int(services.settings.max_region_pixels ** 0.5) + 1
    res = client.post(texture["links"]["regions"], json={**SQUARE, "width": side, "height": side})
    assert res.status_code == 413, res.text


def test_fitted_texture_renders_its_own_tileable_sampler(api, photo, monkeypatch) -> None:
    client, services = api
    fitted = fitted_texture(client, photo, monkeypatch, tileable=True)
    assert services.storage.exists(f"textures/{fitted['id']}/sampler_tileable.onnx")
    png = result(client, region(client, fitted, **SQUARE))
    assert result(client, region(client, fitted, **{**SQUARE, "x0": -128})) == png


def test_refined_upload_renders_its_refinement_tileable(settings, tmp_path, photo, monkeypatch) -> None:
    """An upload's in-place refinement stores the fit's tileable sampler beside the refined
    sampler, and tileable regions of the upload use it."""
    monkeypatch.setattr("service.job_kinds.torch_available", lambda: True)
    monkeypatch.setitem(sys.modules, "model.fit", fake_fit_module(tileable=True))
    settings.auto_fit = True
    client, services = make_client(settings, tmp_path)
    with client:
        texture = client.get(f"/v1/textures/{upload_photo(client, photo)['id']}").json()
        assert texture["sampler"] == "fitted", texture              # refined (immediate mode)
        with services.sessions() as session:
            sampler_key = session.get(Texture, texture["id"]).sampler_key
        assert "/refined/" in sampler_key and services.storage.exists(tileable_key(sampler_key))
        png = result(client, region(client, texture, **SQUARE))
        assert result(client, region(client, texture, **{**SQUARE, "y0": 128})) == png
    services.engine.dispose()


def test_texture_fitted_before_tileable_textures_is_409(api, photo, monkeypatch) -> None:
    client, services = api
    fitted = fitted_texture(client, photo, monkeypatch, tileable=False)
    res = client.post(fitted["links"]["regions"], json=SQUARE)
    assert res.status_code == 409 and res.headers["content-type"] == "application/problem+json"
    problem = res.json()
    assert problem["type"] == "urn:texspace:problem:not-tileable" and "refit" in problem["detail"]
    assert client.post(fitted["links"]["regions"], json={**SQUARE, "tileable": False}).status_code == 202
    # a job queued anyway (e.g. before a worker update) fails with the same advice
    with session_scope(services.sessions) as session:
        row = session.get(Texture, fitted["id"])
    with pytest.raises(FeatureUnavailable, match="refit"):
        services.tileable_sampler_for(row)


def test_model_exported_before_tileable_textures_is_409(settings, tmp_path, photo) -> None:
    client, services = make_client(settings, tmp_path, model_tileable=False)
    with client:
        texture = upload_photo(client, photo)
        res = client.post(texture["links"]["regions"], json=SQUARE)
        assert res.status_code == 409, res.text
        assert "re-export" in res.json()["detail"]
        assert client.post(texture["links"]["regions"], json={**SQUARE, "tileable": False}).status_code == 202
    services.engine.dispose()


def test_tileable_key_sits_beside_the_sampler() -> None:
    assert tileable_key("textures/a/sampler.onnx") == "textures/a/sampler_tileable.onnx"
    assert tileable_key("textures/a/refined/j-1/sampler.onnx") == "textures/a/refined/j-1/sampler_tileable.onnx"
