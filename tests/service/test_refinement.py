"""Refinement by default (TEXSPACE_AUTO_FIT): an upload queues a fit job on the fit lane
that, when it succeeds, makes the same texture serve its own fitted sampler.

The fit is the stand-in of tests/service/helpers.py (no torch); the queue holds its messages
(MemoryHuey, not immediate) so a test sees the texture before and after the job runs.
"""
from __future__ import annotations

import functools
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from service.processes import start_lane
from service.queue import worker_lanes
from service.settings import Settings
from service.tables import Texture
from service.tiles import CACHE_CONTROL, REFINING_CACHE_CONTROL
from tests.service.helpers import FAKE_INTERIM_CODE, FAKE_LATTICE, MODEL_DIR, run_fit_lane, upload_photo

TILE = "/v1/textures/{}/tiles/6/0/0.png?size=64"


def test_upload_is_refined_in_place(refining, photo, fit_calls) -> None:
    client, services = refining
    texture = upload_photo(client, photo)
    # served from the encoder's code at once; the refinement is queued on the fit lane
    assert texture["sampler"] == "encoder" and not texture["has_own_sampler"] and texture["structure"] is None
    refinement = texture["refinement"]
    assert refinement["state"] == "queued" and refinement["progress"] == 0
    assert services.fit_huey.pending_count() == 1 and services.huey.pending_count() == 0
    job = client.get(f"/v1/jobs/{refinement['job_id']}").json()
    assert job["kind"] == "fit" and job["texture_id"] == texture["id"]
    assert job["params"] == {"seconds": services.settings.fit_seconds, "grain": "auto", "lattice": "auto",
                             "even": "auto", "lean": "auto", "in_place": True,  # all detected by model.fit
                             "detail_seconds": 20.0}  # TEXSPACE_REFINE_DETAIL_SECONDS

    before = client.get(TILE.format(texture["id"]))
    assert before.status_code == 200
    assert before.headers["cache-control"] == REFINING_CACHE_CONTROL  # its bytes will change

    run_fit_lane(services)
    assert len(fit_calls) == 1 and fit_calls[0]["threads"] == services.settings.fit_threads == 0
    job = client.get(f"/v1/jobs/{refinement['job_id']}").json()
    assert job["state"] == "succeeded", job
    assert job["output_texture_id"] == texture["id"]           # the same texture, refined
    refined = client.get(f"/v1/textures/{texture['id']}").json()
    assert refined["sampler"] == "fitted" and refined["has_own_sampler"]
    assert refined["refinement"] == {"job_id": job["id"], "state": "succeeded", "progress": 1.0, "stage": "done",
                                     "queue_position": None, "interim_eta_seconds": None, "final_eta_seconds": None}
    assert refined["code"] == [0.0] * 8                         # the fit's code (the stand-in's)
    assert refined["structure"] == {"grain": None, "straightened": 0.0, "grain_stretch": None,
                                   "lattice": FAKE_LATTICE, "muted_octaves": 0, "lean": None,
                                   "detail_zoom": None}   # the fit's
    assert refined["source"] == "upload" and refined["links"]["tiles"] == texture["links"]["tiles"]
    assert client.get("/v1/textures").json()["items"][0]["sampler"] == "fitted"

    # the same URL now serves the fitted sampler's bytes under a new ETag, immutable again
    used: list[Path] = []
    fitted_sampler = services.registry.fitted_sampler
    services.registry.fitted_sampler = lambda path: used.append(Path(path)) or fitted_sampler(path)
    after = client.get(TILE.format(texture["id"]), headers={"If-None-Match": before.headers["etag"]})
    assert after.status_code == 200
    assert after.headers["etag"] != before.headers["etag"] and after.content != before.content
    assert after.headers["cache-control"] == CACHE_CONTROL
    with services.sessions() as session:
        row = session.get(Texture, texture["id"])
    assert used == [services.sampler_path(texture["id"], row.sampler_key)]
    assert used[0].read_bytes() == (MODEL_DIR / "sampler.onnx").read_bytes()  # what the fit wrote
    assert row.encoder_code == texture["code"]                  # kept: blends use it
    assert client.get(TILE.format(texture["id"]), headers={"If-None-Match": after.headers["etag"]}).status_code == 304


