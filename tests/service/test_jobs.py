"""Jobs through the real app with tasks run in-process (huey immediate mode) or held in
an in-memory queue to observe queued / running states."""
from __future__ import annotations

import datetime as dt
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from sqlalchemy import update

from service import jobs
from service.context import build_services
from service.main import create_app
from service.runner import Lease, run_job_attempt
from service.schemas import bake_projection
from service.tables import Job
from worker.errors import InvalidParameter

MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"


def submit_volume(client: TestClient, texture: dict, **body) -> dict:
    res = client.post(texture["links"]["volumes"], json={"resolution": 8, **body})
    assert res.status_code == 202, res.text
    assert res.headers["location"] == f"/v1/jobs/{res.json()['id']}"
    return res.json()


def test_volume_job_npy_result(client, texture) -> None:
    job = submit_volume(client, texture, seed=3, bounds=[[0, 0, 0], [0.5, 0.5, 0.5]])
    done = client.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "succeeded", done
    assert done["progress"] == 1.0 and done["attempt"] == 1
    assert done["started_at"] and done["finished_at"]
    res = client.get(done["links"]["result"])
    assert res.status_code == 200
    volume = np.load(io.BytesIO(res.content))
    assert volume.shape == (8, 8, 8, 3) and volume.dtype == np.float32
    assert np.isfinite(volume).all() and volume.min() >= 0 and volume.max() <= 1
    again = client.get(client.post(texture["links"]["volumes"], json={
        "resolution": 8, "seed": 3, "bounds": [[0, 0, 0], [0.5, 0.5, 0.5]]}).json()["links"]["self"]).json()
    assert np.array_equal(np.load(io.BytesIO(client.get(again["links"]["result"]).content)), volume)


def test_volume_limits_and_validation(client, texture) -> None:
    too_big = client.post(texture["links"]["volumes"], json={"resolution": 33})
    assert too_big.status_code == 413 and too_big.headers["content-type"] == "application/problem+json"
    bad_bounds = client.post(texture["links"]["volumes"], json={"bounds": [[0, 0, 0], [1, -1, 1]]})
    assert bad_bounds.status_code == 422
    bad_format = client.post(texture["links"]["volumes"], json={"format": "openvdb"})
    assert bad_format.status_code == 422
    assert client.post("/v1/textures/missing/volumes", json={}).status_code == 404


def test_idempotency_key_returns_same_job(client, texture) -> None:
    headers = {"Idempotency-Key": "vol-1"}
    first = client.post(texture["links"]["volumes"], json={"resolution": 8}, headers=headers)
    second = client.post(texture["links"]["volumes"], json={"resolution": 8}, headers=headers)
    assert first.status_code == second.status_code == 202
    assert first.json()["id"] == second.json()["id"]
    assert second.headers["idempotent-replayed"] == "true"
    assert len(client.get("/v1/jobs").json()["items"]) == 1
    different = client.post(texture["links"]["volumes"], json={"resolution": 16}, headers=headers)
    assert different.status_code == 422 and "Idempotency-Key" in different.json()["detail"]


def test_idempotency_fingerprint_leaves_out_defaults(client, texture) -> None:
    # A retry that spells out a default, or one sent again after an upgrade added an option
    # with a default, is the same request; a value off the default is not.
    headers = {"Idempotency-Key": "vol-defaults"}
    first = client.post(texture["links"]["volumes"], json={"resolution": 8}, headers=headers)
    spelled = client.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 0}, headers=headers)
    assert spelled.status_code == 202 and spelled.json()["id"] == first.json()["id"]
    other_seed = client.post(texture["links"]["volumes"], json={"resolution": 8, "seed": 5}, headers=headers)
    assert other_seed.status_code == 422


def test_bake_glb_loads_with_texture(client, texture) -> None:
    mesh = (MESHES / "cube.obj").read_bytes()
    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                      data={"resolution": "64", "seed": "1", "format": "glb"})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    result = client.get(job["links"]["result"])
    assert result.headers["content-type"] == "model/gltf-binary"
    scene = trimesh.load(io.BytesIO(result.content), file_type="glb")
    geometry = next(iter(scene.geometry.values()))
    image = geometry.visual.material.baseColorTexture
    assert image is not None and image.size == (64, 64)
    assert len(geometry.faces) == 12


