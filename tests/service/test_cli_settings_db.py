"""The texspace CLI without a server, settings from the environment, and migrations
that match the ORM tables."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from sqlalchemy import create_engine

from service.cli import main
from service.db import migrate
from service.settings import PACKAGED_MODEL_DIR, Settings
from service.tables import Base
from tests.helpers import brick_png, shaded_png

MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"


def test_cli_encode_tile_volume_bake(cli_env: Path, capsys) -> None:
    main(["encode", "brick.png"])
    out = json.loads(capsys.readouterr().out)
    assert len(out["code"]) == 8 and len(out["model_version"]) == 16
    main(["tile", "brick.png", "6", "-2", "5", "--size", "64", "-o", "t.png"])
    assert Image.open(cli_env / "t.png").size == (64, 64)
    # --lighting even: the photo's shading divided out first, as an upload with lighting=even
    (cli_env / "shaded.png").write_bytes(shaded_png())
    capsys.readouterr()
    main(["encode", "shaded.png", "--lighting", "even"])
    evened = json.loads(capsys.readouterr().out)["code"]
    main(["encode", "shaded.png"])
    assert not np.allclose(evened, json.loads(capsys.readouterr().out)["code"], atol=1e-3)
    main(["tile", "shaded.png", "6", "0", "0", "--size", "64", "--lighting", "even", "-o", "e.png"])
    assert Image.open(cli_env / "e.png").size == (64, 64)
    main(["volume", "brick.png", "--resolution", "8", "-o", "v.npy"])
    assert np.load(cli_env / "v.npy").shape == (8, 8, 8, 3)
    main(["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "--resolution", "64", "-o", "c.glb"])
    scene = trimesh.load(cli_env / "c.glb")
    solid = next(iter(scene.geometry.values())).visual.material.baseColorTexture
    assert solid.size == (64, 64)
    main(["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "--resolution", "64", "-o", "tri.glb",
          "--projection", "triplanar"])
    triplanar = next(iter(trimesh.load(cli_env / "tri.glb").geometry.values())).visual.material.baseColorTexture
    assert triplanar.size == (64, 64) and not np.array_equal(np.asarray(triplanar), np.asarray(solid))


def test_cli_tile_of_stored_texture_matches_api(cli_env: Path, capsys) -> None:
    from fastapi.testclient import TestClient

    from service.context import build_services
    from service.main import create_app

    services = build_services(Settings(), immediate=True)
    with TestClient(create_app(services=services)) as client:
        texture = client.post("/v1/textures", files={"image": ("b.png", brick_png())}).json()
        api_tile = client.get(f"/v1/textures/{texture['id']}/tiles/6/1/1.png?size=64").content
    capsys.readouterr()
    main(["tile", texture["id"], "6", "1", "1", "--size", "64", "-o", "stored.png"])
    assert (cli_env / "stored.png").read_bytes() == api_tile
    assert "alembic" not in capsys.readouterr().err.lower()  # the lookup's migrations log quietly
    with pytest.raises(SystemExit) as exit_info:
        main(["tile", "no-such-texture", "6", "0", "0"])
    assert exit_info.value.code == 2
    assert "neither an image file nor a texture id" in capsys.readouterr().err


def test_settings_from_environment(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TEXSPACE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("TEXSPACE_MODEL_DIRS", f"{tmp_path}/a{os.pathsep}{tmp_path}/b")
    monkeypatch.setenv("TEXSPACE_QUEUE_BACKEND", "redis")
    monkeypatch.setenv("TEXSPACE_MAX_UPLOAD_BYTES", "2048")
    settings = Settings()
    assert settings.model_dirs == [tmp_path / "a", tmp_path / "b"]
    assert settings.queue_backend == "redis" and settings.max_upload_bytes == 2048
    assert settings.resolved_database_url == f"sqlite:///{tmp_path.resolve()}/texspace.db"
    monkeypatch.setenv("TEXSPACE_QUEUE_BACKEND", "kafka")
    with pytest.raises(ValueError):
        Settings()
    monkeypatch.delenv("TEXSPACE_MODEL_DIRS")
    monkeypatch.delenv("TEXSPACE_QUEUE_BACKEND")
    assert Settings().model_dirs == [PACKAGED_MODEL_DIR]


def test_migrations_match_tables(tmp_path: Path) -> None:
    """Alembic's head schema is exactly the ORM metadata (no autogenerate diff)."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    url = f"sqlite:///{tmp_path / 'm.db'}"
    migrate(url)
    migrate(url)  # idempotent
    engine = create_engine(url)
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []
