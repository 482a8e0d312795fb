"""Bake the solid texture onto a mesh's UV atlas (GLB or OBJ+MTL+PNG).

Steps, each reported through ``progress`` and preceded by a ``should_cancel`` check:

1. Load with trimesh (OBJ, PLY, STL, GLB/glTF binary; ``process=False`` so seam
   vertices stay split) and validate: parse errors, no faces, non-finite vertices or
   coordinates beyond +-``MAX_COORDINATE``, out-of-range indices, all-degenerate faces -> InvalidMesh; face/vertex counts over
   the limits -> LimitExceeded. Degenerate (zero-area) faces are kept in the output
   but cover no texel.
2. UVs: the mesh's own are kept when present, finite, inside [0, 1] and not
   overlapping (at most ``MAX_UV_OVERLAP`` of the covered texels hit twice; mirrored or
   tiled UVs would give two surface points the same texel). Otherwise xatlas makes an
   atlas in a child process (``worker/atlas.py``).
3. Rasterise every triangle in UV space (``worker/raster.py``) to get the 3D surface
   point of each covered texel; evaluate the sampler at ``scale * point`` for those
   texels only.
4. Fill the gutter: uncovered texels within ``padding`` of a chart copy the nearest
   covered texel, so bilinear filtering and mipmaps near seams never read background.
5. Write atomically: GLB (PBR material, base colour factor 1, embedded 8-bit sRGB PNG)
   or a zip of ``model.obj`` + ``model.mtl`` (``Kd 1 1 1``, ``map_Kd texture.png``) +
   ``texture.png``. With ``exr=True`` a linear half-float ``texture.exr`` is added to the
   OBJ zip, or written next to a GLB as ``<out_path>.exr``.

World scale: a mesh point p is textured with the solid texture at ``scale * p``
(``scale`` = world units per mesh unit). Default (``scale=None``): fit to bounds, the
mesh's longest bounding-box side spans ``DEFAULT_SPAN_PIXELS`` exemplar pixels, i.e.
``scale = DEFAULT_SPAN_PIXELS / pixels_per_unit / longest_side``.
"""
from __future__ import annotations

import io
import os
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from PIL import Image

from worker import atlas, raster
from worker.colour import linear_to_srgb8
from worker.errors import Canceled, InvalidMesh, InvalidParameter, LimitExceeded
from worker.files import atomic_output
from worker.images import write_image
from worker.runtime import Sampler

