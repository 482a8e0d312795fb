"""Texture endpoints through the real app (in-process, no servers)."""
from __future__ import annotations

import io

import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

from tests.helpers import brick_png, shaded_png
from tests.service.helpers import upload_photo

PROBLEM = "application/problem+json"


def test_upload_encodes_and_stores(client, texture, photo) -> None:
    assert len(texture["code"]) == 8 and all(np.isfinite(texture["code"]))
    assert texture["name"] == "brick" and texture["source"] == "upload"
    assert (texture["width"], texture["height"]) == (96, 96)
    models = client.get("/v1/models").json()
    assert texture["model_version"] == models["default"]
    got = client.get(f"/v1/textures/{texture['id']}").json()
    assert got["code"] == texture["code"]
    exemplar = client.get(texture["links"]["exemplar"])
    assert exemplar.status_code == 200 and exemplar.content == photo
    assert exemplar.headers["content-type"] == "image/png"


def test_upload_with_even_lighting_encodes_the_evened_photo(client, services) -> None:
    """lighting=even: the texture says so, its code and colour table are those of the photo
    with its shading divided out (as worker.encode.encode_texture makes them), and the
    photo kept is the one sent. as-is is the default."""
    from worker.encode import encode_texture
    from worker.images import read_image

    shaded = shaded_png()
    runtime = services.registry.get(services.settings.default_model_version)
    as_is, even = upload_photo(client, shaded), upload_photo(client, shaded, lighting="even")
    assert as_is["lighting"] == "as-is" and even["lighting"] == "even"
    code, colour = encode_texture(runtime, read_image(shaded, max_pixels=1 << 20), "even")
    np.testing.assert_allclose(even["code"], code, atol=1e-6)
    np.testing.assert_allclose(even["colour"], colour, atol=1e-6)
    assert not np.allclose(even["colour"], as_is["colour"], atol=1e-3)
    assert client.get(even["links"]["exemplar"]).content == shaded
    assert client.get(f"/v1/textures/{even['id']}").json()["lighting"] == "even"


def test_upload_with_unknown_lighting_is_a_422_problem(client, photo) -> None:
    res = client.post("/v1/textures", files={"image": ("brick.png", photo, "image/png")}, data={"lighting": "flat"})
    assert res.status_code == 422 and res.headers["content-type"] == PROBLEM
    assert "lighting" in res.json()["detail"] and "'as-is' or 'even'" in res.json()["detail"]
    assert client.get("/v1/textures").json()["items"] == []  # nothing stored


def test_upload_location_header(client, photo) -> None:
    res = client.post("/v1/textures", files={"image": ("x.png", photo)})
    assert res.status_code == 201
    assert res.headers["location"] == f"/v1/textures/{res.json()['id']}"


def test_same_image_same_code_rgba_and_16bit_accepted(client, photo) -> None:
    a = client.post("/v1/textures", files={"image": ("a.png", photo)}).json()
    b = client.post("/v1/textures", files={"image": ("b.png", photo)}).json()
    assert a["code"] == b["code"] and a["id"] != b["id"]
    rgba = client.post("/v1/textures", files={"image": ("c.png", brick_png(rgba=True))})
    assert rgba.status_code == 201
    sixteen = np.asarray(Image.open(io.BytesIO(photo)), np.uint16) * 257
    out = oiio.ImageOutput.create("x.tif")
    path = str(client.app.state.services.work_dir / "x16.tif")
    out.open(path, oiio.ImageSpec(96, 96, 3, "uint16"))
    out.write_image(sixteen)
    out.close()
    with open(path, "rb") as f:
        res = client.post("/v1/textures", files={"image": ("x16.tif", f.read())})
    assert res.status_code == 201, res.text
    assert np.allclose(res.json()["code"], a["code"], atol=1e-3)


def test_bad_images_are_problems(client) -> None:
    res = client.post("/v1/textures", files={"image": ("x.png", b"not an image at all")})
    assert res.status_code == 422 and res.headers["content-type"] == PROBLEM
    assert res.json()["type"].endswith("invalid-image") and "format" in res.json()["detail"]
    truncated = brick_png()[:200]
    res = client.post("/v1/textures", files={"image": ("t.png", truncated)})
    assert res.status_code == 422 and res.headers["content-type"] == PROBLEM
    res = client.post("/v1/textures", data={"name": "no file"})
    assert res.status_code == 422 and res.json()["type"].endswith("validation-error")


def test_upload_limit(client, services, photo) -> None:
    services.settings.max_upload_bytes = len(photo) - 1
    res = client.post("/v1/textures", files={"image": ("x.png", photo)})
    assert res.status_code == 413 and res.headers["content-type"] == PROBLEM


def test_list_pagination(client, photo) -> None:
    ids = [client.post("/v1/textures", files={"image": (f"{i}.png", photo)}).json()["id"] for i in range(5)]
    seen, cursor = [], None
    while True:
        res = client.get("/v1/textures", params={"limit": 2, **({"cursor": cursor} if cursor else {})}).json()
        seen += [t["id"] for t in res["items"]]
        cursor = res["next_cursor"]
        if not cursor:
            break
    assert seen == ids[::-1]  # newest first, each exactly once
    assert client.get("/v1/textures", params={"cursor": "@@bad"}).status_code == 422


def test_patch_and_delete(client, texture, services) -> None:
    url = texture["links"]["self"]
    res = client.patch(url, json={"name": "renamed"})
    assert res.status_code == 200 and res.json()["name"] == "renamed"
    assert res.json()["code"] == texture["code"]
    assert client.patch(url, json={"code": [0] * 8}).status_code == 422
    assert client.delete(url).status_code == 204
    assert not services.storage.exists(f"textures/{texture['id']}/exemplar.png")
    res = client.get(url)
    assert res.status_code == 404 and res.headers["content-type"] == PROBLEM
    assert texture["id"] in res.json()["detail"]


