"""The fit endpoint's ``grain`` option travels from the request to ``fit_exemplar(grain=...)``.

The real fit (torch, minutes) is replaced by a stand-in ``model.fit`` module with the
real function's signature that records its call and writes what a fit writes (the
shipped sampler.onnx and a code), so this runs in a second without the train extra.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.context import build_services
from service.main import create_app
from tests.service.helpers import FAKE_LATTICE, FAKE_LEAN, FAKE_MUTED, FAKE_TURN, MODEL_DIR, fake_fit_module

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def fit_client(settings, tmp_path) -> TestClient:
    """The app on a copy of the shipped export plus a space.pt (what the fit starts from)."""
    if not all((MODEL_DIR / f).is_file() for f in ("manifest.json", "encoder.onnx", "sampler.onnx")):
        pytest.skip(f"no model export in {MODEL_DIR}")
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    for name in ("manifest.json", "encoder.onnx", "sampler.onnx"):
        shutil.copy(MODEL_DIR / name, model_dir / name)
    (model_dir / "space.pt").write_bytes(b"stand-in: the fake fit never reads it")
    settings.model_dirs = [model_dir]
    services = build_services(settings, immediate=True)
    with TestClient(create_app(services=services)) as client:
        yield client
    services.engine.dispose()


@pytest.fixture
def fit_texture(fit_client, photo) -> dict:
    res = fit_client.post("/v1/textures", files={"image": ("brick.png", photo, "image/png")})
    assert res.status_code == 201, res.text
    return res.json()


def test_the_stand_in_has_the_real_fit_exemplar_signature() -> None:
    """The stand-in these tests call is only valid while it takes what model/fit.py takes."""
    pytest.importorskip("torch", reason="model.fit needs the train extra")
    import inspect

    from model.fit import fit_exemplar

    fake = fake_fit_module([]).fit_exemplar
    assert list(inspect.signature(fake).parameters) == list(inspect.signature(fit_exemplar).parameters)


def test_fit_with_grain_y_reaches_fit_exemplar(fit_client, fit_texture, fit_calls) -> None:
    res = fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30, "grain": "y"})
    assert res.status_code == 202, res.text
    assert res.json()["params"] == {"seconds": 30, "grain": "y", "lattice": "auto", "even": "auto", "lean": "auto",
                                    "detail_seconds": 20.0}
    job = fit_client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    assert job["params"]["grain"] == "y"                      # recorded on the job
    assert len(fit_calls) == 1 and fit_calls[0]["grain"] == "y"
    assert fit_calls[0]["minutes"] == pytest.approx(0.5)
    assert fit_calls[0]["init_checkpoint"].name == "space.pt"
    assert fit_calls[0]["start_code"] == pytest.approx(fit_texture["code"])  # the code its upload stored
    fitted = fit_client.get(job["links"]["output_texture"]).json()
    assert fitted["source"] == "fit" and fitted["parents"]["job"] == job["id"]
    assert fitted["structure"] == {"grain": "y", "straightened": FAKE_TURN, "grain_stretch": 16.0,
                                   "lattice": FAKE_LATTICE, "muted_octaves": 0, "lean": None,
                                   "detail_zoom": None}  # as the fit says
    assert fit_client.get(f"/v1/textures/{fit_texture['id']}").json()["structure"] is None   # the encoder's


def test_fit_without_grain_detects_it_and_null_is_isotropic(fit_client, fit_texture, fit_calls) -> None:
    res = fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30})
    assert res.status_code == 202, res.text
    assert res.json()["params"]["grain"] == "auto"       # model.fit detects it from the photo
    assert fit_calls[0]["grain"] == "auto"
    res = fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30, "grain": None})
    assert res.status_code == 202, res.text
    assert fit_calls[1]["grain"] is None


def test_fit_lattice_is_detected_by_default_and_null_turns_it_off(fit_client, fit_texture, fit_calls) -> None:
    assert fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30}).status_code == 202
    assert fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30, "lattice": None}).status_code == 202
    assert [call["lattice"] for call in fit_calls] == ["auto", None]
    res = fit_client.post(fit_texture["links"]["fit"], json={"lattice": [32, 0, 16, 11]})  # not a value it takes
    assert res.status_code == 422 and "lattice" in res.json()["detail"]


def test_fit_even_reaches_fit_exemplar_and_the_muted_octaves_show_in_the_structure(
        fit_client, fit_texture, fit_calls) -> None:
    """even=auto (default) lets model.fit mute an even photo's coarse octaves; null never;
    the fitted texture's structure says how many its sampler has muted."""
    structures = []
    for body in ({"seconds": 30, "grain": None, "lattice": None}, {"seconds": 30, "grain": None, "lattice": None,
                                                                   "even": None}):
        res = fit_client.post(fit_texture["links"]["fit"], json=body)
        assert res.status_code == 202, res.text
        job = fit_client.get(res.json()["links"]["self"]).json()
        structures.append(fit_client.get(job["links"]["output_texture"]).json()["structure"])
    assert [call["even"] for call in fit_calls] == ["auto", None]
    assert [s["muted_octaves"] for s in structures] == [FAKE_MUTED, 0]
    res = fit_client.post(fit_texture["links"]["fit"], json={"even": "yes"})
    assert res.status_code == 422 and "even" in res.json()["detail"]
    assert len(fit_calls) == 2


