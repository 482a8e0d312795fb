"""Tables made by an older colour recipe are computed again: ``texspace recolour``
(uploads from their photos, refined ones with their fitted sampler's linear table, blends
mixed again), with new tile ETags; tables already current are left alone."""
from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service import recolour
from service.cli import main
from service.context import build_services
from service.db import session_scope
from service.main import create_app
from service.recolour import recolour_textures, stale_colour_textures, warn_if_stale
from service.settings import Settings
from service.tables import Texture
from tests.helpers import brick_png
from tests.service.test_model_versions import second_model
from worker.colour_match import COLOUR_CALIBRATION, blend_textures, calibrate_texture, identity_colour
from worker.encode import code_colour, encode_texture
from worker.images import read_image
from worker.photo import working_photo
from worker.runtime import SamplerSession

TILE = "/v1/textures/{}/tiles/6/0/0.png?size=64"


@pytest.fixture
def world(tmp_path: Path, database: dict) -> Iterator[dict]:
    """Two uploads (the second evened), a blend of them, a blend of a deleted upload, the
    first upload refined in place and a fit's own texture (both with a sampler unlike the
    model's), then every table made stale: identity tables of an unknown recipe. And one
    upload left current."""
    settings = Settings(data_dir=tmp_path / "data", log_json=False, auto_fit=False, **database)
    services = build_services(settings, immediate=True)
    fitted_onnx = (second_model(tmp_path / "other") / "sampler.onnx").read_bytes()
    with TestClient(create_app(services=services)) as client:
        def upload(photo: bytes, name: str, **form: str) -> dict:
            res = client.post("/v1/textures", files={"image": (f"{name}.png", photo)}, data={"name": name, **form})
            assert res.status_code == 201, res.text
            return res.json()

        a, b = upload(brick_png(), "a"), upload(brick_png(64), "b", lighting="even")
        gone = upload(brick_png(80), "gone")
        blend = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": b["id"], "t": 0.3}).json()
        orphan = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": gone["id"], "t": 0.5}).json()
        assert client.delete(f"/v1/textures/{gone['id']}").status_code == 204
        assert stale_colour_textures(services) == []  # what the service makes is current
        current = upload(brick_png(72), "current")
    refined, fitted = f"textures/{a['id']}/refined/job-1/sampler.onnx", "f" * 32
    services.storage.put_bytes(refined, fitted_onnx)
    services.storage.put_bytes(f"textures/{fitted}/sampler.onnx", fitted_onnx)
    services.storage.put_bytes(f"textures/{fitted}/exemplar.png", brick_png(88))
    stale = [float(v) for v in identity_colour(services.registry.get().sampler.colour_size)]
    with session_scope(services.sessions) as session:
        row = session.get(Texture, a["id"])
        row.encoder_code, row.code, row.sampler_key = row.code, [0.1] * 8, refined
        session.add(Texture(id=fitted, name="a (fitted)", code=[0.2] * 8, model_version=a["model_version"],
                            source="fit", parents={"texture": a["id"], "job": "j"},
                            sampler_key=f"textures/{fitted}/sampler.onnx", exemplar_key=f"textures/{fitted}/exemplar.png"))
    with session_scope(services.sessions) as session:
        for row in session.query(Texture).filter(Texture.id != current["id"]):
            row.colour, row.colour_calibration = stale, None
            row.encoder_colour = stale if row.encoder_code is not None else None
    yield {"services": services, "a": a, "b": b, "blend": blend, "orphan": orphan, "fitted": fitted,
           "current": current, "stale": stale}
    services.engine.dispose()


def rows(services) -> dict[str, Texture]:  # noqa: ANN001
    with session_scope(services.sessions) as session:
        found = {t.id: t for t in session.query(Texture)}
        session.expunge_all()
    return found


