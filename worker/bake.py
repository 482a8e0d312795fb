"""Bake the solid texture onto a mesh's UV atlas (GLB, OBJ+MTL+MaterialX+PNG or USDZ).

Steps, each reported through ``progress`` and preceded by a ``should_cancel`` check:

1. Check the file's header (``worker/mesh_size.py``: counts, a GLB's node tree), then load
   with trimesh (OBJ, PLY, STL, GLB/glTF binary; ``process=False`` so seam
   vertices stay split; an OBJ of plain ``v``/``f`` lines by ``read_plain_obj``, the same
   arrays faster) and validate: parse errors, no faces, non-finite vertices or
   coordinates beyond +-``MAX_COORDINATE``, out-of-range indices, all-degenerate faces -> InvalidMesh; face/vertex counts over
   the limits -> LimitExceeded. Degenerate (zero-area) faces are kept in the output
   but cover no texel. Vertex normals: the file's own (OBJ ``vn``, glTF ``NORMAL``) when
   it has them, else smooth area-weighted normals (``smooth_normals``).
2. UVs: the mesh's own are kept when present, finite, inside [0, 1], not degenerate (at
   most ``MAX_UV_DEGENERATE`` of the 3D area on faces with zero UV area) and not
   overlapping (at most ``MAX_UV_OVERLAP`` of the covered texels hit twice; mirrored or
   tiled UVs would give two surface points the same texel). Otherwise xatlas makes an
   atlas in a child process (``worker/atlas.py``), cached per mesh content when the
   caller gives ``atlas_cache_dir``.
3. Rasterise every triangle in UV space (``worker/raster.py``) to get the 3D surface
   point of each covered texel; evaluate the sampler at ``scale * point`` for those
   texels only (``projection="solid"``), or, with ``projection="triplanar"``, on the
   texture's own xy plane at three projections of the point, blended by the normal there
   (``worker/triplanar.py``).
4. Encode the covered texels to 8-bit sRGB (an exact table, ``raster.encode_srgb8``) and
   fill the gutter: uncovered texels within ``padding`` of a chart copy the nearest
   covered texel, so bilinear filtering and mipmaps near seams never read background.
5. Write atomically: GLB (written here: POSITION, NORMAL, TEXCOORD_0, PBR material, base
   colour factor 1, embedded 8-bit sRGB PNG), a zip of ``<stem>.obj`` (with ``vn``) +
   ``<stem>.mtl`` (``Kd 1 1 1``, ``map_Kd <stem>_basecolor.png``) + ``<stem>.mtlx`` (a
   MaterialX standard_surface naming the same files, ``worker/material_files.py``) +
   ``<stem>_basecolor.png``, or a USDZ (mesh, UVs, normals and a bound UsdPreviewSurface
   with its textures inside, ``worker/material_files.py``), ``<stem>`` being the result
   file's own stem (``worker.files.member_stem``), so two bakes extracted into one folder
   keep their files. With ``exr=True`` a linear half-float ``<stem>_basecolor.exr`` is
   added to the OBJ zip, or written next to a GLB or USDZ as ``<out_path>.exr``. ``maps`` (height,
   normal, roughness, ao) and ``gpu_format`` (dds, ktx2; a DDS in BC1 or, with ``dds_compression="bc7"``,
   BC7) add derived maps and a mipmapped texture of the atlas (``worker/bake_outputs.py``: a GLB embeds normal, roughness and AO in its material and a KTX2 as
   its base colour's KHR_texture_basisu source, and becomes a zip with a height map or a DDS).

Projection: a solid texture is one 3D material, the right thing for isotropic ones (stone,
gravel) and for grain (wood cut from one log). A texture fitted on a 2D repeat lattice
(bricks, tiles) is its photo's pattern drawn through z: a wall facing x shows stripes.
Triplanar projection (``worker/triplanar.py``) shows it on every face; the service picks it
for lattice fits (``projection="auto"``, service/schemas.py ``bake_projection``).

World scale: a mesh point p is textured with the solid texture at ``scale * p``
(``scale`` = world units per mesh unit). Default (``scale=None``): fit to bounds, the
mesh's longest bounding-box side spans ``DEFAULT_SPAN_PIXELS`` exemplar pixels, i.e.
``scale = DEFAULT_SPAN_PIXELS / pixels_per_unit / longest_side``. A texture whose photo's
real width is known bakes at real size instead (``physical_scale``): a teapot and a bunny
get as many features as their size in metres implies.
"""
from __future__ import annotations

import io
import json
import os
import struct
import time
import warnings
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from worker import atlas, raster
from worker.bake_outputs import add_bake_outputs, check_options, write_usdz_bake
from worker.contract import MIN_BAKE_RESOLUTION
from worker.derived_maps import DEFAULT_NORMAL_STRENGTH
from worker.errors import Canceled, InvalidMesh, InvalidParameter, LimitExceeded
from worker.files import OFFERED, ZIP_TIME, atomic_output, media_type, member_name, member_stem
from worker.images import png_bytes, write_image
from worker.material_files import materialx_document
from worker.mesh_size import check_mesh_size
from worker.photo import working_shape
from worker.runtime import Sampler
from worker.triplanar import PROJECTIONS, sample_triplanar

