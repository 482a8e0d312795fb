"""What loading a mesh file will cost, read from its header before anything is decoded.

``check_mesh_size(data, ext, limits)`` is the first step of ``worker.bake.read_mesh``, so
it runs at the API's submission check and again in the bake job, before trimesh parses a
byte. It refuses (``LimitExceeded``, or ``InvalidMesh`` for a malformed header) in
milliseconds what would otherwise hold a thread for minutes or take gigabytes:

* GLB: the JSON chunk alone is read (no buffer is decoded). Nodes, mesh primitives, the
  node tree's depth and the faces and vertices the scene places (each node reachable from
  the scene adds its mesh's primitives, counted from the accessors' ``count``) are held to
  the limits; a node reached twice (a cycle, or two parents: glTF nodes form trees) is
  malformed. A chain of 5,000 nodes of 164 KB once took trimesh 22 minutes to flatten
  (its transform products grow with the cube of the depth, per node); 100k instances
  of one mesh 173 s and 850 MB.
* OBJ: ``f`` and ``v`` lines counted by byte scans (a face line is at least one triangle).
* PLY: the header's ``element vertex`` / ``element face`` counts.
* STL: the binary header's triangle count (three vertices each: nothing is merged), or an
  ASCII file's ``endfacet`` lines.

Peak memory is the JSON chunk's objects, bounded by ``MAX_GLTF_JSON_BYTES`` and
``MAX_GLTF_JSON_CONTAINERS``; the other formats allocate next to nothing. Scenes within
the limits are flattened in linear time (``worker.bake._world_transforms``).
"""
from __future__ import annotations

import json
import re
import struct
from typing import Any

from worker.errors import InvalidMesh, LimitExceeded

#: a GLB's JSON chunk larger than this is refused before it is parsed (4,096 nodes with
#: names and matrices and 4,096 primitives' accessors take ~2 MB; buffers live in the
#: binary chunk). Parsed, 4 MB of the costliest JSON (short strings) peaks at ~55 MB.
MAX_GLTF_JSON_BYTES = 4 << 20
#: arrays and objects (counted as ``[`` and ``{`` bytes) a GLB's JSON may hold: each costs
#: 60-250 bytes parsed for its 2-3 bytes of text
MAX_GLTF_JSON_CONTAINERS = 1 << 18
#: glTF primitive modes trimesh reads as triangles: TRIANGLES (faces = n / 3) and
#: TRIANGLE_STRIP (n - 2); points, lines and fans give no faces
_TRIANGLES, _TRIANGLE_STRIP = 4, 5


def check_mesh_size(data: bytes, ext: str, limits) -> None:  # noqa: ANN001 (worker.bake.BakeLimits)
    """Raise LimitExceeded when the file's header says the mesh is over ``limits``
    (``max_faces``, ``max_vertices``, ``max_nodes``, ``max_depth``), InvalidMesh when a GLB's
    header is malformed. ``ext``: ``obj``, ``ply``, ``stl`` or ``glb``. Says nothing about
    files whose header is fine: the parse that follows validates the rest."""
    if ext == "glb":
        _check_gltf(_glb_json(data), limits)
    elif ext == "obj":
        _check_obj(data, limits)
    elif ext == "ply":
        _check_ply(data, limits)
    elif ext == "stl":
        _check_stl(data, limits)


def _over(what: str, count: int, limit: int) -> None:
    if count > limit:
        raise LimitExceeded(f"{what.format(count=count)}, limit is {limit}")


# --- GLB ------------------------------------------------------------------------------------

