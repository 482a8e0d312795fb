"""The Python client (service/client.py) against a real ``texspace serve``: upload, tiles,
jobs followed with progress, downloads, errors as exceptions, delete."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.client import ApiError, Client
from tests.helpers import brick_png

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.timeout(600)]
MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"


@pytest.fixture(scope="module")
def ts(embedded):
    with Client(embedded.base_url, timeout=120) as client:
        yield client


def test_upload_tiles_jobs_and_downloads(ts: Client, tmp_path: Path) -> None:
    texture = ts.upload(brick_png(128), filename="brick.png", name="client brick")
    assert texture["name"] == "client brick" and len(texture["code"]) == 8 and texture["lighting"] == "as-is"
    assert ts.upload(brick_png(128), filename="brick.png", lighting="even")["lighting"] == "even"
    assert ts.texture(texture["id"])["id"] == texture["id"]
    assert texture["id"] in {t["id"] for t in ts.textures(page_size=1)}

    png = ts.tile(texture["id"], 6, -1, 2, size=64)
    assert Image.open(io.BytesIO(png)).size == (64, 64)
    assert ts.tile(texture["id"], 6, 0, 0, fmt="exr", size=64)[:4] == b"\x76\x2f\x31\x01"
    # two zoom levels out: the server answers a preview first, the client waits for the exact tile
    preview = ts.tile(texture["id"], 4, 7, -5, size=64, exact=False)
    exact = ts.tile(texture["id"], 4, 7, -5, size=64)
    assert exact != preview and Image.open(io.BytesIO(exact)).size == (64, 64)
    assert ts.tile(texture["id"], 4, 7, -5, size=64, exact=False) == exact  # final from now on

    updates: list[dict] = []
    job = ts.volume(texture["id"], resolution=16, format="npy", idempotency_key="client-volume")
    assert ts.volume(texture["id"], resolution=16, format="npy", idempotency_key="client-volume")["id"] == job["id"]
    done = ts.wait(job, timeout=240, progress=updates.append)
    assert done["state"] == "succeeded" and done["progress"] == 1.0
    assert all(0.0 <= u["progress"] <= 1.0 for u in updates)
    path = ts.download(done, f"{tmp_path}/out/")  # a folder (made): the server's file name
    assert path.parent == tmp_path / "out" and path.suffix == ".npy"
    assert np.load(path).shape == (16, 16, 16, 3)
    assert not list(path.parent.glob("*.part"))

    bake = ts.wait(ts.bake(texture["id"], MESHES / "cube.obj", resolution=64, format="obj"), timeout=240)
    baked = ts.download(bake, tmp_path / "cube.zip")
    assert baked == tmp_path / "cube.zip"
    assert any(n.endswith(".obj") for n in zipfile.ZipFile(baked).namelist())
    assert {j["id"] for j in ts.jobs(texture_id=texture["id"])} == {done["id"], bake["id"]}


def test_errors_are_exceptions(ts: Client) -> None:
    texture = ts.upload(brick_png(96), filename="b.png")
    with pytest.raises(ApiError) as bad_lighting:
        ts.upload(brick_png(96), filename="b.png", lighting="flat")
    assert bad_lighting.value.status == 422 and "lighting" in bad_lighting.value.problem["detail"]
    with pytest.raises(ApiError) as bad_zoom:
        ts.tile(texture["id"], 99, 0, 0)
    assert bad_zoom.value.status == 422 and bad_zoom.value.problem["status"] == 422
    with pytest.raises(ApiError) as not_ready:
        job = ts.volume(texture["id"], resolution=8)
        ts.cancel(job)
        ts.download(job)
    assert not_ready.value.status == 409
    ts.delete(texture["id"])
    with pytest.raises(ApiError) as gone:
        ts.texture(texture["id"])
    assert gone.value.status == 404 and gone.value.problem["status"] == 404