BAKE_FORMATS = OFFERED["bake"]  # (an obj bake is a zip; glb and usdz become one with extra files)
MESH_TYPES = {"obj": "obj", "ply": "ply", "stl": "stl", "glb": "glb"}
PARSED_MESH = "mesh.npz"  # a bake job's input as the API parsed it (``mesh_npz``)
MAX_UV_OVERLAP = 0.01
MAX_UV_DEGENERATE = 0.001  # share of 3D area allowed on faces whose UVs have no area
NORMAL_EPS = 1e-12         # a normal shorter than this (relative, for computed ones) is unusable
DEFAULT_SPAN_PIXELS = 512.0


def physical_scale(photo_width_px: int, photo_height_px: int, short_side: int, pixels_per_unit: float,
                   photo_width_m: float, mesh_unit_m: float) -> float:
    """World units per mesh unit that bake a photo ``photo_width_m`` metres wide at its real
    size on a mesh whose unit is ``mesh_unit_m`` metres (1 for metres, 0.01 for centimetres).
    The space reads the photo with its short side at ``short_side`` pixels
    (``worker.photo.working_shape``), ``pixels_per_unit`` of them per world unit, so its width
    spans ``working width / pixels_per_unit`` world units."""
    working_width = working_shape(photo_height_px, photo_width_px, short_side)[1]
    return working_width / pixels_per_unit / photo_width_m * mesh_unit_m
AREA_EPS = 1e-20           # squared-length scale below which a face counts as degenerate
# |coordinate| limit: beyond it xatlas (float32) spins for minutes and extent ** 4 overflows
MAX_COORDINATE = 1e9


@dataclass(frozen=True)
class BakeLimits:
    max_faces: int = 500_000
    max_vertices: int = 500_000
    max_nodes: int = 4096            # a GLB's nodes, and its mesh primitives (worker/mesh_size.py)
    max_depth: int = 64              # levels of a GLB's node tree
    max_resolution: int = 4096
    atlas_timeout: float = 120.0
    atlas_memory_bytes: int = 2 << 30


@dataclass
class BakeResult:
    path: Path
    exr_path: Path | None
    uv_source: str                  # "mesh", "xatlas" or "box" (worker/box_charts.py, when xatlas gives none)
    resolution: int
    scale: float
    covered: np.ndarray = field(repr=False)   # (R, R) bool: texels evaluated by the sampler
    faces: int = 0
    vertices: int = 0
    timings: dict = field(default_factory=dict)   # seconds per stage: load, atlas, raster, sample, gutter, write
    height_range: tuple[float, float] | None = None   # the height map's luminance (min, max), if one was made
    surface_area: float = 0.0        # the mesh's area in mesh units^2 (texel density: covered texels / area)


@dataclass
class Mesh:
    vertices: np.ndarray             # (V, 3) float64
    faces: np.ndarray                # (F, 3) int64
    uv: np.ndarray | None            # (V, 2) float64, v up
    normals: np.ndarray | None       # (V, 3) float64 unit vectors, the file's own; None if it has none


def mesh_npz(mesh: Mesh) -> bytes:
    """A parsed mesh as .npz bytes: what the API stores for the bake job, so the worker does
    not parse the uploaded file a second time (``mesh_from_npz``)."""
    buffer = io.BytesIO()
    arrays = {"vertices": mesh.vertices, "faces": mesh.faces}
    arrays |= {name: value for name, value in (("uv", mesh.uv), ("normals", mesh.normals)) if value is not None}
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def mesh_from_npz(data: bytes) -> Mesh:
    """The mesh ``mesh_npz`` stored (no pickles: plain float and int arrays)."""
    with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
        return Mesh(vertices=arrays["vertices"].astype(np.float64), faces=arrays["faces"].astype(np.int64),
                    uv=arrays["uv"].astype(np.float64) if "uv" in arrays else None,
                    normals=arrays["normals"].astype(np.float64) if "normals" in arrays else None)


