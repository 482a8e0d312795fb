"""Write the hostile-file corpus next to this script (deterministic; re-run to refresh).

    .venv/bin/python tests/data/bad/make_corpus.py

Every file is small (a few KiB at most; the 16 x 1,000,000 strip, 57 kB). ``tests/reliability/test_bad_input.py`` says
what the service must answer for each one; the expectations live there, the bytes here.
"""
from __future__ import annotations

import io
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

HERE = Path(__file__).resolve().parent
SIDE = 48  # above the service's 16-pixel minimum, small enough to keep the corpus tiny


def texture_rgb(side: int = SIDE, seed: int = 0) -> np.ndarray:
    """(side, side, 3) uint8: a deterministic bumpy pattern (not flat, not noise)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:side, :side]
    base = 128 + 60 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    rgb = np.stack([base, base * 0.8, base * 0.6], axis=-1) + rng.normal(0, 8, (side, side, 3))
    return np.clip(rgb, 0, 255).astype(np.uint8)


def pil_bytes(image: Image.Image, fmt: str, **kwargs) -> bytes:
    buf = io.BytesIO()
    image.save(buf, fmt, **kwargs)
    return buf.getvalue()


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bomb(width: int = 60000, height: int = 60000) -> bytes:
    """A valid-looking PNG of a few dozen bytes whose header claims width x height RGB pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 64)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")


def float_exr() -> bytes:
    """A half-float linear EXR with values above 1 and one NaN (must still be accepted)."""
    import os
    import tempfile

    import OpenImageIO as oiio

    pixels = texture_rgb().astype(np.float32) / 64.0   # up to ~4.0: HDR
    pixels[0, 0, 0] = np.nan
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "f.exr")
        out = oiio.ImageOutput.create(path)
        spec = oiio.ImageSpec(SIDE, SIDE, 3, "half")
        spec.attribute("compression", "zip")
        out.open(path, spec)
        out.write_image(pixels)
        out.close()
        return Path(path).read_bytes()