MESH_TYPES = {"obj": "obj", "ply": "ply", "stl": "stl", "glb": "glb"}
MAX_UV_OVERLAP = 0.01
DEFAULT_SPAN_PIXELS = 512.0
AREA_EPS = 1e-20           # squared-length scale below which a face counts as degenerate
# |coordinate| limit: beyond it xatlas (float32) spins for minutes and extent ** 4 overflows
MAX_COORDINATE = 1e9
_ZIP_TIME = (2020, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class BakeLimits:
    max_faces: int = 500_000
    max_vertices: int = 500_000
    max_resolution: int = 4096
    atlas_timeout: float = 120.0
    atlas_memory_bytes: int = 2 << 30


@dataclass
class BakeResult:
    path: Path
    exr_path: Path | None
    uv_source: str                  # "mesh" or "xatlas"
    resolution: int
    scale: float
    covered: np.ndarray = field(repr=False)   # (R, R) bool: texels evaluated by the sampler
    faces: int = 0
    vertices: int = 0
    timings: dict = field(default_factory=dict)   # seconds per stage: load, atlas, raster, sample, gutter, write


def load_mesh(mesh_bytes: bytes, filename: str, limits: BakeLimits = BakeLimits()):
    """Parse and validate a mesh. Returns (vertices (V, 3) float64, faces (F, 3) int64,
    uv (V, 2) float64 or None)."""
    ext = Path(filename).suffix.lower().lstrip(".")
    if ext not in MESH_TYPES:
        raise InvalidMesh(f"unsupported mesh type {ext!r}; use one of {sorted(MESH_TYPES)}")
    if not mesh_bytes:
        raise InvalidMesh("empty mesh upload (0 bytes)")
    try:
        mesh = trimesh.load(io.BytesIO(mesh_bytes), file_type=MESH_TYPES[ext], process=False,
                            force="mesh")
    except Exception as exc:  # trimesh raises many types on malformed files
        raise InvalidMesh(f"cannot parse {ext.upper()} mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise InvalidMesh("file holds no triangle mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0 or len(vertices) == 0:
        raise InvalidMesh("mesh has no faces")
    if len(faces) > limits.max_faces:
        raise LimitExceeded(f"mesh has {len(faces)} faces, limit is {limits.max_faces}")
    if len(vertices) > limits.max_vertices:
        raise LimitExceeded(f"mesh has {len(vertices)} vertices, limit is {limits.max_vertices}")
    if not np.isfinite(vertices).all():
        raise InvalidMesh("mesh has NaN or infinite vertex coordinates")
    if np.abs(vertices).max() > MAX_COORDINATE:
        raise InvalidMesh(f"mesh has vertex coordinates beyond +-{MAX_COORDINATE:g}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidMesh(f"face indices out of range [0, {len(vertices)})")
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    extent = max(float(np.ptp(vertices, axis=0).max()), 1e-300)
    if not ((cross ** 2).sum(axis=1) > AREA_EPS * extent ** 4).any():
        raise InvalidMesh("every face is degenerate (zero area)")
    uv = getattr(mesh.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(vertices) else np.asarray(uv, dtype=np.float64)
    return vertices, faces, uv


def uvs_usable(uv: np.ndarray | None, faces: np.ndarray, resolution: int) -> bool:
    """True when the mesh's UVs can carry a solid texture (see module docstring)."""
    if uv is None or not np.isfinite(uv).all():
        return False
    if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        return False
    texel, _, _ = raster.rasterise(uv[faces], min(resolution, 1024))
    return len(texel) > 0 and raster.overlap_fraction(texel, min(resolution, 1024)) <= MAX_UV_OVERLAP


def bake_texture(sampler: Sampler, code, seed, tri_uv, tri_xyz, *, resolution, padding,
                 scale, progress=None, should_cancel=None, chunk: int = 1 << 16,
                 timings: dict | None = None):
    """Linear RGB atlas (R, R, 3) float32 and its coverage mask (R, R) bool.

    Only covered texels are evaluated. ``timings`` (optional) receives the seconds of
    the raster, sample and gutter stages.
    """
    timings = {} if timings is None else timings
    clock = time.perf_counter()
    R = resolution
    texel, face, bary = raster.rasterise(tri_uv, R)
    texels, pick = raster.last_hits(texel, R)
    timings["raster"], clock = time.perf_counter() - clock, time.perf_counter()
    image = np.zeros((R * R, 3), dtype=np.float32)
    for start in range(0, len(texels), chunk):
        if should_cancel is not None and should_cancel():
            raise Canceled("bake job canceled")
        stop = min(start + chunk, len(texels))
        # Surface points chunk by chunk: cache-sized arrays instead of 60 MB ones.
        rows = pick[start:stop]
        points = raster.barycentric_points(face[rows], bary[rows], tri_xyz)
        points *= scale
        image[texels[start:stop]] = sampler.sample(points, code, seed)
        if progress is not None:
            progress(stop / len(texels))
    timings["sample"], clock = time.perf_counter() - clock, time.perf_counter()
    covered = np.zeros(R * R, dtype=bool)
    covered[texels] = True
    covered = covered.reshape(R, R)
    filled = raster.fill_gutter(image.reshape(R, R, 3), covered, padding)
    timings["gutter"] = time.perf_counter() - clock
    return filled, covered


def bake_mesh(sampler: Sampler, code: np.ndarray, seed: int, *, mesh_bytes: bytes, filename: str,
              resolution: int = 1024, scale: float | None = None, fmt: str = "glb",
              exr: bool = False, out_path: str | os.PathLike, padding: int = 8,
              pixels_per_unit: float | None = None, limits: BakeLimits = BakeLimits(),
              progress: Callable[[float], None] | None = None,
              should_cancel: Callable[[], bool] | None = None,
              atlas_crash_for_test: str | None = None) -> BakeResult:
    """Bake the texture (code, seed) onto the uploaded mesh; see the module docstring."""
    if fmt not in ("glb", "obj"):
        raise InvalidParameter(f"bake format must be 'glb' or 'obj', got {fmt!r}")
    if not 16 <= resolution <= limits.max_resolution:
        raise LimitExceeded(f"texture resolution must be in [16, {limits.max_resolution}]")
    report = progress or (lambda _f: None)

    def step(fraction: float) -> None:
        if should_cancel is not None and should_cancel():
            raise Canceled("bake job canceled")
        report(fraction)

    timings: dict[str, float] = {"atlas": 0.0}
    clock = time.perf_counter()
    vertices, faces, uv = load_mesh(mesh_bytes, filename, limits)
    step(0.05)
    timings["load"], clock = time.perf_counter() - clock, time.perf_counter()
    uv_source = "mesh"
    if not uvs_usable(uv, faces, resolution):
        vmap, faces, uv = atlas.parametrize(
            vertices, faces, resolution=resolution, padding=max(1, padding // 2),
            timeout=limits.atlas_timeout, memory_bytes=limits.atlas_memory_bytes,
            crash_for_test=atlas_crash_for_test, should_cancel=should_cancel)
        vertices, uv_source = vertices[vmap], "xatlas"
        timings["atlas"] = time.perf_counter() - clock
    step(0.3)
    clock = time.perf_counter()
    if scale is None:
        ppu = pixels_per_unit or getattr(sampler, "pixels_per_unit", None)
        if ppu is None:
            raise InvalidParameter("scale or pixels_per_unit is required for a bare sampler session")
        scale = DEFAULT_SPAN_PIXELS / float(ppu) / max(float(np.ptp(vertices, axis=0).max()), 1e-12)
    image, covered = bake_texture(
        sampler, code, seed, uv[faces], vertices[faces], resolution=resolution, padding=padding,
        scale=scale, progress=lambda f: report(0.3 + 0.6 * f), should_cancel=should_cancel,
        timings=timings)
    step(0.9)
    clock = time.perf_counter()
    out_path = Path(out_path)
    exr_path = out_path.with_name(out_path.name + ".exr") if exr and fmt == "glb" else None
    srgb = Image.fromarray(linear_to_srgb8(image), "RGB")
    exr_bytes = write_image(image, "exr") if exr else None
    if fmt == "glb":  # trimesh encodes the PNG itself: hand it the image, not PNG bytes (one encode, not two)
        payload = _glb_bytes(vertices, faces, uv, srgb)
    else:
        payload = _obj_zip_bytes(vertices, faces, uv, _png_bytes(srgb), exr_bytes)
    _atomic_write(out_path, payload)
    if exr_path is not None:
        _atomic_write(exr_path, exr_bytes)
    timings["write"] = time.perf_counter() - clock
    report(1.0)
    return BakeResult(out_path, exr_path, uv_source, resolution, float(scale), covered,
                      len(faces), len(vertices), timings)


# zlib level of baked PNGs. A 2048^2 bake: level 6 1.70 s / 4.48 MB, level 3 0.53 s /
# 5.12 MB, level 1 0.47 s / 5.25 MB (bench/); 14% more bytes for 1.2 s less per bake.
PNG_COMPRESS_LEVEL = 3


def _png_bytes(srgb: Image.Image) -> bytes:
    buf = io.BytesIO()
    srgb.save(buf, "PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _glb_bytes(vertices, faces, uv, srgb: Image.Image) -> bytes:
    # trimesh saves the image itself with no options; Pillow merges an image's own
    # ``encoderinfo`` into save() (Pillow >= 11), which is how the level reaches it.
    srgb.encoderinfo = {"compress_level": PNG_COMPRESS_LEVEL}
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=srgb, baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0, roughnessFactor=1.0, name="texspace")
    visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)
    return mesh.export(file_type="glb")


def _obj_zip_bytes(vertices, faces, uv, png: bytes, exr: bytes | None) -> bytes:
    """OBJ with one vt per v (same indices), an MTL with Kd 1 1 1, and the textures."""
    text = io.StringIO()
    text.write("# texspace bake\nmtllib model.mtl\no texspace\n")
    np.savetxt(text, vertices, fmt="v %.9g %.9g %.9g")
    np.savetxt(text, uv, fmt="vt %.9g %.9g")
    text.write("usemtl texspace\n")
    np.savetxt(text, np.repeat(faces + 1, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
    mtl = ("newmtl texspace\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd texture.png\n")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        members = [("model.obj", text.getvalue().encode()), ("model.mtl", mtl.encode()),
                   ("texture.png", png)] + ([("texture.exr", exr)] if exr else [])
        for name, data in members:
            z.writestr(zipfile.ZipInfo(name, _ZIP_TIME), data, compress_type=zipfile.ZIP_DEFLATED)
    return buf.getvalue()


def _atomic_write(path: Path, data: bytes) -> None:
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