def read_mesh(mesh_bytes: bytes, filename: str, limits: BakeLimits = BakeLimits()) -> Mesh:
    """Parse and validate a mesh (module docstring, step 1), keeping its own vertex
    normals (OBJ ``vn``, glTF ``NORMAL``, PLY ``nx ny nz``) when it has usable ones."""
    ext = Path(filename).suffix.lower().lstrip(".")
    if ext not in MESH_TYPES:
        raise InvalidMesh(f"unsupported mesh type {ext!r}; use one of {sorted(MESH_TYPES)}")
    if not mesh_bytes:
        raise InvalidMesh("empty mesh upload (0 bytes)")
    check_mesh_size(mesh_bytes, ext, limits)     # from the header, before any parse
    plain = read_plain_obj(mesh_bytes) if ext == "obj" else None
    if plain is not None:
        (vertices, faces), uv, normals = plain, None, None
    else:
        try:
            loaded = trimesh.load(io.BytesIO(mesh_bytes), file_type=MESH_TYPES[ext], process=False)
            mesh, normals = _as_mesh(loaded)
        except Exception as exc:  # trimesh raises many types on malformed files
            raise _unreadable(mesh_bytes, ext, f"cannot parse {ext.upper()} mesh: {exc}") from None
        if not isinstance(mesh, trimesh.Trimesh):
            raise InvalidMesh("file holds no triangle mesh")
        if ext == "obj" and _obj_names_vertex_zero(mesh_bytes):   # trimesh reads 0 as the last vertex
            raise _unreadable(mesh_bytes, ext, "an OBJ face names vertex 0; OBJ counts vertices from 1")
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
        uv = getattr(mesh.visual, "uv", None)
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
        raise _unreadable(mesh_bytes, ext, f"face indices out of range [0, {len(vertices)})")
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    extent = max(float(np.ptp(vertices, axis=0).max()), 1e-300)
    if not ((cross ** 2).sum(axis=1) > AREA_EPS * extent ** 4).any():
        raise InvalidMesh("every face is degenerate (zero area)")
    uv = None if uv is None or len(uv) != len(vertices) else np.asarray(uv, dtype=np.float64)
    return Mesh(vertices, faces, uv, _unit_normals(normals, len(vertices)))


def _obj_names_vertex_zero(data: bytes) -> bool:
    """Whether an OBJ face has a corner whose vertex number is 0 (OBJ counts from 1, or
    back from -1). trimesh loads it as the last vertex, which would bake a wrong triangle
    or call the mesh "degenerate". Vectorised: the lone zeros (a 0 after a blank and before
    a blank, a slash or the end) are found with numpy, and only their lines are read; a
    regex over a 23 MB file took 0.2-0.3 s."""
    text = np.frombuffer(data + b"\n", np.uint8)
    zeros = np.flatnonzero(text[1:-1] == ord("0")) + 1
    blank, ends = np.frombuffer(b" \t", np.uint8), np.frombuffer(b" \t/\r\n", np.uint8)
    lone = zeros[np.isin(text[zeros - 1], blank) & np.isin(text[zeros + 1], ends)]
    return any(data[data.rfind(b"\n", 0, at) + 1:at].lstrip()[:1] == b"f" for at in lone)


def _unreadable(mesh_bytes: bytes, ext: str, otherwise: str) -> InvalidMesh:
    """The error for a mesh that failed to load: an OBJ's bad face where it has one, else ``otherwise``."""
    problem = obj_face_problem(mesh_bytes) if ext == "obj" else None
    return InvalidMesh(f"bad OBJ mesh: {problem}" if problem else otherwise)


def obj_face_problem(data: bytes) -> str | None:
    """The first face of an OBJ that names a vertex the file does not have, said so that
    its author can find it ("face 2 (line 5) names vertex 9; the file has 3 vertices"), or
    None. Positive numbers count from the file's first vertex, negative ones back from the
    last vertex before the face (the OBJ convention). Only run on a mesh that failed to load:
    a line-by-line read."""
    lines = data.splitlines()
    keywords = [line.split(maxsplit=1)[:1] for line in lines]
    total = keywords.count([b"v"])
    seen = faces = 0
    for number, (line, keyword) in enumerate(zip(lines, keywords), 1):
        if keyword == [b"v"]:
            seen += 1
        elif keyword == [b"f"]:
            faces += 1
            for corner in line.split()[1:]:
                text = corner.split(b"/")[0].decode("ascii", "replace")
                try:
                    index = int(text)
                except ValueError:
                    return f"face {faces} (line {number}) has a corner {text!r} that is not a vertex number"
                if index == 0 or index > total or -index > seen:
                    have = (f"{seen} {_vertices(seen)} {'comes' if seen == 1 else 'come'} before it" if index < 0
                            else f"the file has {total} {_vertices(total)}")
                    return f"face {faces} (line {number}) names vertex {index}; {have}"
    return None


def _vertices(count: int) -> str:
    return "vertex" if count == 1 else "vertices"


_OBJ_HEADER_LINES = (b"#", b"\n", b"o ", b"g ", b"s ", b"mtllib ")  # lines before the first v that name, not shape


