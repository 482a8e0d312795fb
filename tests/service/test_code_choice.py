"""Uploads whose code was chosen by an older recipe get today's, on their own model:
``texspace reencode --stale-codes`` (refined uploads keep their fits, blends mixed again)."""
from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.cli import main
from service.context import build_services
from service.db import session_scope
from service.main import create_app
from service.reencode import choose_codes_again, stale_choice_textures, warn_if_stale_choice
from service.settings import Settings
from service.tables import Texture
from tests.helpers import brick_png
from tests.service.test_recolour import rows
from worker.colour_match import blend_textures
from worker.encode import CODE_CHOICE, encode_texture
from worker.images import read_image

OLD_CODE = [0.3] * 8  # what an older recipe chose (the crops' mean, say)


@pytest.fixture
def world(tmp_path: Path, database: dict) -> Iterator[dict]:
    """Uploads a (then refined in place), b (evened) and current, a blend of a and b, a fit's
    own texture; then a's and b's codes made those of an older recipe (NULL)."""
    settings = Settings(data_dir=tmp_path / "data", log_json=False, auto_fit=False, **database)
    services = build_services(settings, immediate=True)
    with TestClient(create_app(services=services)) as client:
        def upload(photo: bytes, name: str, **form: str) -> dict:
            res = client.post("/v1/textures", files={"image": (f"{name}.png", photo)}, data={"name": name, **form})
            assert res.status_code == 201, res.text
            return res.json()

        a, b, current = upload(brick_png(), "a"), upload(brick_png(64), "b", lighting="even"), upload(brick_png(72), "c")
        blend = client.post("/v1/textures/interpolate", json={"a": a["id"], "b": b["id"], "t": 0.3}).json()
        assert stale_choice_textures(services) == []  # what the service makes is current
    refined, fitted = f"textures/{a['id']}/refined/job-1/sampler.onnx", "f" * 32
    with session_scope(services.sessions) as session:
        assert session.get(Texture, a["id"]).code_choice == CODE_CHOICE
        row = session.get(Texture, a["id"])
        row.encoder_code, row.encoder_colour = OLD_CODE, row.colour
        row.code, row.sampler_key, row.code_choice = [0.1] * 8, refined, None
        row = session.get(Texture, b["id"])
        row.code, row.code_choice = OLD_CODE, None
        session.add(Texture(id=fitted, name="a (fitted)", code=[0.2] * 8, model_version=a["model_version"],
                            source="fit", parents={"texture": a["id"], "job": "j"}, sampler_key="x.onnx",
                            exemplar_key=f"textures/{a['id']}/exemplar.png"))
    yield {"services": services, "a": a, "b": b, "current": current, "blend": blend, "fitted": fitted,
           "refined": refined}
    services.engine.dispose()


def test_stale_uploads_get_todays_code_and_keep_their_fits(world: dict, caplog) -> None:
    services, a, b, blend = (world[k] for k in ("services", "a", "b", "blend"))
    with caplog.at_level("WARNING", logger="service.reencode"):
        assert warn_if_stale_choice(services) == 2  # a and b; not the fit's own texture, not c
    assert "2 uploads" in caplog.text and "texspace reencode --stale-codes" in caplog.text
    before = rows(services)

    dry = choose_codes_again(services, dry_run=True)
    assert rows(services)[b["id"]].code == OLD_CODE  # a dry run changes nothing
    report = choose_codes_again(services)
    assert (dry.encoded, dry.blended) == (report.encoded, report.blended) == ([a["id"], b["id"]], [blend["id"]])
    assert report.skipped == {}

    after, runtime = rows(services), services.registry.get()
    code, colour = encode_texture(runtime, read_image(brick_png(), max_pixels=10**7))
    # a was refined: it serves its fit still; the code it keeps for blends is today's
    assert after[a["id"]].code == [0.1] * 8 and after[a["id"]].sampler_key == world["refined"]
    np.testing.assert_allclose(after[a["id"]].encoder_code, code, atol=1e-6)
    np.testing.assert_allclose(after[a["id"]].encoder_colour, colour, atol=1e-6)
    code, colour = encode_texture(runtime, read_image(brick_png(64), max_pixels=10**7), "even")
    np.testing.assert_allclose(after[b["id"]].code, code, atol=1e-6)  # evened, as it was uploaded
    np.testing.assert_allclose(after[b["id"]].colour, colour, atol=1e-6)
    assert after[a["id"]].code_choice == after[b["id"]].code_choice == CODE_CHOICE
    mixed = blend_textures(after[a["id"]].model_space(), after[b["id"]].model_space(), 0.3,
                           runtime.sampler.colour_size)
    np.testing.assert_allclose(after[blend["id"]].code, mixed[0], atol=1e-9)
    for untouched in (world["current"]["id"], world["fitted"]):
        assert after[untouched].code == before[untouched].code
        assert after[untouched].updated_at == before[untouched].updated_at
    assert stale_choice_textures(services) == [] and warn_if_stale_choice(services) == 0


def test_an_upload_refined_meanwhile_is_skipped(world: dict, monkeypatch) -> None:
    services, b = world["services"], world["b"]
    real, calls = encode_texture, []

    def refined_while_encoding(*args, **kwargs):  # noqa: ANN002, ANN003
        calls.append(1)
        if len(calls) == 2:  # b's photo (oldest first): its refinement lands meanwhile
            with session_scope(services.sessions) as session:
                row = session.get(Texture, b["id"])
                row.encoder_code, row.code, row.sampler_key = row.code, [0.5] * 8, "landed.onnx"
        return real(*args, **kwargs)

    monkeypatch.setattr("service.reencode.encode_texture", refined_while_encoding)
    report = choose_codes_again(services)
    assert "run the command again" in report.skipped[b["id"]]
    after = rows(services)[b["id"]]
    assert (after.code, after.encoder_code, after.code_choice) == ([0.5] * 8, OLD_CODE, None)  # the fit's landing kept
    assert [t.id for t in stale_choice_textures(services)] == [b["id"]]


@pytest.mark.parametrize("database", ["sqlite"], indirect=True)
def test_cli_reencode_stale_codes(tmp_path: Path, world: dict, monkeypatch, capsys) -> None:
    for key in [k for k in os.environ if k.startswith("TEXSPACE_")]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TEXSPACE_AUTO_FIT", "false")
    main(["reencode", "--stale-codes", "--dry-run"])
    assert capsys.readouterr().out.startswith("would choose the codes of 2 uploads again")
    main(["reencode", "--stale-codes"])
    assert capsys.readouterr().out.startswith("chose the codes of 2 uploads again")
    main(["reencode", "--stale-codes"])
    assert capsys.readouterr().out.startswith("chose the codes of 0 uploads again")
    with pytest.raises(SystemExit) as exit_:
        main(["reencode", "--stale-codes", "--from", "0123456789abcdef"])
    assert exit_.value.code == 2 and "--stale-codes" in capsys.readouterr().err