def test_upload_serves_its_fits_interim_until_the_fit_ends(refining, photo, fit_calls) -> None:
    """A fit that publishes its best state part way (TEXSPACE_FIT_INTERIM_SECONDS): the
    texture serves it at once (new code, new ETag, still no-cache: the fit will replace it),
    then the finished fit's sampler under yet another ETag, immutable; the interim's files
    stay in the attempt's folder."""
    client, services = refining
    texture = upload_photo(client, photo)
    encoder = client.get(TILE.format(texture["id"]))
    seen: dict = {}

    def during_interim() -> None:
        seen["texture"] = client.get(f"/v1/textures/{texture['id']}").json()
        seen["tile"] = client.get(TILE.format(texture["id"]))
        with services.sessions() as session:
            seen["key"] = session.get(Texture, texture["id"]).sampler_key

    sys.modules["model.fit"].during_interim = during_interim
    run_fit_lane(services)
    assert fit_calls[0]["interim_seconds"] == services.settings.fit_interim_seconds == 10.0
    interim_texture, tile = seen["texture"], seen["tile"]
    assert interim_texture["sampler"] == "interim" and interim_texture["has_own_sampler"]
    assert interim_texture["code"] == FAKE_INTERIM_CODE and interim_texture["refinement"]["state"] == "running"
    assert interim_texture["structure"]["lattice"] == FAKE_LATTICE          # what the fit builds in, from the start
    assert tile.status_code == 200 and tile.headers["etag"] != encoder.headers["etag"]
    assert tile.content != encoder.content
    assert tile.headers["cache-control"] == REFINING_CACHE_CONTROL  # the finished fit will replace it
    assert seen["key"].endswith("/interim/sampler.onnx")

    refined = client.get(f"/v1/textures/{texture['id']}").json()
    assert refined["sampler"] == "fitted" and refined["code"] == [0.0] * 8
    assert refined["refinement"]["state"] == "succeeded"
    final = client.get(TILE.format(texture["id"]), headers={"If-None-Match": tile.headers["etag"]})
    assert final.status_code == 200 and final.headers["etag"] not in (tile.headers["etag"], encoder.headers["etag"])
    assert final.headers["cache-control"] == CACHE_CONTROL
    with services.sessions() as session:
        row = session.get(Texture, texture["id"])
    assert row.encoder_code == texture["code"] and not row.sampler_interim  # the encoder's code kept from before
    assert services.storage.exists(seen["key"])  # a request that read the row before the swap still finds it


def test_no_interim_is_asked_for_when_it_is_off_or_for_a_fit_of_a_new_texture(refining, photo, fit_calls) -> None:
    client, services = refining
    services.settings.fit_interim_seconds = 0
    sys.modules["model.fit"].during_interim = lambda: pytest.fail("no interim was asked for")
    texture = upload_photo(client, photo)
    run_fit_lane(services)
    assert fit_calls[-1]["interim"] is None
    assert client.get(f"/v1/textures/{texture['id']}").json()["sampler"] == "fitted"
    services.settings.fit_interim_seconds = 10.0
    job = client.post(f"/v1/textures/{texture['id']}/fit", json={"seconds": 5}).json()  # a new texture
    run_fit_lane(services)
    assert fit_calls[-1]["interim"] is None
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "succeeded"


def test_refined_upload_blends_by_its_encoder_code(refining, photo) -> None:
    client, services = refining
    a, b = upload_photo(client, photo), upload_photo(client, photo)
    run_fit_lane(services)  # a's first stage: it pauses at its interim's second, b waits for its own
    run_fit_lane(services)  # b's first stage: nothing waits behind it, so it goes on to the end
    run_fit_lane(services)  # a's continuation: a is refined
    assert all(client.get(f"/v1/textures/{t['id']}").json()["sampler"] == "fitted" for t in (a, b))
    res = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": b["id"], "t": 0.0})
    assert res.status_code == 201, res.text
    assert res.json()["code"] == pytest.approx(a["code"])       # a's encoder code (its upload's), not the fit's
    assert res.json()["sampler"] == "encoder" and res.json()["refinement"] is None
    assert res.json()["parents"]["encoder_codes_of"] == [a["id"], b["id"]]  # the blend says what it mixed


def test_canceled_refinement_leaves_the_encoder_tiles_final(refining, photo) -> None:
    client, services = refining
    texture = upload_photo(client, photo)
    job_id = texture["refinement"]["job_id"]
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 202
    refreshed = client.get(f"/v1/textures/{texture['id']}").json()
    assert refreshed["sampler"] == "encoder" and refreshed["refinement"]["state"] == "canceled"
    assert client.get(TILE.format(texture["id"])).headers["cache-control"] == CACHE_CONTROL