def _glb_json(data: bytes) -> dict:
    """The parsed JSON chunk of a GLB (header: magic, version, length; then the chunk)."""
    if len(data) < 20:
        raise InvalidMesh(f"cannot parse GLB mesh: {len(data)} bytes, too few for a GLB header and its JSON chunk")
    magic, version, _ = struct.unpack_from("<4sII", data)
    chunk_length, chunk_type = struct.unpack_from("<I4s", data, 12)
    if magic != b"glTF":
        raise InvalidMesh("cannot parse GLB mesh: the file does not start with the 'glTF' magic")
    if version != 2:
        raise InvalidMesh(f"cannot parse GLB mesh: version {version}; only glTF 2.0 (version 2) is supported")
    if chunk_type != b"JSON":
        raise InvalidMesh("cannot parse GLB mesh: its first chunk is not the JSON chunk")
    if 20 + chunk_length > len(data):
        raise InvalidMesh(f"cannot parse GLB mesh: its JSON chunk of {chunk_length} bytes runs past the end "
                          "of the file")
    if chunk_length > MAX_GLTF_JSON_BYTES:
        raise LimitExceeded(f"the GLB's JSON chunk has {chunk_length} bytes, limit is {MAX_GLTF_JSON_BYTES}")
    text = data[20:20 + chunk_length]
    containers = text.count(b"[") + text.count(b"{")
    if containers > MAX_GLTF_JSON_CONTAINERS:
        raise LimitExceeded(f"the GLB's JSON has {containers} arrays and objects, limit is {MAX_GLTF_JSON_CONTAINERS}")
    try:
        gltf = json.loads(text)
    except (ValueError, RecursionError) as exc:   # UnicodeDecodeError is a ValueError
        raise InvalidMesh(f"cannot parse GLB mesh: its JSON chunk does not parse ({type(exc).__name__})") from None
    if not isinstance(gltf, dict):
        raise InvalidMesh("cannot parse GLB mesh: its JSON chunk is not an object")
    return gltf


def _index(value: Any, length: int, what: str) -> int:
    """``value`` as an index into a list of ``length`` (glTF indices are non-negative integers)."""
    if type(value) is not int or not 0 <= value < length:
        raise InvalidMesh(f"cannot parse GLB mesh: {what} is {value!r}, not an index below {length}")
    return value


def _array(owner: dict, key: str, what: str) -> list:
    value = owner.get(key, [])
    if not isinstance(value, list):
        raise InvalidMesh(f"cannot parse GLB mesh: {what}{key} is not an array")
    return value


def _object(value: Any, what: str) -> dict:
    if not isinstance(value, dict):
        raise InvalidMesh(f"cannot parse GLB mesh: {what} is not an object")
    return value


def _mesh_sizes(gltf: dict) -> tuple[list[int], list[int], int]:
    """(faces of each mesh, vertices of each mesh, primitives in all), from accessor counts."""
    accessors = _array(gltf, "accessors", "")

    def count(index: Any, what: str) -> int:
        accessor = _object(accessors[_index(index, len(accessors), what)], f"accessor {index}")
        value = accessor.get("count")
        if type(value) is not int or value < 0:
            raise InvalidMesh(f"cannot parse GLB mesh: accessor {index} has count {value!r}")
        return value

    faces, vertices, primitives = [], [], 0
    for m, mesh in enumerate(_array(gltf, "meshes", "")):
        mesh_faces = mesh_vertices = 0
        for p, primitive in enumerate(_array(_object(mesh, f"mesh {m}"), "primitives", f"mesh {m}'s ")):
            where = f"mesh {m} primitive {p}"
            primitive = _object(primitive, where)
            attributes = _object(primitive.get("attributes", {}), f"{where}'s attributes")
            positions = count(attributes["POSITION"], f"{where}'s POSITION accessor") if "POSITION" in attributes else 0
            corners = count(primitive["indices"], f"{where}'s indices accessor") if "indices" in primitive else positions
            mode = primitive.get("mode", _TRIANGLES)
            mesh_faces += corners // 3 if mode == _TRIANGLES else max(corners - 2, 0) if mode == _TRIANGLE_STRIP else 0
            mesh_vertices += positions
            primitives += 1
        faces.append(mesh_faces)
        vertices.append(mesh_vertices)
    return faces, vertices, primitives