def images() -> dict[str, bytes]:
    rgb = texture_rgb()
    png = pil_bytes(Image.fromarray(rgb), "PNG")
    jpeg = pil_bytes(Image.fromarray(rgb), "JPEG", quality=90)
    frames = [Image.fromarray(texture_rgb(seed=s)) for s in range(3)]
    grey16 = (rgb[:, :, 0].astype(np.uint16) * 257)
    return {
        "zero.png": b"",
        "truncated.png": png[: len(png) // 2],
        "garbage_after_header.jpg": jpeg[:20] + bytes(np.random.default_rng(1).integers(0, 256, 2000, np.uint8)),
        # a script behind a GIF signature (the GIFAR / JS-polyglot trick): not a decodable image
        "polyglot_gif_script.gif": b"GIF89a/*\x00\x00\x00\x00*/=1;alert(document.domain);//" + b"A" * 200,
        # a valid PNG with a zip archive appended: decodes as the PNG, the zip is ignored
        "polyglot_png_zip.png": png + _zip_bytes(),
        "png_named.jpg": png,                                   # wrong extension, right bytes
        "text_named.png": b"hello, I am plain text pretending to be a PNG\n" * 4,
        "grey16.png": pil_bytes(Image.fromarray(grey16), "PNG"),
        "float32.tif": pil_bytes(Image.fromarray(rgb[:, :, 1].astype(np.float32) / 255.0), "TIFF"),
        "half_hdr.exr": float_exr(),
        "one_pixel.png": pil_bytes(Image.new("RGB", (1, 1), (200, 10, 10)), "PNG"),
        "cmyk.jpg": pil_bytes(Image.fromarray(rgb).convert("CMYK"), "JPEG", quality=90),
        "animated.gif": pil_bytes(frames[0], "GIF", save_all=True, append_images=frames[1:], duration=100, loop=0),
        "animated.webp": pil_bytes(frames[0], "WEBP", save_all=True, append_images=frames[1:], duration=100,
                                   lossless=True),
        "bomb_60000x60000.png": png_bomb(),
        # under the pixel limit, but the upscale of the short side to the working size had
        # no bound: it tried to allocate 45.8 GiB; 16 x 16,000 cost 10-25 s and +800 MB
        "thin_16x1000000.png": thin_png(16, 1_000_000),
        "strip_16x16000.png": thin_png(16, 16_000),
    }


def thin_png(width: int, height: int) -> bytes:
    """A grey width x height PNG with some structure (every 7th row bright), compressed hard."""
    pixels = np.zeros((height, width), np.uint8)
    pixels[::7] = 200
    return pil_bytes(Image.fromarray(pixels, "L"), "PNG", compress_level=9)


def _zip_bytes() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(zipfile.ZipInfo("payload.txt", (2020, 1, 1, 0, 0, 0)), "not for you")
    return buf.getvalue()


def obj(vertices: list[tuple], faces: list[tuple]) -> bytes:
    lines = [f"v {' '.join(str(c) for c in v)}" for v in vertices]
    lines += [f"f {' '.join(str(i) for i in f)}" for f in faces]
    return ("\n".join(lines) + "\n").encode()


def grid_obj(n: int) -> bytes:
    """A flat n x n grid of quads split into 2 n^2 triangles (1-based OBJ indices)."""
    verts = [(x, y, 0) for y in range(n + 1) for x in range(n + 1)]
    faces = []
    for y in range(n):
        for x in range(n):
            a = y * (n + 1) + x + 1
            faces += [(a, a + 1, a + n + 2), (a, a + n + 2, a + n + 1)]
    return obj(verts, faces)


def meshes() -> dict[str, bytes]:
    quad = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    glb_header = b"glTF" + struct.pack("<II", 2, 10_000_000) + struct.pack("<I", 50) + b"JSON" + b"{\"asset\":"
    return {
        "nan_vertices.obj": obj([(0, 0, 0), ("nan", 0, 0), (0, 1, 0)], [(1, 2, 3)]),
        "out_of_range.obj": obj(quad, [(1, 2, 3), (1, 3, 99)]),
        "no_faces.obj": obj(quad, []),
        "one_face.obj": obj(quad[:3], [(1, 2, 3)]),
        # three triangles share the edge 1-2: not a manifold, still a usable surface
        "non_manifold.obj": obj(quad + [(0.5, -1, 0.5), (0.5, 0.5, 1)], [(1, 2, 3), (1, 2, 5), (2, 1, 6)]),
        "some_degenerate.obj": obj(quad + [(2, 2, 0)], [(1, 2, 3), (1, 3, 4), (1, 1, 2), (1, 3, 5)]),
        "all_degenerate.obj": obj([(0, 0, 0), (1, 1, 1), (2, 2, 2)], [(1, 2, 3), (1, 1, 2)]),
        "faces_over_limit.obj": grid_obj(24),            # 1152 faces; the test lowers the limit to 1000
        "junk.obj": bytes(np.random.default_rng(2).integers(0, 256, 4096, np.uint8)),
        "broken_header.glb": glb_header,
        # coordinates whose extent overflowed (1e100: a 500) or sent xatlas spinning for 120 s
        "huge_coordinates.obj": obj([(0, 0, 0), ("1e100", 0, 0), (0, "1e100", 0)], [(1, 2, 3)]),
        "far_coordinates.obj": obj([("1e30", 0, 0), ("1e60", 0, 0), (0, "1e45", 0), (0, 0, "1e30")],
                                   [(1, 2, 3), (1, 3, 4), (1, 2, 4), (2, 3, 4)]),
        "cube.obj": obj([(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)],
                        [(1, 3, 2), (2, 3, 4), (5, 6, 7), (6, 8, 7), (1, 2, 5), (2, 6, 5),
                         (3, 7, 4), (4, 7, 8), (1, 5, 3), (3, 5, 7), (2, 4, 6), (4, 8, 6)]),
    }


def main() -> None:
    for name, data in {**images(), **meshes()}.items():
        (HERE / name).write_bytes(data)
        print(f"{len(data):7d}  {name}")


if __name__ == "__main__":
    main()