def test_volume_vdb_and_exr_jobs(client, texture) -> None:
    bounds = [[0, 0, 0], [2, 1, 0.5]]
    vdb = client.get(submit_volume(client, texture, format="vdb", bounds=bounds)["links"]["self"]).json()
    assert vdb["state"] == "succeeded", vdb
    assert vdb["result"]["media_type"] == "application/x-vdb" and vdb["result"]["filename"].endswith(".vdb")
    raw = client.get(vdb["links"]["result"]).content
    assert raw[:8] == b" BDV\0\0\0\0" and b"Tree_vec3s_5_4_3" in raw[:200]
    exr = client.get(submit_volume(client, texture, format="exr", bounds=bounds)["links"]["self"]).json()
    assert exr["state"] == "succeeded", exr
    assert b"boundsMin" in client.get(exr["links"]["result"]).content[:4096]


def test_bake_with_maps_and_gpu_texture(client, texture) -> None:
    from PIL import Image

    mesh = (MESHES / "cube.obj").read_bytes()
    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                      data={"resolution": "64", "format": "glb", "maps": ["normal", "height"], "gpu_format": "dds"})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    assert job["params"]["maps"] == ["height", "normal"] and job["params"]["gpu_format"] == "dds"
    # named for people: texture, mesh, size, seed; the members after the result
    stem = "brick_cube_bake_64px_seed0"
    assert job["result"]["media_type"] == "application/zip" and job["result"]["filename"] == f"{stem}.zip"
    assert len(job["result"]["height_range"]) == 2
    res = client.get(job["links"]["result"])
    assert res.headers["content-disposition"] == f'attachment; filename="{stem}.zip"'
    with zipfile.ZipFile(io.BytesIO(res.content)) as z:
        assert sorted(z.namelist()) == [f"{stem}.glb", f"{stem}_basecolor.dds", f"{stem}_height.png"]
        assert Image.open(io.BytesIO(z.read(f"{stem}_height.png"))).size == (64, 64)
        scene = trimesh.load(io.BytesIO(z.read(f"{stem}.glb")), file_type="glb")
    material = next(iter(scene.geometry.values())).visual.material
    assert material.normalTexture is not None and material.normalTexture.size == (64, 64)
    only_normal = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                              data={"resolution": "64", "maps": "normal"})
    done = client.get(only_normal.json()["links"]["self"]).json()
    assert done["state"] == "succeeded" and done["result"]["media_type"] == "model/gltf-binary"
    assert done["result"]["height_range"] is None
    # a KTX2 goes inside the GLB (KHR_texture_basisu) beside the material maps: the result stays a GLB
    with_ktx2 = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                            data={"resolution": "64", "maps": ["normal", "roughness"], "gpu_format": "ktx2"})
    done = client.get(with_ktx2.json()["links"]["self"]).json()
    assert done["state"] == "succeeded" and done["result"]["media_type"] == "model/gltf-binary"
    assert done["result"]["filename"] == f"{stem}.glb"
    glb = client.get(done["links"]["result"]).content
    gltf = json.loads(glb[20:20 + int.from_bytes(glb[12:16], "little")])
    assert gltf["extensionsUsed"] == ["KHR_texture_basisu"] and gltf["images"][-1]["mimeType"] == "image/ktx2"
    assert {"normalTexture", "pbrMetallicRoughness"} <= set(gltf["materials"][0])
    assert "metallicRoughnessTexture" in gltf["materials"][0]["pbrMetallicRoughness"]
    bad = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)}, data={"maps": "gloss"})
    assert bad.status_code == 422


def baked_atlas(client: TestClient, texture: dict, **form: str) -> tuple[dict, np.ndarray]:
    from PIL import Image

    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", (MESHES / "cube.obj").read_bytes())},
                      data={"resolution": "64", "format": "obj", **form})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    with zipfile.ZipFile(io.BytesIO(client.get(job["links"]["result"]).content)) as z:
        colour = next(name for name in z.namelist() if name.endswith("_basecolor.png"))
        return job, np.asarray(Image.open(io.BytesIO(z.read(colour))))