def test_fit_lean_reaches_fit_exemplar_and_shows_in_the_structure(fit_client, fit_texture, fit_calls) -> None:
    """lean=auto (default) lets model.fit start a photo without grain or lattice from its lean;
    null never; the fitted texture's structure says where it started."""
    structures = []
    for body in ({"grain": None, "lattice": None}, {"grain": None, "lattice": None, "lean": None}):
        res = fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30} | body)
        assert res.status_code == 202, res.text
        job = fit_client.get(res.json()["links"]["self"]).json()
        structures.append(fit_client.get(job["links"]["output_texture"]).json()["structure"])
    assert [call["lean"] for call in fit_calls] == ["auto", None]
    assert [s["lean"] for s in structures] == [FAKE_LEAN, None]
    res = fit_client.post(fit_texture["links"]["fit"], json={"lean": 30})
    assert res.status_code == 422 and "lean" in res.json()["detail"]


@pytest.mark.parametrize("grain", ["z", "Y", "", 1])
def test_bad_grain_is_a_422_problem_naming_the_allowed_values(fit_client, fit_texture, fit_calls, grain) -> None:
    res = fit_client.post(fit_texture["links"]["fit"], json={"grain": grain})
    assert res.status_code == 422, res.text
    assert res.headers["content-type"] == "application/problem+json"
    problem = res.json()
    assert problem["type"] == "urn:texspace:problem:validation-error"
    assert "grain" in problem["detail"] and "'x', 'y' or 'auto'" in problem["detail"]
    assert fit_calls == []
    assert fit_client.get("/v1/jobs").json()["items"] == []    # nothing queued


def test_fit_of_an_exr_exemplar_reads_it_with_the_service_reader(fit_client, fit_calls, tmp_path) -> None:
    # The fit gets the uploaded file itself, and model.fit decodes it with the service's
    # one reader (worker.decode): an EXR fits (Pillow, model/'s old loader, failed on it).
    pytest.importorskip("torch")
    from model.data import load_exemplar
    from worker.images import read_image, write_image

    linear = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32) * 0.5
    exr = write_image(linear, "exr")
    created = fit_client.post("/v1/textures", files={"image": ("t.exr", exr, "image/x-exr")})
    assert created.status_code == 201, created.text
    job = fit_client.post(f"/v1/textures/{created.json()['id']}/fit", json={}).json()
    done = fit_client.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "succeeded"
    (call,) = fit_calls
    assert call["image_path"].suffix == ".exr" and call["image_bytes"] == exr
    copy = tmp_path / "t.exr"
    copy.write_bytes(exr)
    fitted = load_exemplar(copy, 64)
    served = read_image(exr, max_pixels=1 << 20)
    assert fitted.shape == served.shape and np.abs(fitted - served).max() <= 1 / 255 + 1e-6
    # the fitted texture keeps the uploaded file itself as its exemplar, not the decoded PNG
    texture_id = done.get("output_texture_id") or done["result"]["output_texture_id"]
    exemplar = fit_client.get(f"/v1/textures/{texture_id}/exemplar")
    assert exemplar.content == exr and exemplar.headers["content-type"] == "image/x-exr"


