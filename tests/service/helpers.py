"""Plain helpers of the service tests (fixtures live in conftest.py)."""
from __future__ import annotations

import datetime as dt
import json
import shutil
import types
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.db import session_scope
from service.tables import Job, utcnow

#: the shipped model export the service tests serve and the stand-in fit copies
MODEL_DIR = Path(__file__).resolve().parents[2] / "model" / "weights"

# What the stand-in fit (``fake_fit_module``) reports and writes
FAKE_LATTICE = [0.5, 0.0, -0.21875, 0.166875]
FAKE_TURN = -6.86  # degrees a leaning grain was turned (vpython_wood_old's lean)
FAKE_MUTED = 4  # coarse octaves an even photo's fit mutes at 256 px a unit
FAKE_LEAN = [-39.14, 1.258]  # the validation granite's (model.structure.photo_lean)

FAKE_INTERIM_CODE = [0.5] * 8  # the code of the stand-in's interim


def fake_fit_module(calls: list[dict]) -> types.ModuleType:
    """A stand-in for model.fit (no torch): it writes the shipped sampler as the fit's and
    reports what the real one would have used. With ``module.during_interim`` set (a
    callable), a fit given a ``interim`` hook publishes an interim first (the shipped sampler
    again, FAKE_INTERIM_CODE, step 25) and then calls it, as the real fit goes on meanwhile;
    unset, it publishes none (a real fit whose start stayed best until then)."""
    def fit_exemplar(image_path, out_dir, *, init_checkpoint=None, minutes=4.0, patch=64, grain="auto",  # noqa: ANN001, ANN202
                     loss="gram", progress=None, quiet=True, seed=0, threads=0, device="cpu", lattice="auto",
                     rate="falling", spectrum=0.0, even="auto", lean="auto", interim=None, interim_seconds=60.0,
                     precision="auto", run_dir=None, pause=None, shade="auto", detail_seconds=0.0,
                     wants_detail=None, start_code=None):
        calls.append({"image_path": Path(image_path), "image_bytes": Path(image_path).read_bytes(),
                      "init_checkpoint": Path(init_checkpoint),
                      "minutes": minutes, "grain": grain, "threads": threads, "lattice": lattice, "even": even,
                      "lean": lean, "interim": interim, "interim_seconds": interim_seconds, "device": device,
                      "precision": precision, "pause": pause, "detail_seconds": detail_seconds,
                      "wants_detail": wants_detail, "start_code": start_code})
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        # what model.fit reports it used: the grain asked for (straightened by FAKE_TURN), a
        # lattice when asked to detect one
        structure = {"grain": grain if grain in ("x", "y") else None,
                     "straightened": FAKE_TURN if grain in ("x", "y") else 0.0,
                     "grain_stretch": 16.0 if grain in ("x", "y") else None,
                     "lattice": FAKE_LATTICE if lattice == "auto" else None,
                     "muted_octaves": FAKE_MUTED if even == "auto" and not grain and not lattice else 0,
                     "lean": FAKE_LEAN if lean == "auto" and not grain and not lattice else None}
        if interim is not None and module.during_interim is not None:
            (out_dir / "interim").mkdir()
            shutil.copy(MODEL_DIR / "sampler.onnx", out_dir / "interim" / "sampler.onnx")
            interim(out_dir / "interim", FAKE_INTERIM_CODE, 25, dict(structure))
            module.during_interim()
        if pause is not None and pause():  # as model.fit, at the interim's second, published or not:
            Path(run_dir).mkdir(parents=True, exist_ok=True)  # the run's state kept in run_dir, nothing exported
            (Path(run_dir) / "checkpoint.pt").write_bytes(b"paused at step 25")
            return {"paused": True, "steps": 25, **structure}
        for name in ("sampler.onnx", "sampler_tileable.onnx"):  # (the pair model.fit writes)
            shutil.copy(MODEL_DIR / name, out_dir / name)
        (out_dir / "code.json").write_text(json.dumps({"code": [0.0] * 8}))
        # as model.fit, once the fit ends: whether its detail stage would run (None: not asked)
        calls[-1]["detail_wanted"] = wants_detail() if detail_seconds > 0 and wants_detail is not None else None
        if progress:
            progress(1.0)
        return {"code": [0.0] * 8, "sampler": str(out_dir / "sampler.onnx"), "version": "fake", "steps": 1,
                **structure}

    module = types.ModuleType("model.fit")
    module.fit_exemplar = fit_exemplar
    module.during_interim = None
    return module


def upload_photo(client: TestClient, photo: bytes, **form: str) -> dict:
    """POST a PNG to /v1/textures (``form``: e.g. name=...); the 201 answer's texture."""
    res = client.post("/v1/textures", files={"image": ("brick.png", photo, "image/png")}, data=form)
    assert res.status_code == 201, res.text
    return res.json()


def tile_url(texture: dict, z: int, x: int, y: int, fmt: str = "png") -> str:
    """The API path of tile (z, x, y) of an uploaded texture."""
    return f"/v1/textures/{texture['id']}/tiles/{z}/{x}/{y}.{fmt}"


def run_fit_lane(services) -> None:
    """Run the next message on the fit lane (the queue keeps them: MemoryHuey)."""
    task = services.fit_huey.dequeue()
    assert task is not None, "no message on the fit lane"
    services.fit_huey.execute(task)


def drain_fit_lane(services, limit: int = 20) -> None:
    """Run the fit lane's messages until none is left (fails after ``limit``)."""
    for _ in range(limit):
        if not services.fit_huey.pending_count():
            return
        run_fit_lane(services)
    pytest.fail("the fit lane never emptied")


def add_fit(services, owner: str | None, minutes_ago: float, **values) -> str:
    """A queued in-place fit job of tenant ``owner``, created ``minutes_ago``, with no message
    on the lane (``values``: other columns, ``state`` too); its id."""
    job = Job(kind="fit", texture_id=None, params={"in_place": True, "seconds": 90.0},
              owner_id=owner, created_at=utcnow() - dt.timedelta(minutes=minutes_ago), **{"state": "queued", **values})
    with session_scope(services.sessions) as session:
        session.add(job)
    return job.id