def _check_gltf(gltf: dict, limits) -> None:  # noqa: ANN001
    nodes = _array(gltf, "nodes", "")
    _over("the GLB has {count} nodes", len(nodes), limits.max_nodes)
    mesh_faces, mesh_vertices, primitives = _mesh_sizes(gltf)
    _over("the GLB has {count} mesh primitives", primitives, limits.max_nodes)
    _over("the GLB's meshes have {count} faces", sum(mesh_faces), limits.max_faces)
    _over("the GLB's meshes have {count} vertices", sum(mesh_vertices), limits.max_vertices)
    scenes = _array(gltf, "scenes", "")
    if not scenes:      # nothing placed: trimesh loads each mesh once
        return
    scene = _object(scenes[_index(gltf.get("scene", 0), len(scenes), "the scene index")], "the scene")
    # Depth-first from the scene's roots, without recursion. A node is marked when first
    # reached and refused when reached again, so the stack holds each node at most once.
    reached = bytearray(len(nodes))

    def reach(value: Any, what: str) -> int:
        index = _index(value, len(nodes), what)
        if reached[index]:
            raise InvalidMesh(f"cannot parse GLB mesh: node {index} is reached twice from the scene (a cycle, or a node "
                              "with two parents); glTF nodes form trees")
        reached[index] = 1
        return index

    stack = [(reach(root, "a scene root node"), 1) for root in _array(scene, "nodes", "the scene's ")]
    depth = faces = vertices = instances = 0
    while stack:
        index, level = stack.pop()
        depth = max(depth, level)
        node = _object(nodes[index], f"node {index}")
        if "mesh" in node:
            mesh = _index(node["mesh"], len(mesh_faces), f"node {index}'s mesh")
            faces, vertices, instances = faces + mesh_faces[mesh], vertices + mesh_vertices[mesh], instances + 1
        for child in _array(node, "children", f"node {index}'s "):
            stack.append((reach(child, f"a child of node {index}"), level + 1))
    _over("the GLB's node tree is {count} levels deep", depth, limits.max_depth)
    _over(f"the GLB's scene places {{count}} faces ({instances} mesh instances)", faces, limits.max_faces)
    _over(f"the GLB's scene places {{count}} vertices ({instances} mesh instances)", vertices, limits.max_vertices)


# --- OBJ, PLY, STL -------------------------------------------------------------------------

def _lines_starting(data: bytes, keyword: bytes) -> int:
    """Lines that start with ``keyword`` and a blank (C-speed byte counts, no copy)."""
    return sum(data.count(b"\n" + keyword + blank) + data.startswith(keyword + blank) for blank in (b" ", b"\t"))


def _check_obj(data: bytes, limits) -> None:  # noqa: ANN001
    _over("the OBJ has at least {count} faces (one per f line)", _lines_starting(data, b"f"), limits.max_faces)
    _over("the OBJ has {count} vertices (v lines)", _lines_starting(data, b"v"), limits.max_vertices)


_PLY_ELEMENT = re.compile(rb"^element[ \t]+(vertex|face)[ \t]+(\d+)[ \t]*\r?$", re.MULTILINE)


def _check_ply(data: bytes, limits) -> None:  # noqa: ANN001
    end = data.find(b"end_header", 0, 1 << 16)     # headers are a few hundred bytes
    header = data[:end] if end >= 0 else b""
    counts = {name: int(number) for name, number in _PLY_ELEMENT.findall(header)}
    _over("the PLY header declares {count} faces", counts.get(b"face", 0), limits.max_faces)
    _over("the PLY header declares {count} vertices", counts.get(b"vertex", 0), limits.max_vertices)


def _check_stl(data: bytes, limits) -> None:  # noqa: ANN001
    binary = len(data) >= 84 and 84 + 50 * struct.unpack_from("<I", data, 80)[0] == len(data)
    faces = struct.unpack_from("<I", data, 80)[0] if binary else data.count(b"endfacet")
    _over("the STL has {count} triangles", faces, limits.max_faces)
    _over("the STL has {count} vertices (three per triangle)", 3 * faces, limits.max_vertices)