def test_recolour_computes_stale_tables_again(world: dict) -> None:
    services, a, b = world["services"], world["a"], world["b"]
    model = services.registry.get()
    with TestClient(create_app(services=services)) as client:
        old = client.get(TILE.format(b["id"]))
        before = rows(services)
        dry = recolour_textures(services, dry_run=True)
        assert rows(services)[b["id"]].colour == world["stale"]  # a dry run changes nothing
        report = recolour_textures(services)
        new = client.get(TILE.format(b["id"]))
    assert (dry.recoloured, dry.blended, dry.skipped) == (report.recoloured, report.blended, report.skipped)
    assert report.recoloured == [a["id"], b["id"], world["fitted"]] and report.blended == [world["blend"]["id"]]
    assert "deleted" in report.skipped[world["orphan"]["id"]]
    assert new.headers["etag"] != old.headers["etag"] and new.content != old.content  # the table is in the ETag

    after = rows(services)
    photo = read_image(brick_png(), max_pixels=10**7)
    # an upload's table is what a fresh upload of its photo gets (evened where it was)
    np.testing.assert_allclose(after[b["id"]].colour, encode_texture(model, read_image(brick_png(64),
                                                                                       max_pixels=10**7), "even")[1])
    # a refined upload: the kept encoder code's table, and the fitted sampler's linear one
    np.testing.assert_allclose(after[a["id"]].encoder_colour, encode_texture(model, photo)[1], atol=1e-6)
    fitted_sampler = services.sampler_for(after[a["id"]])
    assert isinstance(fitted_sampler, SamplerSession) and fitted_sampler.path != model.sampler.path
    image = working_photo(photo, model.short_side)
    linear = calibrate_texture(fitted_sampler, np.full(8, 0.1, np.float32), image, curves="linear")
    np.testing.assert_allclose(after[a["id"]].colour, linear, atol=1e-6)
    assert np.abs(linear - calibrate_texture(fitted_sampler, np.full(8, 0.1, np.float32), image)).max() > 1e-3
    # a fit's own texture: from its own photo copy, with its sampler
    own = calibrate_texture(fitted_sampler, np.full(8, 0.2, np.float32),
                            working_photo(read_image(brick_png(88), max_pixels=10**7), model.short_side), "linear")
    np.testing.assert_allclose(after[world["fitted"]].colour, own, atol=1e-6)
    # the blend: its parents' new tables at its t; its code unchanged
    mixed = blend_textures(after[a["id"]].model_space(), after[b["id"]].model_space(), 0.3, model.sampler.colour_size)
    np.testing.assert_allclose(after[world["blend"]["id"]].colour, mixed[1], atol=1e-9)
    assert after[world["blend"]["id"]].code == before[world["blend"]["id"]].code
    for texture_id in (a["id"], b["id"], world["fitted"], world["blend"]["id"]):
        assert after[texture_id].colour_calibration == COLOUR_CALIBRATION
        assert after[texture_id].code == before[texture_id].code  # codes and samplers stay
        assert after[texture_id].sampler_key == before[texture_id].sampler_key
    orphan = after[world["orphan"]["id"]]
    assert orphan.colour == world["stale"] and orphan.colour_calibration is None  # reported, left as it was
    assert after[world["current"]["id"]].updated_at == before[world["current"]["id"]].updated_at

    again = recolour_textures(services)  # idempotent: only the orphan is left
    assert (again.recoloured, again.blended, list(again.skipped)) == ([], [], [world["orphan"]["id"]])


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_the_api_start_names_the_command_while_tables_are_stale(world: dict, caplog) -> None:
    services = world["services"]
    with caplog.at_level("WARNING", logger="service.recolour"):
        assert warn_if_stale(services) == 5  # a, b, the fit's, the blend, the orphan
    assert "5 textures" in caplog.text and "texspace recolour" in caplog.text
    recolour_textures(services)
    caplog.clear()
    with caplog.at_level("WARNING", logger="service.recolour"):
        assert warn_if_stale(services) == 1  # the orphan, reported by the command


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_a_texture_refined_meanwhile_is_skipped(world: dict, monkeypatch) -> None:
    services, b = world["services"], world["b"]

    def calibrate_while_refined(runtime, image, code):  # noqa: ANN001, ANN202
        if np.allclose(code[:8], b["code"]):  # a refinement of b lands while its table is computed
            with session_scope(services.sessions) as session:
                session.get(Texture, b["id"]).sampler_key = f"textures/{b['id']}/refined/job-2/sampler.onnx"
        return code_colour(runtime, image, code)

    monkeypatch.setattr(recolour, "code_colour", calibrate_while_refined)
    report = recolour_textures(services)
    assert "run recolour again" in report.skipped[b["id"]]
    assert rows(services)[b["id"]].colour == world["stale"]
    # the blend of it is not mixed from a stale parent
    assert f"parent {b['id']}" in report.skipped[world["blend"]["id"]]


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_a_blend_of_a_stale_parent_is_stale(world: dict) -> None:
    services = world["services"]
    with TestClient(create_app(services=services)) as client:
        mixed = client.post("/v1/textures/interpolate",
                            json={"a": world["current"]["id"], "b": world["b"]["id"], "t": 0.5}).json()
        fresh = client.post("/v1/textures/interpolate",
                            json={"a": world["current"]["id"], "b": world["current"]["id"], "t": 0.5}).json()
    found = rows(services)
    assert found[mixed["id"]].colour_calibration is None and found[fresh["id"]].colour_calibration == COLOUR_CALIBRATION
    assert mixed["id"] in {t.id for t in stale_colour_textures(services)}


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_cli_recolour(tmp_path: Path, world: dict, monkeypatch, capsys) -> None:
    for key in [k for k in os.environ if k.startswith("TEXSPACE_")]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TEXSPACE_AUTO_FIT", "false")
    main(["recolour", "--dry-run"])
    out = capsys.readouterr().out
    assert out.startswith(f"would recolour 3 textures (from their photos) and 1 blends with colour calibration "
                          f"{COLOUR_CALIBRATION}") and f"skipped {world['orphan']['id']}" in out
    assert rows(world["services"])[world["b"]["id"]].colour == world["stale"]
    with pytest.raises(SystemExit) as exit_:  # the orphan blend cannot be mixed: the run says so and fails
        main(["recolour"])
    assert exit_.value.code == 1 and capsys.readouterr().out.startswith("recoloured 3 textures")
    assert rows(world["services"])[world["b"]["id"]].colour_calibration == COLOUR_CALIBRATION
