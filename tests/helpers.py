"""Plain helpers shared by several test folders (fixtures live in the conftests)."""
from __future__ import annotations

import contextlib
import io
import json
import os
import struct
import subprocess
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service import spawn
from worker.photo import working_shape

PG_ADMIN_URL = os.environ.get("TEXSPACE_TEST_PG_URL", "postgresql://postgres@127.0.0.1:5432/test")
REDIS_URL = os.environ.get("TEXSPACE_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")


@contextlib.contextmanager
def fresh_postgres_database(prefix: str = "texspace_test") -> Iterator[str]:
    """The URL of a new, empty database on the local PostgreSQL server, dropped on exit;
    a skip saying why when the server does not answer."""
    import psycopg  # a dependency: a missing one fails; only an absent server skips
    try:
        admin = psycopg.connect(PG_ADMIN_URL, autocommit=True, connect_timeout=3)
    except psycopg.Error as exc:
        pytest.skip(f"PostgreSQL unreachable at {PG_ADMIN_URL}: {exc}")
    name = f"{prefix}_{uuid.uuid4().hex[:10]}"
    admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield PG_ADMIN_URL.rsplit("/", 1)[0] + "/" + name
    finally:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.close()


def brick_png(size: int = 96, rgba: bool = False) -> bytes:
    """A real texture photo (scikit-image's CC0 brick wall), cropped small for speed."""
    from skimage import data

    grey = data.brick()[:size, :size]
    rgb = np.stack([grey, (grey * 0.8).astype(np.uint8), (grey * 0.6).astype(np.uint8)], axis=-1)
    if rgba:
        rgb = np.concatenate([rgb, np.full(grey.shape + (1,), 200, np.uint8)], axis=-1)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, "PNG")
    return buf.getvalue()


def shaded_png() -> bytes:
    """The brick photo under a light falling off to the right (0.4x at the far side)."""
    from worker.colour import linear_to_srgb8, srgb_to_linear

    rgb = np.asarray(Image.open(io.BytesIO(brick_png(128))).convert("RGB"), np.float32) / 255
    shade = np.linspace(1.0, 0.4, rgb.shape[1], dtype=np.float32)[None, :, None]
    buf = io.BytesIO()
    Image.fromarray(linear_to_srgb8(srgb_to_linear(rgb) * shade)).save(buf, "PNG")
    return buf.getvalue()


def wait_ready(base_url: str, procs: Iterable[subprocess.Popen], timeout: float, *,
               output: Callable[[], str] = lambda: "", name: str = "texspace", path: str = "/readyz") -> None:
    """``service.spawn.wait_ready``, failing the test (with the processes' logs) instead of raising."""
    try:
        spawn.wait_ready(base_url, procs, timeout, output=output, name=name, path=path)
    except spawn.NotReady as exc:
        pytest.fail(str(exc))


def pillow_lanczos(rgb8: np.ndarray, short_side: int) -> np.ndarray:
    """Pillow's 8-bit Lanczos resize to the working resolution, the resize the shipped space
    was trained through (the oracle ``worker.photo.resize_short_side`` is held to)."""
    rows, cols = working_shape(*rgb8.shape[:2], short_side)
    if (rows, cols) != rgb8.shape[:2]:
        rgb8 = np.asarray(Image.fromarray(rgb8).resize((cols, rows), Image.Resampling.LANCZOS))
    return rgb8.astype(np.float32) / 255


def export_mask_noise_sampler(path) -> None:
    """The shipped space exported with the noise of samplers made before 2026-11-26 (full
    lowbias32 cell hash, three masked 10-bit fields at their bin centres), for checks that
    such stored samplers keep their own shader. Needs the train extra (torch)."""
    import torch

    import model.noise as noise
    from model.export import export_sampler
    from model.networks import load_checkpoint
    from worker.shader import CHANNEL_BITS, CHANNEL_LOW_BIT, HALF_BIN, MASKS

    masks = torch.tensor(MASKS, dtype=torch.int32)
    # level / 1024 + half a bin, in the unscaled units noise_features multiplies by 2**-32
    scales = torch.tensor([2.0 ** (32 - b - CHANNEL_BITS) for b in CHANNEL_LOW_BIT])

    def mask_fields(h, axis=-1):
        h = h.unsqueeze(axis)
        shape = [1] * h.dim()
        shape[axis] = 3
        fields = torch.bitwise_and(h, masks.reshape(shape)).to(torch.float32)
        return fields * scales.reshape(shape) + HALF_BIN * 2.0**32

    model, _ = load_checkpoint(str(Path(__file__).resolve().parents[1] / "model" / "weights" / "space.pt"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(noise, "cell_mix", noise.mix32)
        patch.setattr(noise, "channel_fields", mask_fields)
        export_sampler(model.field, Path(path))


def glb_file(gltf: dict, binary: bytes = b"") -> bytes:
    """A GLB: the 12-byte header, the JSON chunk, then the binary chunk (each padded to 4 bytes)."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        body += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def tetrahedra_glb(nodes: list[dict], roots: list[int]) -> bytes:
    """A GLB whose one mesh is a tetrahedron (4 faces, 4 vertices), placed by ``nodes``
    (glTF node objects; ``{"mesh": 0}`` places it) under the scene's ``roots``."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint16)
    gltf = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": roots}], "nodes": nodes,
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "buffers": [{"byteLength": vertices.nbytes + faces.nbytes}],
            "bufferViews": [{"buffer": 0, "byteLength": vertices.nbytes},
                            {"buffer": 0, "byteOffset": vertices.nbytes, "byteLength": faces.nbytes}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 1]},
                          {"bufferView": 1, "componentType": 5123, "count": 12, "type": "SCALAR"}]}
    return glb_file(gltf, vertices.tobytes() + faces.tobytes())


def chained_glb(depth: int) -> bytes:
    """A chain of ``depth`` nodes, each a child of the one before, each placing a tetrahedron
    half a unit along x: a chain of 5,000 once held the API for 22 minutes."""
    nodes = [{"mesh": 0, "translation": [0.5, 0, 0], "children": [i + 1]} for i in range(depth)]
    del nodes[-1]["children"]
    return tetrahedra_glb(nodes, [0])


def instanced_glb(instances: int) -> bytes:
    """One root node with ``instances`` children, each placing the tetrahedron somewhere
    else: 100k of them once took 173 s and 850 MB to refuse."""
    nodes = [{"children": list(range(1, instances + 1))}]
    nodes += [{"mesh": 0, "translation": [i % 100, i // 100, 0]} for i in range(instances)]
    return tetrahedra_glb(nodes, [0])