def bake_atlas(client: TestClient, texture: dict, **form: str) -> np.ndarray:
    import io
    import zipfile

    from PIL import Image

    cube = (REPO / "tests" / "data" / "meshes" / "cube.obj").read_bytes()
    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", cube)},
                      data={"resolution": "64", "format": "obj", **form})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    with zipfile.ZipFile(io.BytesIO(client.get(job["links"]["result"]).content)) as z:
        colour = next(name for name in z.namelist() if name.endswith("_basecolor.png"))
        return np.asarray(Image.open(io.BytesIO(z.read(colour))))


@pytest.mark.parametrize("lattice", ["auto", None])
def test_a_lattice_fit_bakes_triplanar_by_default(fit_client, fit_texture, fit_calls, lattice) -> None:
    """What the fit says it built decides ``projection=auto``: triplanar on a repeat lattice."""
    job = fit_client.get(fit_client.post(fit_texture["links"]["fit"], json={"seconds": 30, "lattice": lattice})
                         .json()["links"]["self"]).json()
    fitted = fit_client.get(job["links"]["output_texture"]).json()
    assert (fitted["structure"]["lattice"] is not None) == (lattice == "auto")
    auto = bake_atlas(fit_client, fitted)
    triplanar, solid = (bake_atlas(fit_client, fitted, projection=p) for p in ("triplanar", "solid"))
    assert not np.array_equal(triplanar, solid)
    assert np.array_equal(auto, triplanar if lattice == "auto" else solid)


def test_fit_of_an_evened_texture_sees_the_photo_as_its_encoding_did(fit_client, fit_calls) -> None:
    """A texture uploaded with lighting=even is fitted from its evened photo at the working
    resolution (16-bit TIFF; model.fit reads it with the service's reader), its colour table
    made from the same; the texture keeps the photo that was sent."""
    from worker.images import read_image
    from worker.photo import working_photo
    from tests.helpers import shaded_png

    shaded = shaded_png()
    created = fit_client.post("/v1/textures", files={"image": ("shaded.png", shaded, "image/png")},
                              data={"lighting": "even"}).json()
    job = fit_client.post(f"/v1/textures/{created['id']}/fit", json={}).json()
    done = fit_client.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "succeeded", done
    (call,) = fit_calls
    short_side = json.loads((MODEL_DIR / "manifest.json").read_text())["exemplar_short_side"]
    want = working_photo(read_image(shaded, max_pixels=1 << 20), short_side, "even")
    got = read_image(call["image_bytes"], max_pixels=1 << 20)
    assert got.shape == want.shape and np.abs(got - want).max() < 1.5 / 65535
    fitted = fit_client.get(f"/v1/textures/{done['output_texture_id']}").json()
    assert fitted["lighting"] == "even"
    assert fit_client.get(fitted["links"]["exemplar"]).content == shaded


def test_a_grain_fit_stored_before_the_stretch_was_recorded_reads_as_8x() -> None:
    """Rows from before structure.grain_stretch: every grain fit then stretched its cells 8x."""
    from service.schemas import Structure

    assert Structure(grain="y", straightened=0.0, lattice=None).grain_stretch == 8.0
    assert Structure(grain=None, lattice=None).grain_stretch is None
    assert Structure(grain="x", grain_stretch=16.0).grain_stretch == 16.0


def test_a_fit_starts_from_the_code_users_saw() -> None:
    """The upload's stored code (kept as encoder_code once a refinement replaced it); none for a
    code that is a fitted sampler's own."""
    from types import SimpleNamespace

    from service.job_kinds import start_code

    upload = SimpleNamespace(code=[0.5, -1.0], encoder_code=None, sampler_key=None)
    refined = SimpleNamespace(code=[9.0, 9.0], encoder_code=[0.5, -1.0], sampler_key="refinements/a/sampler.onnx")
    fitted = SimpleNamespace(code=[9.0, 9.0], encoder_code=None, sampler_key="fits/b/sampler.onnx")
    assert start_code(upload) == [0.5, -1.0] and start_code(refined) == [0.5, -1.0]
    assert start_code(fitted) is None