def test_interpolate(client, texture, photo) -> None:
    other = client.post("/v1/textures", files={"image": ("o.png", brick_png(size=64))}).json()
    res = client.post("/v1/textures/interpolate", json={"a": texture["id"], "b": other["id"], "t": 0.25})
    assert res.status_code == 201, res.text
    blend = res.json()
    expected = 0.75 * np.array(texture["code"]) + 0.25 * np.array(other["code"])
    assert np.allclose(blend["code"], expected, atol=1e-6)
    assert blend["source"] == "interpolate" and blend["links"]["exemplar"] is None
    assert client.get(f"/v1/textures/{blend['id']}/exemplar").status_code == 404
    assert client.get(f"/v1/textures/{blend['id']}/tiles/6/0/0.png?size=64").status_code == 200
    bad = client.post("/v1/textures/interpolate", json={"a": texture["id"], "b": other["id"], "t": 1.5})
    assert bad.status_code == 422
    missing = client.post("/v1/textures/interpolate", json={"a": texture["id"], "b": "nope", "t": 0.5})
    assert missing.status_code == 404


def test_request_id_echoed(client) -> None:
    res = client.get("/healthz", headers={"X-Request-ID": "abc-123"})
    assert res.headers["x-request-id"] == "abc-123"
    generated = client.get("/healthz").headers["x-request-id"]
    assert len(generated) == 32
    hostile = client.get("/healthz", headers={"X-Request-ID": "a b\tc"}).headers["x-request-id"]
    assert hostile != "a b\tc"


def test_web_page_and_wrong_methods(client) -> None:
    page = client.get("/")
    assert page.status_code == 200 and "<html" in page.text.lower()
    res = client.request("OPTIONS", "/v1/textures")
    assert res.status_code == 405 and res.headers["content-type"] == PROBLEM
    assert set(res.headers["allow"].split(", ")) >= {"GET", "POST"}
    res = client.put("/v1/jobs/abc/cancel")
    assert res.status_code == 405 and res.headers["allow"] == "POST"
    missing = client.get("/v1/nothing-here")
    assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM


def _encoded(fmt: str, pixels: np.ndarray, tmp_path) -> bytes:
    path = str(tmp_path / f"upload.{fmt}")
    if fmt in ("exr",):
        out = oiio.ImageOutput.create(path)
        out.open(path, oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], "half"))
        out.write_image(pixels.astype(np.float32))
        out.close()
    else:
        Image.fromarray(pixels).save(path)
    with open(path, "rb") as f:
        return f.read()


@pytest.mark.parametrize("fmt,kind", [("jpg", "rgb8"), ("webp", "rgb8"), ("png", "grey8"),
                                      ("exr", "float"), ("tif", "rgb8")])
def test_upload_formats(client, fmt, kind, tmp_path) -> None:
    grey = np.asarray(Image.open(io.BytesIO(brick_png(80))).convert("L"))
    pixels = {"rgb8": np.stack([grey] * 3, -1), "grey8": grey,
              "float": np.stack([grey] * 3, -1).astype(np.float32) / 255.0}[kind]
    res = client.post("/v1/textures", files={"image": (f"x.{fmt}", _encoded(fmt, pixels, tmp_path))})
    assert res.status_code == 201, res.text
    body = res.json()
    assert (body["width"], body["height"]) == (80, 80) and np.isfinite(body["code"]).all()
    assert client.get(body["links"]["exemplar"]).headers["content-type"].startswith("image/")


def test_request_body_limit_while_streaming(client, services, photo) -> None:
    """The body limit is enforced as bytes arrive, for any route (chunked: no Content-Length)."""
    limit = services.settings.max_upload_bytes = services.settings.max_mesh_bytes = 4096
    from fastapi.testclient import TestClient  # the app reads the limit when built: build a new one

    from service.main import create_app

    with TestClient(create_app(services=services)) as small:
        big = b"x" * (limit + (2 << 20))
        res = small.post("/v1/textures", files={"image": ("big.png", big)})
        assert res.status_code == 413 and res.json()["type"].endswith("limit-exceeded")

        def chunks():
            for _ in range(40):
                yield b"y" * (128 << 10)

        res = small.post("/v1/textures/interpolate", content=chunks(), headers={"Content-Type": "application/json"})
        assert res.status_code == 413 and res.headers["content-type"] == PROBLEM


def test_shader_routes(client, texture):
    """GET /v1/textures/{id}/shader.glsl|.wgsl: the function, an ETag, 304 on revalidation."""
    name = f"texspace_{texture['id']}"
    glsl = client.get(f"/v1/textures/{texture['id']}/shader.glsl")
    assert glsl.status_code == 200 and glsl.headers["content-type"].startswith("text/x-glsl")
    assert f"vec3 {name}(vec3 p, uint seed)" in glsl.text
    wgsl = client.get(f"/v1/textures/{texture['id']}/shader.wgsl")
    assert wgsl.status_code == 200 and f"fn {name}(p: vec3<f32>, seed: u32) -> vec3<f32>" in wgsl.text
    again = client.get(f"/v1/textures/{texture['id']}/shader.glsl", headers={"If-None-Match": glsl.headers["etag"]})
    assert again.status_code == 304
    assert client.get(f"/v1/textures/{texture['id']}/shader.hlsl").status_code == 422
    assert client.get("/v1/textures/nope/shader.glsl").status_code == 404