def test_bake_projection(client, texture) -> None:
    auto_job, auto = baked_atlas(client, texture)
    assert auto_job["params"]["projection"] == "auto"
    _, solid = baked_atlas(client, texture, projection="solid")
    triplanar_job, triplanar = baked_atlas(client, texture, projection="triplanar")
    assert triplanar_job["params"]["projection"] == "triplanar"
    # an encoder texture has no repeat lattice: auto is the solid texture itself
    assert np.array_equal(auto, solid) and not np.array_equal(triplanar, solid)
    bad = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", b"v 0 0 0\n")},
                      data={"projection": "cubic"})
    assert bad.status_code == 422 and "projection" in bad.text


def test_auto_projection_is_triplanar_for_lattice_fits_only() -> None:
    lattice = {"grain": None, "lattice": [0.1, 0.0, 0.05, 0.1]}
    assert bake_projection("auto", lattice) == "triplanar"
    assert bake_projection("auto", {"grain": "y", "lattice": None}) == "solid"  # wood: one log, a true solid
    assert bake_projection("auto", None) == "solid"
    assert bake_projection("solid", lattice) == "solid" and bake_projection("triplanar", None) == "triplanar"


def test_bake_bad_mesh_is_refused_at_submission(client, texture) -> None:
    res = client.post(texture["links"]["bakes"], files={"mesh": ("junk.obj", b"v 0 0\nf 1 2 9\n")},
                      data={"resolution": "64"})
    assert res.status_code == 422 and res.headers["content-type"] == "application/problem+json"
    assert res.json()["type"].endswith("invalid-mesh") and res.json()["detail"]
    assert client.get("/v1/jobs").json()["items"] == []


def test_list_jobs_filters(client, texture, monkeypatch) -> None:
    ok = submit_volume(client, texture)
    from service import job_kinds  # bad meshes are now refused at submission: fail a job in the worker

    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise InvalidParameter("made to fail")

    monkeypatch.setitem(job_kinds.KINDS, "volume", broken)
    submit_volume(client, texture, resolution=9)
    states = {j["id"]: j["state"] for j in client.get("/v1/jobs").json()["items"]}
    assert len(states) == 2 and states[ok["id"]] == "succeeded"
    failed = client.get("/v1/jobs", params={"state": "failed"}).json()["items"]
    assert [j["state"] for j in failed] == ["failed"]
    assert client.get("/v1/jobs", params={"texture_id": "other"}).json()["items"] == []
    assert client.get("/v1/jobs", params={"state": "sleeping"}).status_code == 422


def test_events_stream_ends_with_final_state(client, texture) -> None:
    job = submit_volume(client, texture)
    with client.stream("GET", f"/v1/jobs/{job['id']}/events") as res:
        assert res.headers["content-type"].startswith("text/event-stream")
        text = "".join(res.iter_text())
    assert "event: succeeded" in text
    data = json.loads(text.split("event: succeeded\ndata: ")[1].split("\n")[0])
    assert data["id"] == job["id"] and data["state"] == "succeeded"


def test_fit_without_torch_is_501(client, texture, monkeypatch) -> None:
    monkeypatch.setattr("service.routes.jobs.torch_available", lambda: False)
    res = client.post(texture["links"]["fit"], json={"seconds": 5})
    assert res.status_code == 501 and res.headers["content-type"] == "application/problem+json"
    assert "train" in res.json()["detail"]


# --- queued / running / leases: hold messages in an in-memory queue -------------------

@pytest.fixture
def held(settings):
    """(client, services) whose queue keeps messages until the test runs them."""
    settings.queue_backend = "memory"
    services = build_services(settings)
    with TestClient(create_app(services=services)) as client:
        yield client, services
    services.engine.dispose()


def run_next_message(services) -> None:
    task = services.huey.dequeue()
    assert task is not None
    services.huey.execute(task)


def upload(client, photo) -> dict:
    return client.post("/v1/textures", files={"image": ("b.png", photo)}).json()