def test_texture_deleted_during_its_refinement_leaves_no_files(refining, photo, monkeypatch) -> None:
    client, services = refining
    texture = upload_photo(client, photo)
    module = sys.modules["model.fit"]

    @functools.wraps(module.fit_exemplar)
    def fit_then_delete(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        written = module_fit(*args, **kwargs)
        assert client.delete(f"/v1/textures/{texture['id']}").status_code == 204
        return written

    module_fit = module.fit_exemplar
    monkeypatch.setattr(module, "fit_exemplar", fit_then_delete)
    deleted: list[str] = []
    delete_prefix = services.storage.delete_prefix
    monkeypatch.setattr(services.storage, "delete_prefix", lambda prefix: deleted.append(prefix) or delete_prefix(prefix))
    run_fit_lane(services)
    assert any(prefix.startswith(f"textures/{texture['id']}/refined/") for prefix in deleted)  # its own upload
    root = services.storage.root
    assert [str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()] == []
    assert list((services.cache_dir / "samplers").glob(f"{texture['id']}*")) == []


@pytest.mark.parametrize("when", ["before its interim", "at its interim"])
def test_texture_deleted_around_its_interim_leaves_no_empty_folder(refining, photo, monkeypatch, when) -> None:
    """The fit stores its interim (or its final sampler) under textures/<id>/refined/ after the
    texture was deleted, then drops it: the folders it made went with it only to the
    attempt's, leaving an empty textures/<id>/refined/ behind."""
    client, services = refining
    texture = upload_photo(client, photo)
    module = sys.modules["model.fit"]
    delete = lambda: client.delete(f"/v1/textures/{texture['id']}").status_code  # noqa: E731
    module.during_interim = (lambda: None) if when == "before its interim" else delete

    @functools.wraps(module.fit_exemplar)
    def delete_then_fit(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        assert delete() == 204
        return module_fit(*args, **kwargs)

    module_fit = module.fit_exemplar
    if when == "before its interim":
        monkeypatch.setattr(module, "fit_exemplar", delete_then_fit)
    run_fit_lane(services)
    assert client.get(f"/v1/textures/{texture['id']}").status_code == 404
    root = services.storage.root
    assert [str(p.relative_to(root)) for p in root.rglob("*") if p.parent != root] == []  # below textures/, jobs/


def test_refinement_of_a_texture_moved_to_another_model_is_dropped(refining, photo, monkeypatch) -> None:
    """texspace reencode may move a texture to a new model while its old model's refinement
    runs: that refinement must not replace what the new model serves, nor leave files."""
    client, services = refining
    texture = upload_photo(client, photo)
    module = sys.modules["model.fit"]
    module_fit = module.fit_exemplar

    @functools.wraps(module_fit)
    def fit_then_move(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        written = module_fit(*args, **kwargs)
        with services.sessions() as session, session.begin():  # what reencode writes
            session.get(Texture, texture["id"]).model_version = "f" * 16
        return written

    monkeypatch.setattr(module, "fit_exemplar", fit_then_move)
    run_fit_lane(services)
    job = client.get(f"/v1/jobs/{texture['refinement']['job_id']}").json()
    assert job["state"] == "canceled" and "moved from model" in job["error"]["detail"], job
    with services.sessions() as session:
        row = session.get(Texture, texture["id"])
    assert row.model_version == "f" * 16 and row.sampler_key is None and row.code == texture["code"]
    root = services.storage.root
    assert [p for p in root.rglob("*") if p.is_file() and "/refined/" in str(p)] == []
    assert list((services.cache_dir / "samplers").glob(f"{texture['id']}*")) == []


def test_auto_fit_off_queues_nothing(refining, photo, fit_calls) -> None:
    client, services = refining
    services.settings.auto_fit = False
    texture = upload_photo(client, photo)
    assert texture["refinement"] is None and texture["sampler"] == "encoder"
    assert client.get("/v1/jobs").json()["items"] == []
    assert services.pending_count() == 0 and fit_calls == []
    assert client.get(TILE.format(texture["id"])).headers["cache-control"] == CACHE_CONTROL


def test_without_torch_auto_fit_is_skipped_silently(refining, photo, monkeypatch) -> None:
    client, services = refining
    monkeypatch.setattr("service.job_kinds.torch_available", lambda: False)
    texture = upload_photo(client, photo)
    assert texture["refinement"] is None
    assert client.get("/v1/jobs").json()["items"] == []


def test_model_without_checkpoint_is_not_refined(refining, photo) -> None:
    client, services = refining
    (services.settings.model_dirs[0] / "space.pt").unlink()
    assert upload_photo(client, photo)["refinement"] is None


def test_full_queue_does_not_fail_the_upload(refining, photo) -> None:
    client, services = refining
    services.settings.max_queued_fits = 1
    first, second = upload_photo(client, photo), upload_photo(client, photo)
    assert first["refinement"]["state"] == "queued"
    assert second["refinement"]["stage"] == "deferred"          # the fit queue was full: refined later
    assert len(client.get("/v1/jobs").json()["items"]) == 1


def test_refinement_recomputes_the_colour_with_the_fitted_sampler(refining, photo, monkeypatch) -> None:
    from service import job_kinds
    from worker.colour_match import calibrate_texture as real

    client, services = refining
    calls = []

    def calibrate(sampler, code, image, curves="quantile"):  # noqa: ANN001, ANN202
        calls.append((sampler, np.asarray(code).tolist(), image.shape, curves))
        return real(sampler, code, image, curves)

    monkeypatch.setattr(job_kinds, "calibrate_texture", calibrate)
    texture = upload_photo(client, photo)
    calls.clear()
    run_fit_lane(services)
    with services.sessions() as session:
        row = session.get(Texture, texture["id"])
    sampler, code, shape, curves = calls[-1]
    assert curves == "linear"  # the fit's table is the moment transfer it was optimised under
    assert sampler is services.registry.fitted_sampler(services.sampler_path(row.id, row.sampler_key))
    assert code == [0.0] * 8 and shape[2] == 3
    # the photo at the model's working resolution (its shorter side), as at upload
    assert min(shape[:2]) == services.registry.get(row.model_version).manifest.get("exemplar_short_side")
    assert row.colour is not None and len(row.colour) == len(real(sampler, np.zeros(8, np.float32),
                                                                   np.full((64, 64, 3), 0.5, np.float32)))


def test_the_fit_lane_thread_runs_fit_jobs(refining, photo) -> None:
    client, services = refining
    texture = upload_photo(client, photo)
    stop = threading.Event()
    thread = start_lane(services.fit_huey, stop)
    try:
        for _ in range(200):
            state = client.get(f"/v1/jobs/{texture['refinement']['job_id']}").json()["state"]
            if state == "succeeded":
                break
            stop.wait(0.05)
    finally:
        stop.set()
        thread.join(5)
    assert state == "succeeded"
    assert client.get(f"/v1/textures/{texture['id']}").json()["sampler"] == "fitted"


@pytest.mark.parametrize(("kinds", "lanes"), [
    ("volume,bake,region,fit", ["main", "fit"]), ("fit", ["fit"]), ("volume, bake, region", ["main"])])
def test_worker_kinds_pick_the_lanes(tmp_path, kinds, lanes) -> None:
    settings = Settings(data_dir=tmp_path, worker_kinds=kinds)
    assert worker_lanes(settings) == lanes


@pytest.mark.parametrize("kinds", ["volume", "bake,fit", "", "tiles"])
def test_worker_kinds_must_take_whole_queues(tmp_path, kinds) -> None:
    with pytest.raises(ValueError):
        Settings(data_dir=tmp_path, worker_kinds=kinds)


def test_defaults(monkeypatch) -> None:
    for key in ("TEXSPACE_AUTO_FIT", "TEXSPACE_FIT_THREADS", "TEXSPACE_WORKER_KINDS"):
        monkeypatch.delenv(key, raising=False)
    settings = Settings()
    assert settings.auto_fit and settings.fit_threads == 0
    assert worker_lanes(settings) == ["main", "fit"]


def test_a_texture_deleted_during_a_fit_of_it_does_not_come_back_as_its_child(refining, photo, monkeypatch) -> None:
    """POST .../fit, then DELETE the texture while the fit exports: its fitted child appeared
    25 s later, pointing at the deleted texture and serving its photo. Now nothing survives."""
    client, services = refining
    texture = upload_photo(client, photo)
    client.post(f"/v1/jobs/{texture['refinement']['job_id']}/cancel")  # (its refinement: not this test's subject)
    module = sys.modules["model.fit"]
    module_fit = module.fit_exemplar

    @functools.wraps(module_fit)
    def fit_then_delete(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        written = module_fit(*args, **kwargs)
        assert client.delete(f"/v1/textures/{texture['id']}").status_code == 204
        return written

    monkeypatch.setattr(module, "fit_exemplar", fit_then_delete)
    job = client.post(f"/v1/textures/{texture['id']}/fit", json={"seconds": 5}).json()
    run_fit_lane(services)
    names = [t["name"] for t in client.get("/v1/textures").json()["items"]]
    assert names == [] and client.get(f"/v1/jobs/{job['id']}").status_code == 404
    root = services.storage.root
    assert [str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()] == []
