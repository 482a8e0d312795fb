"""Fit jobs: optimise a sampler for one exemplar (torch, the train extra) and serve the
new texture with its own sampler."""
from __future__ import annotations

import io

import pytest
from PIL import Image

pytestmark = pytest.mark.slow


def test_fit_job_makes_a_texture_with_its_own_sampler(client, texture) -> None:
    pytest.importorskip("torch", reason="fitting needs the train extra")
    res = client.post(texture["links"]["fit"], json={"seconds": 3})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    fitted = client.get(job["links"]["output_texture"]).json()
    assert fitted["source"] == "fit" and fitted["has_own_sampler"]
    assert fitted["parents"]["texture"] == texture["id"]
    assert fitted["model_version"] == texture["model_version"]
    structure = fitted["structure"]                 # what the real fit reports it built (grain/lattice auto)
    assert structure["grain"] in (None, "x", "y")
    assert structure["lattice"] is None or (len(structure["lattice"]) == 4 and structure["grain"] is None)
    tile = client.get(f"/v1/textures/{fitted['id']}/tiles/6/0/0.png?size=64")
    assert tile.status_code == 200 and Image.open(io.BytesIO(tile.content)).size == (64, 64)
    assert client.get(fitted["links"]["exemplar"]).status_code == 200
    sampler = client.get(job["links"]["result"])  # the job's result is the fitted sampler.onnx
    assert sampler.status_code == 200 and len(sampler.content) > 1000
    assert sampler.headers["content-disposition"] == 'attachment; filename="brick_sampler.onnx"'
    blend = client.post("/v1/textures/interpolate", json={"a": fitted["id"], "b": texture["id"], "t": 0.5})
    assert blend.status_code == 409