def test_cancel_queued_job(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    assert job["state"] == "queued"
    res = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert res.status_code == 202 and res.json()["state"] == "canceled"
    run_next_message(services)  # the message is dropped: the row says canceled
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "canceled"
    assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 409


def test_cancel_running_job_is_seen_by_heartbeat(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    claim = jobs.claim(services, job["id"])
    assert claim is not None and claim.attempt == 1
    lease = Lease(services, claim)
    lease.beat()
    assert not lease.should_cancel()
    res = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert res.json()["state"] == "running" and res.json()["cancel_requested"]
    lease.beat()
    assert lease.should_cancel()


def test_running_job_canceled_between_slabs(held, photo, monkeypatch) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    client.post(f"/v1/jobs/{job['id']}/cancel")  # while queued: immediate
    assert run_job_attempt(services, job["id"]) is None
    job = submit_volume(client, upload(client, photo), seed=1)
    from service import job_kinds

    real = job_kinds.run_volume

    def cancel_then_run(services_, job_, workdir, progress, should_cancel):  # the user cancels mid-run
        client.post(f"/v1/jobs/{job_.id}/cancel")
        deadline = 50
        while not should_cancel() and deadline:  # the heartbeat thread notices within a beat
            import time
            time.sleep(0.05)
            deadline -= 1
        return real(services_, job_, workdir, progress, should_cancel)

    monkeypatch.setitem(job_kinds.KINDS, "volume", cancel_then_run)
    assert run_job_attempt(services, job["id"]) == "canceled"
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "canceled" and body["result"] is None


def test_reaper_requeues_expired_lease_then_fails(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    services.huey.flush()
    past = dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=5)
    for attempt in range(1, services.settings.max_attempts + 1):
        claim = jobs.claim(services, job["id"])  # a worker takes it ... and dies
        assert claim is not None and claim.attempt == attempt
        with services.sessions.begin() as session:
            session.execute(update(Job).where(Job.id == job["id"]).values(lease_expires_at=past))
        counts = jobs.reap(services)
        expect_failed = attempt == services.settings.max_attempts
        assert counts["failed" if expect_failed else "requeued"] == 1
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "failed" and "lease expired" in body["error"]["detail"]
    assert services.huey.pending_count() == services.settings.max_attempts - 1


def test_reaper_ends_a_canceled_job_whose_worker_died_as_canceled(held, photo) -> None:
    # The cancel ends it, whatever attempts are left: its error said "giving up after 3"
    # while its state was canceled.
    client, services = held
    job = submit_volume(client, upload(client, photo))
    services.huey.flush()
    assert jobs.claim(services, job["id"]).attempt == 1  # a worker takes it ...
    assert client.post(f"/v1/jobs/{job['id']}/cancel").json()["cancel_requested"]
    with services.sessions.begin() as session:  # ... and dies before it sees the cancel
        session.execute(update(Job).where(Job.id == job["id"]).values(
            lease_expires_at=dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=1)))
    jobs.reap(services)
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "canceled" and body["attempt"] == 1
    assert body["error"]["type"] == "urn:texspace:problem:canceled", body["error"]
    assert "canceled" in body["error"]["detail"] and "giving up" not in body["error"]["detail"]
    assert services.huey.pending_count() == 0


def test_requeued_job_runs_to_success(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    services.huey.flush()
    jobs.claim(services, job["id"])
    with services.sessions.begin() as session:
        session.execute(update(Job).where(Job.id == job["id"]).values(
            lease_expires_at=dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=1)))
    assert jobs.reap(services)["requeued"] == 1
    run_next_message(services)
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "succeeded" and body["attempt"] == 2


def test_metrics_report_jobs_and_queue(held, photo) -> None:
    client, services = held
    submit_volume(client, upload(client, photo))
    text = client.get("/metrics").text
    assert 'texspace_jobs{state="queued"} 1.0' in text
    assert "texspace_queue_depth 1.0" in text
    assert 'texspace_http_requests_total{method="POST",route="/v1/textures/{texture_id}/volumes",status="202"}' in text


def test_region_png_job(client, texture) -> None:
    res = client.post(texture["links"]["regions"], json={"z": 6, "x0": -40, "y0": 10, "width": 100, "height": 70})
    assert res.status_code == 202, res.text
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    from PIL import Image

    image = Image.open(io.BytesIO(client.get(job["links"]["result"]).content))
    assert image.size == (100, 70)
    too_big = client.post(texture["links"]["regions"], json={"z": 6, "x0": 0, "y0": 0, "width": 16384,
                                                              "height": 16384})
    assert too_big.status_code == 413


def test_region_gpu_textures_and_maps(client, texture) -> None:
    from PIL import Image

    from tests.worker.gpu_readers import read_ktx2

    rect = {"z": 6, "x0": -40, "y0": 10, "width": 100, "height": 70}
    submitted = client.post(texture["links"]["regions"], json={**rect, "format": "ktx2"})
    ktx = client.get(submitted.json()["links"]["self"]).json()
    assert ktx["state"] == "succeeded", ktx
    assert ktx["result"]["media_type"] == "image/ktx2" and ktx["result"]["filename"].endswith(".ktx2")
    header, levels = read_ktx2(client.get(ktx["links"]["result"]).content)
    assert (header["width"], header["height"], header["levels"]) == (100, 70, 7) and levels[-1].shape == (1, 1, 4)
    res = client.post(texture["links"]["regions"], json={**rect, "format": "dds",
                                                         "maps": ["height", "normal", "roughness", "ao"]})
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded", job
    assert job["result"]["media_type"] == "application/zip"
    low, high = job["result"]["height_range"]          # the luminance the 16-bit height map spans
    assert 0 <= low < high <= 1
    with zipfile.ZipFile(io.BytesIO(client.get(job["links"]["result"]).content)) as z:
        stem = "brick_region_z6_100x70px_seed0"
        assert job["result"]["filename"] == f"{stem}.zip"
        assert sorted(z.namelist()) == [f"{stem}_{name}" for name in ("ao.png", "basecolor.dds", "height.png",
                                                                       "normal.png", "roughness.png")]
        height = np.asarray(Image.open(io.BytesIO(z.read(f"{stem}_height.png"))))
        assert (height.min(), height.max()) == (0, 65535)
        normal = np.asarray(Image.open(io.BytesIO(z.read(f"{stem}_normal.png"))), dtype=np.float32) / 127.5 - 1
    assert normal.shape == (70, 100, 3) and np.abs(np.linalg.norm(normal, axis=-1) - 1).max() < 0.02
    for body in ({**rect, "format": "pyramid", "maps": ["height"]}, {**rect, "maps": ["gloss"]},
                 {**rect, "format": "ktx2", "width": 8192, "height": 4096}):
        assert client.post(texture["links"]["regions"], json=body).status_code == 422, body


def test_bc7_dds_region_and_bake(client, texture) -> None:
    """``dds_compression: bc7`` gives a DX10 BC7 DDS, for a region and a bake's texture; asked
    for without a DDS it is a 422 problem, before any job."""
    from tests.worker.gpu_readers import read_bc7_dds

    rect = {"z": 6, "x0": 0, "y0": 0, "width": 40, "height": 24}
    res = client.post(texture["links"]["regions"], json={**rect, "format": "dds", "dds_compression": "bc7"})
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded" and job["result"]["media_type"] == "image/vnd-ms.dds", job
    header, levels = read_bc7_dds(client.get(job["links"]["result"]).content)
    assert (header["dxgi_format"], header["width"], header["height"], len(levels)) == (99, 40, 24, 6)
    mesh = (MESHES / "cube.obj").read_bytes()
    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                      data={"resolution": "64", "format": "obj", "gpu_format": "dds", "dds_compression": "bc7"})
    job = client.get(res.json()["links"]["self"]).json()
    assert job["state"] == "succeeded" and job["params"]["dds_compression"] == "bc7", job
    with zipfile.ZipFile(io.BytesIO(client.get(job["links"]["result"]).content)) as z:
        dds = next(name for name in z.namelist() if name.endswith("_basecolor.dds"))
        assert read_bc7_dds(z.read(dds))[0]["dxgi_format"] == 99
    before = len(client.get("/v1/jobs").json()["items"])
    refused = [client.post(texture["links"]["regions"], json={**rect, "format": "png", "dds_compression": "bc7"}),
               client.post(texture["links"]["regions"], json={**rect, "format": "dds", "dds_compression": "bc5"}),
               client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                           data={"resolution": "64", "gpu_format": "ktx2", "dds_compression": "bc7"})]
    for res in refused:
        assert res.status_code == 422 and res.headers["content-type"].startswith("application/problem+json"), res.text
    assert "dds_compression" in refused[2].json()["detail"]
    assert len(client.get("/v1/jobs").json()["items"]) == before


