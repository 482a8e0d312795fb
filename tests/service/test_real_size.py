"""Bakes at real size: a texture whose photo's width in metres is known (upload or PATCH)
is baked onto a mesh in metres (``unit_m``) at that size, so a bigger mesh gets more of
the texture's features, not the same ones stretched."""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
import trimesh
from PIL import Image

from worker.bake import physical_scale


def cube_obj(side: float) -> bytes:
    """A cube ``side`` mesh units wide, with UVs of its own (no atlas to wait for)."""
    box = trimesh.creation.box(extents=(side, side, side))
    faces = np.asarray(box.faces)
    uv = np.zeros((len(faces) * 3, 2))
    corners = np.array([[0.05, 0.05], [0.45, 0.05], [0.05, 0.45]])
    for k in range(len(faces)):  # each face its own small triangle on a grid, none overlapping
        cell = np.array([k % 4, k // 4]) / 4.0
        uv[3 * k:3 * k + 3] = cell + corners / 4.0
    out = io.StringIO()
    for v in box.vertices:
        out.write(f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}\n")
    for t in uv:
        out.write(f"vt {t[0]:.6f} {t[1]:.6f}\n")
    for k, f in enumerate(faces):
        out.write("f " + " ".join(f"{f[i] + 1}/{3 * k + i + 1}" for i in range(3)) + "\n")
    return out.getvalue().encode()


def test_physical_scale_is_world_units_of_the_photo_per_metre_times_the_unit():
    # a 1024 x 768 photo read at short side 256: 341 px wide (worker.photo.working_shape), 128 px
    # per world unit = 2.66 units; 2 m wide: 1.33 world units per metre; a mesh in centimetres:
    # 0.0133 per mesh unit
    assert physical_scale(1024, 768, 256, 128.0, 2.0, 0.01) == pytest.approx(341 / 128 / 2 * 0.01)
    assert physical_scale(1024, 768, 256, 128.0, 2.0, 1.0) == pytest.approx(
        100 * physical_scale(1024, 768, 256, 128.0, 2.0, 0.01))


def test_width_m_is_kept_from_the_upload_and_set_by_patch(client, photo):
    texture = client.post("/v1/textures", files={"image": ("b.png", photo, "image/png")}, data={"width_m": "1.5"}).json()
    assert texture["width_m"] == 1.5
    patched = client.patch(f"/v1/textures/{texture['id']}", json={"width_m": 0.6}).json()
    assert patched["width_m"] == 0.6 and patched["name"] == texture["name"]
    renamed = client.patch(f"/v1/textures/{texture['id']}", json={"name": "oak"}).json()
    assert renamed["width_m"] == 0.6 and renamed["name"] == "oak"
    for bad in ({}, {"width_m": 0}, {"width_m": -1}, {"name": None}):
        res = client.patch(f"/v1/textures/{texture['id']}", json=bad)
        assert res.status_code == 422 and res.headers["content-type"] == "application/problem+json", bad


def test_a_bake_at_real_size_needs_the_photos_width_and_not_a_scale(client, texture):
    mesh = {"mesh": ("cube.obj", cube_obj(1.0))}
    res = client.post(texture["links"]["bakes"], files=mesh, data={"resolution": "64", "unit_m": "1"})
    assert res.status_code == 422 and "width_m" in res.json()["detail"]
    client.patch(f"/v1/textures/{texture['id']}", json={"width_m": 0.5})
    res = client.post(texture["links"]["bakes"], files=mesh, data={"resolution": "64", "unit_m": "1", "scale": "2"})
    assert res.status_code == 422 and "not both" in res.json()["detail"]


def baked(client, texture: dict, side: float, unit_m: str | None) -> tuple[dict, np.ndarray]:
    """(the job's result, the base colour atlas as float) of an OBJ bake of a cube ``side`` units wide."""
    data = {"resolution": "128", "format": "obj"} | ({"unit_m": unit_m} if unit_m else {})
    job = client.post(texture["links"]["bakes"], files={"mesh": ("cube.obj", cube_obj(side))}, data=data).json()
    done = client.get(job["links"]["self"]).json()
    assert done["state"] == "succeeded", done
    with zipfile.ZipFile(io.BytesIO(client.get(done["links"]["result"]).content)) as z:
        name = next(n for n in z.namelist() if n.endswith(".png"))
        atlas = np.asarray(Image.open(io.BytesIO(z.read(name))).convert("L"), np.float64)
    return done["result"], atlas


def test_a_hundred_times_bigger_mesh_gets_a_hundred_times_the_features(client, texture, services):
    # by default a texture is fitted to the mesh's bounds: a cube 100x bigger, a 100x smaller
    # scale. (100x, not 10x: the brick's texture has detail down to a few exemplar pixels, so a
    # 0.2-m cube's magnified texels differ nearly as much as a 2-m cube's; at 0.02 m they blur.)
    fitted_small, fitted_big = baked(client, texture, 0.02, None)[0], baked(client, texture, 2.0, None)[0]
    assert fitted_small["scale"] == pytest.approx(100 * fitted_big["scale"]) and fitted_small["texels_per_metre"] is None
    client.patch(f"/v1/textures/{texture['id']}", json={"width_m": 0.5})
    (small_result, small), (big_result, big) = baked(client, texture, 0.02, "1"), baked(client, texture, 2.0, "1")
    runtime = services.registry.get(None)
    real = physical_scale(texture["width"], texture["height"], runtime.short_side, runtime.pixels_per_unit, 0.5, 1.0)
    assert small_result["scale"] == pytest.approx(real) and big_result["scale"] == pytest.approx(real)
    assert small_result["texels_per_metre"] == pytest.approx(100 * big_result["texels_per_metre"], rel=1e-3)

    def detail(atlas: np.ndarray) -> float:  # mean step between neighbouring texels on the faces
        both = (atlas[:, 1:] > 0) & (atlas[:, :-1] > 0)
        return float(np.abs(np.diff(atlas, axis=1))[both].mean())
    assert detail(big) > 2 * detail(small)  # the same texels hold a hundred times the texture's width
    # a mesh in centimetres 2 units wide is the same bake as one in metres 0.02 units wide
    cm_result, cm = baked(client, texture, 2.0, "0.01")
    assert cm_result["texels_per_metre"] == pytest.approx(small_result["texels_per_metre"])
    assert np.array_equal(cm, small)
