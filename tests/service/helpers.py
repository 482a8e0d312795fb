"""Plain helpers of the service tests (fixtures live in conftest.py)."""
from __future__ import annotations

from fastapi.testclient import TestClient


def upload_photo(client: TestClient, photo: bytes, **form: str) -> dict:
    """POST a PNG to /v1/textures (``form``: e.g. name=...); the 201 answer's texture."""
    res = client.post("/v1/textures", files={"image": ("brick.png", photo, "image/png")}, data=form)
    assert res.status_code == 201, res.text
    return res.json()


def tile_url(texture: dict, z: int, x: int, y: int, fmt: str = "png") -> str:
    """The API path of tile (z, x, y) of an uploaded texture."""
    return f"/v1/textures/{texture['id']}/tiles/{z}/{x}/{y}.{fmt}"