def test_usdz_bake(client, texture, tmp_path) -> None:
    """``format: usdz`` gives a USDZ (its own media type and name) that USD opens with the
    material bound; with a height map it comes as a zip of the USDZ and the map."""
    from pxr import Usd, UsdShade

    mesh = (MESHES / "cube.obj").read_bytes()
    res = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                      data={"resolution": "64", "format": "usdz", "maps": ["normal", "roughness"]})
    job = client.get(res.json()["links"]["self"]).json()
    stem = "brick_cube_bake_64px_seed0"
    assert job["state"] == "succeeded", job
    assert job["result"]["media_type"] == "model/vnd.usdz+zip" and job["result"]["filename"] == f"{stem}.usdz"
    res = client.get(job["links"]["result"])
    assert res.headers["content-type"] == "model/vnd.usdz+zip"
    with zipfile.ZipFile(io.BytesIO(res.content)) as z:
        assert z.namelist()[0] == f"{stem}.usdc"
        assert sorted(z.namelist()[1:]) == [f"{stem}_basecolor.png", f"{stem}_normal.png", f"{stem}_roughness.png"]
    package = tmp_path / f"{stem}.usdz"
    package.write_bytes(res.content)
    stage = Usd.Stage.Open(str(package))
    mesh_prim = stage.GetPrimAtPath("/texspace/mesh")
    material, _ = UsdShade.MaterialBindingAPI(mesh_prim).ComputeBoundMaterial()
    assert material.GetPath() == "/texspace/material" and len(mesh_prim.GetAttribute("faceVertexCounts").Get()) == 12
    with_height = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", mesh)},
                              data={"resolution": "64", "format": "usdz", "maps": ["height"]})
    job = client.get(with_height.json()["links"]["self"]).json()
    assert job["result"]["media_type"] == "application/zip" and job["result"]["filename"] == f"{stem}.zip"
    with zipfile.ZipFile(io.BytesIO(client.get(job["links"]["result"]).content)) as z:
        assert sorted(z.namelist()) == [f"{stem}.usdz", f"{stem}_height.png"]


