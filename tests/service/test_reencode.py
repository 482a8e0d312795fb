"""Retiring a model loses no texture: ``texspace reencode`` moves its textures onto the
loaded model (photos encoded again, blends mixed again, refinements queued)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.cli import main
from service.context import build_services
from service.db import session_scope
from service.main import create_app
from service.reencode import reencode_textures
from service.settings import PACKAGED_MODEL_DIR, Settings
from service.tables import Job, Texture
from tests.helpers import brick_png
from tests.service.test_model_versions import second_model
from worker.colour_match import blend_textures
from worker.encode import encode_texture
from worker.images import read_image


@pytest.fixture
def settings_for(tmp_path: Path, database: dict):
    def settings_for(model_dir: Path, **extra) -> Settings:
        return Settings(data_dir=tmp_path / "data", model_dirs=[model_dir], log_json=False,
                        **{"auto_fit": False, **database, **extra})
    return settings_for


@pytest.fixture
def old_world(tmp_path: Path, settings_for) -> dict:
    """Under the old model: two uploads (the second with its lighting evened), a blend of
    them, a blend of a deleted texture, and the first upload refined (its sampler file in
    storage)."""
    old_dir = tmp_path / "models" / "old"
    shutil.copytree(PACKAGED_MODEL_DIR, old_dir)
    services = build_services(settings_for(old_dir), immediate=True)
    with TestClient(create_app(services=services)) as client:
        def upload(photo: bytes, name: str, **form: str) -> dict:
            return client.post("/v1/textures", files={"image": (f"{name}.png", photo)},
                               data={"name": name, **form}).json()

        a, b = upload(brick_png(), "a"), upload(brick_png(64), "b", lighting="even")
        gone = upload(brick_png(80), "gone")
        blend = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": b["id"], "t": 0.3}).json()
        orphan = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": gone["id"], "t": 0.5}).json()
        assert client.delete(f"/v1/textures/{gone['id']}").status_code == 204
        tile = client.get(f"/v1/textures/{a['id']}/tiles/6/0/0.png?size=64")
    refined = f"textures/{a['id']}/refined/job-1/sampler.onnx"
    services.storage.put_bytes(refined, b"a sampler fitted in the old space")
    # a fit's own texture (POST .../fit): its photo, and its sampler pair beside it
    fitted = "f" * 32
    own = [f"textures/{fitted}/{name}" for name in ("exemplar.png", "sampler.onnx", "sampler_tileable.onnx")]
    for key in own:
        services.storage.put_bytes(key, brick_png(72) if key.endswith(".png") else b"fitted in the old space")
    with session_scope(services.sessions) as session:
        row = session.get(Texture, a["id"])
        row.encoder_code, row.encoder_colour, row.code, row.sampler_key = row.code, row.colour, [0.0] * 8, refined
        row.structure = {"grain": None, "lattice": None}
        session.add(Texture(id=fitted, name="a (fitted)", code=[0.0] * 8, model_version=a["model_version"],
                            source="fit", parents={"texture": a["id"], "job": "j"}, exemplar_key=own[0],
                            sampler_key=own[1], structure={"grain": None, "lattice": None}))
    services.engine.dispose()
    return {"a": a, "b": b, "blend": blend, "orphan": orphan, "old_etag": tile.headers["etag"],
            "refined": refined, "fitted": fitted, "own": own, "new_dir": second_model(tmp_path / "models" / "new")}


def test_reencode_moves_retired_textures_onto_the_loaded_model(old_world: dict, settings_for) -> None:
    a, b, blend, orphan = (old_world[k] for k in ("a", "b", "blend", "orphan"))
    services = build_services(settings_for(old_world["new_dir"]), immediate=True)
    new = services.registry.get()
    url = f"/v1/textures/{a['id']}/tiles/6/0/0.png?size=64"
    with TestClient(create_app(services=services)) as client:
        retired = client.get(url)  # the old model is retired: the answer says what brings it back
        assert retired.status_code == 503 and "texspace reencode" in retired.json()["detail"]

        dry = reencode_textures(services, dry_run=True)
        assert client.get(url).status_code == 503  # a dry run changes nothing
        report = reencode_textures(services)
        assert (dry.encoded, dry.blended, dry.skipped) == (report.encoded, report.blended, report.skipped)
        assert report.target == new.version and report.refinements == []  # refinement is off here
        assert report.encoded == [a["id"], b["id"], old_world["fitted"]] and report.blended == [blend["id"]]
        assert "deleted" in report.skipped[orphan["id"]]

        tile = client.get(url)
        assert tile.status_code == 200 and tile.headers["etag"] != old_world["old_etag"]
        moved = {t["id"]: t for t in client.get("/v1/textures").json()["items"]}
        assert moved[a["id"]]["model_version"] == new.version
        assert moved[orphan["id"]]["model_version"] == a["model_version"]  # reported, left as it was

    with session_scope(services.sessions) as session:
        rows = {t.id: t for t in session.query(Texture)}
    # the photo's code in the new space, as a fresh upload of it gets; the old fit is gone
    code, colour = encode_texture(new, read_image(brick_png(), max_pixels=10**7))
    np.testing.assert_allclose(rows[a["id"]].code, code, atol=1e-6)
    np.testing.assert_allclose(rows[a["id"]].colour, colour, atol=1e-6)
    assert rows[a["id"]].sampler_key is rows[a["id"]].encoder_code is rows[a["id"]].structure is None
    # a photo uploaded to be evened is evened again
    code, colour = encode_texture(new, read_image(brick_png(64), max_pixels=10**7), "even")
    assert rows[b["id"]].lighting == "even"
    np.testing.assert_allclose(rows[b["id"]].code, code, atol=1e-6)
    assert not services.storage.exists(old_world["refined"])
    photo, *samplers = old_world["own"]  # the fit's own texture keeps its photo, not its old samplers
    assert services.storage.exists(photo) and not any(services.storage.exists(k) for k in samplers)
    assert rows[old_world["fitted"]].sampler_key is None and rows[old_world["fitted"]].model_version == new.version
    # the blend: its parents' new values mixed at its t
    mixed = blend_textures((rows[a["id"]].code, rows[a["id"]].colour), (rows[b["id"]].code, rows[b["id"]].colour),
                           0.3, new.sampler.colour_size)
    np.testing.assert_allclose(rows[blend["id"]].code, mixed[0], atol=1e-9)
    np.testing.assert_allclose(rows[blend["id"]].colour, mixed[1], atol=1e-9)
    assert reencode_textures(services).encoded == []  # nothing left on a retired model but the orphan
    services.engine.dispose()


def test_reencode_queues_refinements_for_the_owners(old_world: dict, settings_for) -> None:
    pytest.importorskip("torch", reason="refinement needs the train extra")
    # a real (not immediate) queue: the fit jobs wait for a worker
    services = build_services(settings_for(old_world["new_dir"], auto_fit=True))
    report = reencode_textures(services)
    assert report.refinements == report.encoded == [old_world["a"]["id"], old_world["b"]["id"], old_world["fitted"]]
    with session_scope(services.sessions) as session:
        for texture_id in report.refinements:
            texture = session.get(Texture, texture_id)
            job = session.get(Job, texture.refinement_job_id)
            assert (job.kind, job.state, job.texture_id, job.params["in_place"]) == ("fit", "queued", texture_id, True)
            assert job.owner_id == texture.owner_id
    services.engine.dispose()


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_cli_reencode(tmp_path: Path, old_world: dict, monkeypatch, capsys) -> None:
    for key in [k for k in os.environ if k.startswith("TEXSPACE_")]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TEXSPACE_MODEL_DIRS", str(old_world["new_dir"]))
    monkeypatch.setenv("TEXSPACE_AUTO_FIT", "false")
    main(["reencode", "--dry-run"])
    out = capsys.readouterr().out
    assert out.startswith("would move 3 textures (photo encoded again) and 1 blends") and "skipped" in out
    with pytest.raises(SystemExit) as exit_:  # the orphan blend cannot move: the run says so and fails
        main(["reencode"])
    assert exit_.value.code == 1
    assert capsys.readouterr().out.startswith("moved 3 textures")
    with pytest.raises(SystemExit) as exit_:
        main(["reencode", "--to", "0123456789abcdef"])
    assert exit_.value.code == 2 and "not loaded" in capsys.readouterr().err
