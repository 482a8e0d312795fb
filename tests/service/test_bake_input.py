"""A bake's mesh is parsed once, by the API at submission (a bad mesh is a 422 then): the
job's input is the parsed arrays, and the worker bakes them without reading the file again."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from worker import bake
from worker.bake import PARSED_MESH, mesh_from_npz, mesh_npz, read_mesh

CUBE = Path(__file__).resolve().parents[1] / "data" / "meshes" / "cube.obj"
BUNNY = Path(__file__).resolve().parents[1] / "data" / "meshes" / "bunny_uv.obj"


def test_a_parsed_mesh_round_trips_through_its_npz() -> None:
    for path in (CUBE, BUNNY):
        mesh = read_mesh(path.read_bytes(), path.name)
        again = mesh_from_npz(mesh_npz(mesh))
        for name in ("vertices", "faces", "uv", "normals"):
            a, b = getattr(mesh, name), getattr(again, name)
            assert (a is None and b is None) or (np.array_equal(a, b) and a.dtype == b.dtype), name


def test_the_worker_bakes_the_apis_parse(client, texture, services, monkeypatch) -> None:
    calls = []
    real = bake.read_mesh
    monkeypatch.setattr(bake, "read_mesh", lambda *args, **kw: calls.append(args[1]) or real(*args, **kw))
    job = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", CUBE.read_bytes())},
                      data={"resolution": "32"}).json()
    done = client.get(job["links"]["self"]).json()
    assert done["state"] == "succeeded", done
    assert calls == []  # the API parsed it (service.limits.check_mesh); the job read the arrays
    inputs = services.storage.root / "jobs" / job["id"] / "input"
    assert [p.name for p in inputs.iterdir()] == [PARSED_MESH]