def read_plain_obj(data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (V, 3) float64, faces (F, 3) int64) of an OBJ that is only 'v x y z'
    lines followed by 'f a b c' lines (single spaces, positive indices, no slashes) after
    header lines (comments, object and group names), as scanners, trimesh and
    numpy.savetxt write a mesh without UVs; None for anything else, which
    trimesh reads. The same arrays as trimesh's loader (unreferenced vertices dropped,
    order kept) in a third of its time: 0.03 s instead of 0.09 s for the 100k-face bench
    mesh, whose bake is otherwise bound by the sampler.
    """
    header = 0
    while data.startswith(_OBJ_HEADER_LINES, header):   # comments, an object name, as most writers put first
        header = data.find(b"\n", header) + 1
        if header == 0:
            return None
    data = data[header:].rstrip(b"\n") + b"\n"   # blank lines at the end too
    split = data.find(b"\nf ") + 1
    if split == 0:
        return None
    vertex_lines, face_lines = data[:split], data[split:]
    nv = _count_lines_of_three(vertex_lines, b"v", b"0123456789.-+eE")
    nf = _count_lines_of_three(face_lines, b"f", b"0123456789")
    if nv is None or nf is None:
        return None
    with warnings.catch_warnings():   # fromstring warns where it stops early: caught by the sizes
        warnings.simplefilter("ignore")
        values = np.fromstring(vertex_lines.translate(None, b"v"), dtype=np.float64, sep=" ")
        indices = np.fromstring(face_lines.translate(None, b"f"), dtype=np.int64, sep=" ")
    if values.size != 3 * nv or indices.size != 3 * nf or indices.min() < 1 or indices.max() > nv:
        return None
    vertices, faces = values.reshape(nv, 3), indices.reshape(nf, 3) - 1
    used = np.zeros(nv, bool)
    used[faces] = True
    if not used.all():
        faces = (np.cumsum(used) - 1)[faces]
        vertices = vertices[used]
    return vertices, faces


def _count_lines_of_three(block: bytes, tag: bytes, allowed: bytes) -> int | None:
    """The number of lines of ``block`` if every one reads '<tag> a b c' (one space before
    each field, fields made of ``allowed``), else None. C-speed byte scans, no Python loop."""
    lines = block.count(b"\n")
    if (not block.startswith(tag + b" ") or block.count(b"\n" + tag + b" ") + 1 != lines
            or block.count(tag) != lines or block.translate(None, allowed + tag + b" \n")
            or b"  " in block or b" \n" in block):
        return None
    text = np.frombuffer(block, np.uint8)
    spaces_before = np.searchsorted(np.flatnonzero(text == 32), np.flatnonzero(text == 10))
    return lines if (np.diff(spaces_before, prepend=0) == 3).all() else None


def load_mesh(mesh_bytes: bytes, filename: str, limits: BakeLimits = BakeLimits()):
    """Parse and validate a mesh. Returns (vertices (V, 3) float64, faces (F, 3) int64,
    uv (V, 2) float64 or None)."""
    mesh = read_mesh(mesh_bytes, filename, limits)
    return mesh.vertices, mesh.faces, mesh.uv


def _as_mesh(loaded):
    """(one Trimesh, the file's own vertex normals (V, 3) or None). A scene is flattened
    as trimesh's ``to_mesh`` does (which drops normals), with each node's transform from
    ``_world_transforms``; normals are kept for a scene of one geometry, turned by its
    node's transform."""
    if isinstance(loaded, trimesh.Trimesh):
        return loaded, (loaded.vertex_normals if "vertex_normals" in loaded._cache else None)
    if not isinstance(loaded, trimesh.Scene):        # e.g. a point cloud: an empty mesh, "no faces"
        loaded = trimesh.Scene(loaded)
    world = _world_transforms(loaded.graph)
    placed = []
    for node in loaded.graph.nodes_geometry:
        geometry = loaded.geometry[loaded.graph.transforms.node_data[node]["geometry"]]
        if isinstance(geometry, trimesh.Trimesh):     # points and lines are dropped, as to_mesh does
            placed.append(geometry.copy().apply_transform(world[node]))
    mesh = trimesh.util.concatenate(placed)
    normals = None
    if len(loaded.graph.nodes_geometry) == 1:
        node = loaded.graph.nodes_geometry[0]
        geometry = loaded.geometry[loaded.graph.transforms.node_data[node]["geometry"]]
        if "vertex_normals" in geometry._cache and len(geometry.vertices) == len(mesh.vertices):
            linear = world[node][:3, :3]
            if abs(np.linalg.det(linear)) > 1e-300:
                normals = geometry.vertex_normals @ np.linalg.inv(linear)  # inverse transpose, row vectors
    return mesh, normals


def _world_transforms(graph) -> dict:
    """Each frame of a trimesh scene graph -> its (4, 4) float64 transform from the base
    frame: one product per edge, parents first. (trimesh's ``graph[node]`` multiplies each
    node's whole path anew, choosing the order by numpy's O(depth^3) chain search: 22
    minutes for a 5,000-node chain.) Raises ValueError for a node off the tree."""
    children: dict = {}
    for (parent, child), edge in graph.transforms.edge_data.items():
        children.setdefault(parent, []).append((child, edge.get("matrix")))
    world = {graph.base_frame: np.eye(4)}
    stack = [graph.base_frame]
    while stack:
        parent = stack.pop()
        for child, matrix in children.get(parent, ()):
            if child not in world:                  # a forest: one parent each
                world[child] = world[parent] if matrix is None else world[parent] @ np.asarray(matrix, np.float64)
                stack.append(child)
    missing = [node for node in graph.nodes_geometry if node not in world]
    if missing:
        raise ValueError(f"scene node {missing[0]!r} is not connected to the scene's root")
    return world


def _unit_normals(normals, count: int) -> np.ndarray | None:
    """The file's normals, unit length, or None when absent, misshapen or unusable."""
    if normals is None:
        return None
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != (count, 3) or not np.isfinite(normals).all():
        return None
    length = np.linalg.norm(normals, axis=1)
    if not (length >= NORMAL_EPS).any():
        return None
    bad = length < NORMAL_EPS                 # zero rows: filled from smooth normals by the bake
    length[bad] = 1.0
    normals = normals / length[:, None]
    normals[bad] = 0.0
    return normals


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """The mesh's own vertex normals, smooth ones (``smooth_normals``) where it has none."""
    normals = mesh.normals
    if normals is not None and normals.any(axis=1).all():
        return normals
    smooth = smooth_normals(mesh.vertices, mesh.faces)
    return smooth if normals is None else np.where(normals.any(axis=1)[:, None], normals, smooth)


def smooth_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals (V, 3) float64, unit length.

    vertices : (V, 3) float64, faces : (F, 3) int64. Vertices at the same position
    (split at UV seams) share one normal, so seams do not shade. A vertex with no face
    of non-zero area gets +z (glTF requires unit normals).
    """
    # Weld by the bytes of each position (+ 0.0 turns -0.0 into 0.0): one sort of 24-byte
    # items, 3x faster than np.unique(axis=0)'s field-by-field comparisons.
    rows = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64) + 0.0).view("V24").reshape(-1)
    _, weld = np.unique(rows, return_inverse=True)
    weld = weld.reshape(-1)
    tri = vertices[faces]
    face_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])   # length = 2 x area
    corners = weld[faces].reshape(-1)
    total = np.stack([np.bincount(corners, np.repeat(face_normal[:, k], 3), minlength=weld.max() + 1)
                      for k in range(3)], axis=1)[weld]
    length = np.linalg.norm(total, axis=1)
    bad = length <= NORMAL_EPS * np.maximum(length.max(), 1e-300)
    total[bad], length[bad] = (0.0, 0.0, 1.0), 1.0
    return total / length[:, None]


def uvs_usable(uv: np.ndarray | None, faces: np.ndarray, resolution: int,
               vertices: np.ndarray | None = None) -> bool:
    """True when the mesh's UVs can carry a solid texture (see module docstring)."""
    if uv is None or not np.isfinite(uv).all():
        return False
    if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        return False
    if vertices is not None and atlas.atlas_quality(vertices, faces, uv)["uv_degenerate_area"] > MAX_UV_DEGENERATE:
        return False
    texel, _ = raster.rasterise(uv[faces], min(resolution, 1024), barycentric=False)
    return len(texel) > 0 and raster.overlap_fraction(texel, min(resolution, 1024)) <= MAX_UV_OVERLAP


def face_normals(tri_xyz: np.ndarray) -> np.ndarray:
    """(F, 3, 3) triangle corners -> (F, 3) float64 unit normals (zero for degenerate faces)."""
    tri = np.asarray(tri_xyz, np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    return np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)


def bake_texture(sampler: Sampler, code, seed, tri_uv, tri_xyz, *, resolution, padding,
                 scale, progress=None, should_cancel=None, chunk: int = 1 << 18,
                 timings: dict | None = None, linear: bool = False, projection: str = "solid",
                 tri_normals=None):
    """The atlas as 8-bit sRGB (R, R, 3) uint8, its coverage mask (R, R) bool, and (with
    ``linear``) the linear float32 atlas (R, R, 3), else None.

    ``projection="triplanar"`` blends by the normal at each texel: interpolated from
    ``tri_normals`` (F, 3, 3), the file's own vertex normals, when given; else the face's
    (a cube without normals stays hard-edged, not blended across every face).

    Only covered texels are evaluated and encoded; the gutter (``padding`` texels around
    charts) copies encoded texels. ``timings`` (optional) receives the seconds of the
    raster, sample and gutter stages (the gutter's nearest-texel search and the sRGB encode
    run beside the sampler, inside ``sample``; ``gutter`` is what is left: the copies).
    """
    if projection not in PROJECTIONS:
        raise InvalidParameter(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    timings = {} if timings is None else timings
    clock = time.perf_counter()
    R = resolution
    # A helper thread takes what does not need the sampler off the main thread: each
    # face's affine map while the (single-threaded) raster runs, then the gutter's
    # nearest-texel search (it depends on coverage only), the next chunk's surface points
    # and the previous chunk's sRGB codes while the sampler works (its session.run releases
    # the GIL, as do numpy's loops). Beside the sampler's two threads it still takes CPU
    # about one for one (docs/PERFORMANCE.md), so each of those stages is kept cheap too.
    with ThreadPoolExecutor(1, thread_name_prefix="bake-helper") as helper:
        affine_job = helper.submit(raster.face_affine, tri_uv, tri_xyz, R)
        texels, face = raster.rasterise(tri_uv, R, barycentric=False)
        covered = np.zeros(R * R, dtype=bool)
        covered[texels] = True
        if np.count_nonzero(covered) != len(texels):   # texels on edges two triangles share: the last wins
            texels, pick = raster.last_hits(texels, R)
            face = face[pick]
            del pick
        covered = covered.reshape(R, R)
        affine = affine_job.result()
        affine *= scale
        # the normal at a texel, as an affine map of the texel like its point (unit length
        # not needed: triplanar_weights normalises); a face normal is the map's constant term
        normal_affine = None
        if projection == "triplanar" and tri_normals is not None:
            normal_affine = raster.face_affine(tri_uv, tri_normals, R)
        elif projection == "triplanar":
            normal_affine = np.zeros_like(affine)
            normal_affine[0] = face_normals(tri_xyz).T
        timings["raster"], clock = time.perf_counter() - clock, time.perf_counter()
        rgb = np.empty((len(texels), 3), dtype=np.float32)
        encoded = np.empty((len(texels), 3), dtype=np.uint8)
        starts = list(range(0, len(texels), chunk)) + [len(texels)]

        def points_of(i: int) -> np.ndarray:
            # Surface points chunk by chunk: 6 MB arrays instead of 60 MB ones; 2^18 points per
            # call (not 2^16) so the sampler's two threads wait for each other 4x less often.
            return raster.texel_points(texels[starts[i]:starts[i + 1]], face[starts[i]:starts[i + 1]], affine, R)

        def encode(i: int) -> None:
            encoded[starts[i]:starts[i + 1]] = raster.encode_srgb8(rgb[starts[i]:starts[i + 1]])

        # The helper's queue: chunk 1's points, then the gutter search (done while the
        # sampler works on chunks 0 and 1), then points and encodes as they come.
        next_points = helper.submit(points_of, 1) if len(starts) > 2 else None
        sources = helper.submit(raster.gutter_sources, covered, padding)
        encodes = []
        for i in range(len(starts) - 1):
            if should_cancel is not None and should_cancel():
                raise Canceled("bake job canceled")
            points = points_of(0) if i == 0 else next_points.result()
            if 0 < i and i + 2 < len(starts):
                next_points = helper.submit(points_of, i + 1)
            if normal_affine is None:
                rgb[starts[i]:starts[i + 1]] = sampler.sample(points, code, seed)
            else:
                normals = raster.texel_points(texels[starts[i]:starts[i + 1]], face[starts[i]:starts[i + 1]],
                                              normal_affine, R)
                rgb[starts[i]:starts[i + 1]] = sample_triplanar(sampler, points, normals, code, seed)
            encodes.append(helper.submit(encode, i))
            if progress is not None:
                progress(starts[i + 1] / len(texels))
        for job in encodes:
            job.result()
        dst, src = sources.result()
    timings["sample"], clock = time.perf_counter() - clock, time.perf_counter()
    srgb = np.zeros((R * R, 3), dtype=np.uint8)
    _scatter_texels(srgb, texels, encoded, dst, src)
    image = None
    if linear:
        image = np.zeros((R * R, 3), dtype=np.float32)
        _scatter_texels(image, texels, rgb, dst, src)
        image = image.reshape(R, R, 3)
    timings["gutter"] = time.perf_counter() - clock
    return srgb.reshape(R, R, 3), covered, image


def _scatter_texels(atlas: np.ndarray, texels: np.ndarray, values: np.ndarray,
                    dst: np.ndarray, src: np.ndarray) -> None:
    """atlas[texels] = values, then the gutter copies atlas[dst] = atlas[src]; atlas (N, 3).
    Each texel moved as one opaque item (a void view), half the time of (N, 3) rows."""
    item = f"V{atlas.itemsize * 3}"
    flat = atlas.view(item).reshape(-1)
    flat[texels] = np.ascontiguousarray(values).view(item).reshape(-1)
    flat[dst] = flat[src]


def bake_mesh(sampler: Sampler, code: np.ndarray, seed: int, *, mesh_bytes: bytes | None = None, filename: str,
              mesh: Mesh | None = None,
              resolution: int = 1024, scale: float | None = None, fmt: str = "glb",
              exr: bool = False, out_path: str | os.PathLike, padding: int = 8,
              pixels_per_unit: float | None = None, limits: BakeLimits = BakeLimits(),
              progress: Callable[[float], None] | None = None,
              should_cancel: Callable[[], bool] | None = None,
              atlas_cache_dir: str | os.PathLike | None = None,
              atlas_cache_bytes: int = atlas.DEFAULT_CACHE_BYTES,
              maps: tuple[str, ...] = (), gpu_format: str | None = None, dds_compression: str = "bc1",
              normal_strength: float = DEFAULT_NORMAL_STRENGTH, projection: str = "solid") -> BakeResult:
    """Bake the texture (code, seed) onto the uploaded mesh; see the module docstring.

    The mesh: ``mesh_bytes`` (the file, parsed here; ``filename``'s extension says its type),
    or ``mesh``, one ``read_mesh`` parsed already (``filename`` is then not read).
    ``atlas_cache_dir``: where xatlas results are kept per mesh content (``worker/atlas.py``);
    None runs xatlas every time.
    """
    if fmt not in BAKE_FORMATS:
        raise InvalidParameter(f"bake format must be one of {BAKE_FORMATS}, got {fmt!r}")
    if not MIN_BAKE_RESOLUTION <= resolution <= limits.max_resolution:
        raise LimitExceeded(f"texture resolution must be in [{MIN_BAKE_RESOLUTION}, {limits.max_resolution}]")
    if projection not in PROJECTIONS:
        raise InvalidParameter(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    check_options(maps, gpu_format, dds_compression)
    extras = bool(maps) or gpu_format is not None
    report = progress or (lambda _f: None)

    def step(fraction: float) -> None:
        if should_cancel is not None and should_cancel():
            raise Canceled("bake job canceled")
        report(fraction)

    timings: dict[str, float] = {"atlas": 0.0}
    clock = time.perf_counter()
    if mesh is None:  # (a mesh parsed already: the API's, from the job's input)
        mesh = read_mesh(mesh_bytes or b"", filename, limits)
    vertices, faces, uv = mesh.vertices, mesh.faces, mesh.uv
    step(0.05)
    timings["load"], clock = time.perf_counter() - clock, time.perf_counter()
    # Normals are needed only for writing: a thread computes them while xatlas's child or
    # the single-threaded raster leaves a core idle.
    with ThreadPoolExecutor(1, thread_name_prefix="bake-normals") as beside:
        normals_job = beside.submit(vertex_normals, mesh)
        uv_source, vmap = "mesh", None
        if not uvs_usable(uv, faces, resolution, vertices):
            vmap, faces, uv, uv_source = atlas.parametrize(
                vertices, faces, resolution=resolution, padding=max(1, padding // 2),
                timeout=limits.atlas_timeout, memory_bytes=limits.atlas_memory_bytes,
                should_cancel=should_cancel,
                cache_dir=atlas_cache_dir, cache_bytes=atlas_cache_bytes)
            vertices = vertices[vmap]
        timings["atlas"] = time.perf_counter() - clock
        step(0.3)
        # triplanar blends by the file's own normals when it has them all (its intended shading)
        own_normals = mesh.normals if mesh.normals is not None and mesh.normals.any(axis=1).all() else None
        own_normals = own_normals[vmap] if own_normals is not None and vmap is not None else own_normals
        if scale is None:
            ppu = pixels_per_unit or getattr(sampler, "pixels_per_unit", None)
            if ppu is None:
                raise InvalidParameter("scale or pixels_per_unit is required for a bare sampler session")
            scale = DEFAULT_SPAN_PIXELS / float(ppu) / max(float(np.ptp(vertices, axis=0).max()), 1e-12)
        srgb, covered, image = bake_texture(
            sampler, code, seed, uv[faces], vertices[faces], resolution=resolution, padding=padding,
            scale=scale, progress=lambda f: report(0.3 + 0.6 * f), should_cancel=should_cancel,
            timings=timings, linear=exr or extras, projection=projection,
            tri_normals=own_normals[faces] if own_normals is not None else None)
        step(0.9)
        clock = time.perf_counter()
        normals = normals_job.result()
    normals = normals if vmap is None else normals[vmap]
    timings["normals"], clock = time.perf_counter() - clock, time.perf_counter()   # the wait for them
    out_path = Path(out_path)
    exr_path = out_path.with_name(out_path.name + ".exr") if exr and fmt != "obj" else None
    png = png_bytes(srgb)
    exr_bytes = write_image(image, "exr") if exr else None
    if exr_path is not None:
        _atomic_write(exr_path, exr_bytes)
    height_range = None
    if fmt == "usdz":   # the material needs the maps: written whole, with them, in one go
        outputs = write_usdz_bake(out_path, vertices, faces, uv, normals, png, image if extras else None,
                                  maps=maps, gpu_format=gpu_format, dds_compression=dds_compression,
                                  strength=normal_strength, mask=covered)
        out_path, height_range = outputs.path, outputs.height_range
    elif fmt == "glb":
        _atomic_write(out_path, glb_bytes(vertices, faces, uv, normals, png))
    else:
        _atomic_write(out_path, _obj_zip_bytes(vertices, faces, uv, normals, png, exr_bytes, member_stem(out_path)))
    if extras and fmt != "usdz":
        outputs = add_bake_outputs(out_path, fmt, image, maps=maps, gpu_format=gpu_format,
                                   dds_compression=dds_compression, strength=normal_strength, mask=covered)
        out_path, height_range = outputs.path, outputs.height_range
    timings["write"] = time.perf_counter() - clock
    report(1.0)
    corners = vertices[faces]
    area = 0.5 * float(np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                                      axis=1).sum())
    return BakeResult(out_path, exr_path, uv_source, resolution, float(scale), covered,
                      len(faces), len(vertices), timings, height_range, area)


def glb_bytes(vertices, faces, uv, normals, png: bytes) -> bytes:
    """Binary glTF 2.0: one mesh (POSITION, NORMAL, TEXCOORD_0, uint32 indices), one PBR
    material (base colour factor 1, metallic 0, roughness 1) whose base colour texture is
    the embedded PNG. glTF's v points down the image: TEXCOORD_0 = (u, 1 - v)."""
    position = np.ascontiguousarray(vertices, dtype=np.float32)
    texcoord = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).astype(np.float32)
    arrays = [(position, 34962), (np.ascontiguousarray(normals, dtype=np.float32), 34962),
              (texcoord, 34962), (np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1), 34963)]
    views, blobs, offset = [], [], 0
    for data, target in arrays + [(np.frombuffer(png, np.uint8), None)]:
        raw = data.tobytes()
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        views.append(view)
        pad = -len(raw) % 4
        blobs += [raw, b"\0" * pad]
        offset += len(raw) + pad
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": len(position), "type": "VEC3",
         "min": position.min(axis=0).tolist(), "max": position.max(axis=0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": len(position), "type": "VEC3"},
        {"bufferView": 2, "componentType": 5126, "count": len(position), "type": "VEC2"},
        {"bufferView": 3, "componentType": 5125, "count": int(faces.size), "type": "SCALAR"},
    ]
    gltf = {
        "asset": {"version": "2.0", "generator": "texspace"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "texspace"}],
        "meshes": [{"name": "texspace", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0,
            "mode": 4}]}],
        "materials": [{"name": "texspace", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0}, "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": 4, "mimeType": media_type("png")}],
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": offset}],
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    body = b"".join(blobs)
    total = 12 + 8 + len(text) + 8 + len(body)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total), struct.pack("<I4s", len(text), b"JSON"), text,
                     struct.pack("<I4s", len(body), b"BIN\0"), body])