def test_worker_shutdown_hands_running_jobs_back(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    services.huey.flush()
    claim = jobs.claim(services, job["id"])
    assert jobs.release_worker(services) == [job["id"]]
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "queued" and body["worker_id"] is None
    assert not jobs.finish(services, claim, "succeeded")  # the old attempt cannot record a result
    assert body["attempt"] == 0  # handed back by a stopping worker: the attempt is not spent
    run_next_message(services)  # the stopping worker claims nothing; the message goes back
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "queued" and body["attempt"] == 0 and services.huey.pending_count() == 1
    services.stopping.clear()  # (another worker, in a process of its own)
    run_next_message(services)
    body = client.get(f"/v1/jobs/{job['id']}").json()
    assert body["state"] == "succeeded" and body["attempt"] == 1


def test_reaper_resends_lost_messages_only(held, photo) -> None:
    client, services = held
    job = submit_volume(client, upload(client, photo))
    old = dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=services.settings.requeue_after_seconds + 1)
    with services.sessions.begin() as session:
        session.execute(update(Job).where(Job.id == job["id"]).values(enqueued_at=old))
    assert jobs.reap(services)["resent"] == 0  # its message is still in the broker: just waiting
    services.huey.flush()  # the broker lost it (e.g. Redis restarted without persistence)
    with services.sessions.begin() as session:
        session.execute(update(Job).where(Job.id == job["id"]).values(enqueued_at=old))
    assert jobs.reap(services)["resent"] == 1
    run_next_message(services)
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "succeeded"