def _obj_zip_bytes(vertices, faces, uv, normals, png: bytes, exr: bytes | None, stem: str) -> bytes:
    """OBJ with one vt and one vn per v (same indices), an MTL with Kd 1 1 1, a MaterialX
    document of the base colour (``worker.material_files.materialx_document``; the maps
    rewrite it, ``worker/bake_outputs.py``) and the textures (stored: PNG and EXR are
    compressed already), every member named after ``stem``."""
    f = faces + 1
    obj, mtl_name, colour = (member_name(stem, "", ".obj"), member_name(stem, "", ".mtl"),
                             member_name(stem, "basecolor", ".png"))
    text = "".join([
        f"# texspace bake\nmtllib {mtl_name}\no {stem}\n",
        ("v %.9g %.9g %.9g\n" * len(vertices)) % tuple(vertices.ravel().tolist()),
        ("vt %.9g %.9g\n" * len(uv)) % tuple(uv.ravel().tolist()),
        ("vn %.6f %.6f %.6f\n" * len(normals)) % tuple(normals.ravel().tolist()),
        f"usemtl {stem}\n",
        ("f %d/%d/%d %d/%d/%d %d/%d/%d\n" * len(f)) % tuple(np.repeat(f, 3, axis=1).ravel().tolist()),
    ])
    mtl = f"newmtl {stem}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {colour}\n"
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        members = [(obj, text.encode(), zipfile.ZIP_DEFLATED), (mtl_name, mtl.encode(), zipfile.ZIP_DEFLATED),
                   (member_name(stem, "", ".mtlx"), materialx_document(stem).encode(), zipfile.ZIP_DEFLATED),
                   (colour, png, zipfile.ZIP_STORED)]
        members += [(member_name(stem, "basecolor", ".exr"), exr, zipfile.ZIP_STORED)] if exr else []
        for name, data, method in members:
            z.writestr(zipfile.ZipInfo(name, ZIP_TIME), data, compress_type=method)
    return buf.getvalue()


def _atomic_write(path: Path, data: bytes) -> None:
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
