"""A dense OpenVDB writer in numpy: a Vec3s colour grid ``Cd`` (``Tree_vec3s_5_4_3``) and a
float ``density`` grid (``Tree_float_5_4_3``), zip compression.

No OpenVDB Python binding installs into the project's environment from the registries
(PyPI: ``openvdb``, ``pyopenvdb`` and ``nanovdb`` offer no installable distribution for
CPython 3.11 on Linux; Debian's ``python3-openvdb`` 10.0.1 is built against Debian's
numpy 1.x and crashes under numpy 2), so the file is written here, following the OpenVDB 10 library's
own serialisation (``io/Archive.cc``, ``tree/RootNode.h``, ``InternalNode.h``,
``LeafNode.h``, ``io/Compression.h``, ``math/Maps.h``). The tests read the files back
with Debian's ``pyopenvdb`` under the system Python when it is installed.

Layout of the file (all little-endian):

* header: magic ``0x56444220``, file format 224, library 10.0, has-grid-offsets 1, a
  36-character UUID (derived from the volume's size and bounds, so output is
  deterministic), file metadata (``creator``), grid count 2;
* per grid, ``Cd`` then ``density``: a descriptor (name, type, no instance parent, the
  grid's three stream offsets: grid, data blocks, end), then the grid itself;
* grid: compression flags ``COMPRESS_ZIP`` (no active-mask compression, so every node
  stores all its values), metadata (``class``: ``unknown`` / ``fog volume``, ``name``,
  ``vector_type = invariant`` for ``Cd``, ``is_local_space``, ``texspace_bounds_min/max``, ``texspace_colour = linear``), the
  transform ``ScaleTranslateMap`` with scale = voxel size and translation = the first
  voxel's centre (so index (i, j, k) maps to voxel centre ``min + (index + 0.5) * size``,
  which is how Houdini and Blender place VDB voxels), then the topology (root with one
  5-level internal node at the origin, 4-level nodes, 8^3 leaves; only leaves that hold
  voxels) and the leaf buffers. Voxel (i, j, k) is volume[k, j, i] (x = column, y = row,
  z = slice); voxels past N in a partial leaf are inactive and 0 (the background).

``density`` is the colour's linear Rec. 709 luminance: Blender's volume shader renders a
grid of that name (and colours it with ``Cd`` when asked), Houdini's volume tools take it
too; a colour grid alone renders as empty space.
"""
from __future__ import annotations

import struct
import uuid
import zlib

import numpy as np

from worker.colour import LUMA_709

FILE_VERSION = 224
LIBRARY_VERSION = (10, 0)
COMPRESS_ZIP = 0x1
GRID_TYPES = {3: "Tree_vec3s_5_4_3", 1: "Tree_float_5_4_3"}   # by components per voxel
NO_MASK_AND_ALL_VALS = 6        # io/Compression.h: per-node "metadata" byte
LEAF, NODE1, NODE2 = 8, 128, 4096        # voxels per side of a leaf, 4-level and 5-level node
ZIP_LEVEL = 1                   # zlib level: float noise barely compresses; level 1 is fastest
MAX_SIDE = NODE2                # one 5-level node; volumes are at most 1024 per side


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _metadata(entries: dict[str, tuple[str, bytes]]) -> bytes:
    """A MetaMap: count, then (name, type name, value size, value) sorted by name."""
    out = struct.pack("<i", len(entries))
    for name in sorted(entries):
        kind, value = entries[name]
        out += _string(name) + _string(kind) + struct.pack("<I", len(value)) + value
    return out


def _meta_string(text: str) -> tuple[str, bytes]:
    return "string", text.encode()


def _meta_vec3d(values) -> tuple[str, bytes]:
    return "vec3d", struct.pack("<3d", *(float(v) for v in values))


def _zip(data: bytes) -> bytes:
    """io::zipToStream: int64 size then zlib data, or -size then the raw bytes."""
    packed = zlib.compress(data, ZIP_LEVEL)
    if len(packed) < len(data):
        return struct.pack("<q", len(packed)) + packed
    return struct.pack("<q", -len(data)) + data


def _values(data: bytes) -> bytes:
    """io::writeCompressedValues without active-mask compression: flag byte + zipped data."""
    return bytes([NO_MASK_AND_ALL_VALS]) + _zip(data)


def _mask(bits: np.ndarray) -> bytes:
    """util::NodeMask::save: the bits in node order as little-endian 64-bit words."""
    return np.packbits(np.asarray(bits, dtype=bool).ravel(), bitorder="little").tobytes()


def _counts(n: int, origin: int, size: int, child: int) -> int:
    """Children (of ``child`` voxels) holding voxels, along one axis of a node at ``origin``."""
    return max(0, min(size // child, -(-(n - origin) // child)))


def _leaf_mask(n: int, origin: tuple[int, int, int]) -> bytes:
    inside = [np.arange(LEAF) + o < n for o in origin]
    return _mask(inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :])


def _node1_origins(n: int):
    """Origins (x, y, z) of the 4-level nodes, in the 5-level node's child order (x-major)."""
    c = -(-n // NODE1)
    return [(x * NODE1, y * NODE1, z * NODE1) for x in range(c) for y in range(c) for z in range(c)]


def _node1_leaves(n: int, origin) -> tuple[int, int, int]:
    return tuple(_counts(n, o, NODE1, LEAF) for o in origin)


def _topology(n: int, components: int) -> bytes:
    """Tree::writeTopology: buffer count, root (background, tiles, children), nodes, leaf masks."""
    value = 4 * components                               # bytes per voxel value
    background = bytes(value)
    c2 = -(-n // NODE1)
    child2 = np.zeros((32, 32, 32), dtype=bool)
    child2[:c2, :c2, :c2] = True
    out = [struct.pack("<i", 1), background, struct.pack("<II", 0, 1), struct.pack("<3i", 0, 0, 0),
           _mask(child2), _mask(np.zeros(32 ** 3, bool)), _values(bytes(32 ** 3 * value))]
    empty1, values1 = _mask(np.zeros(16 ** 3, bool)), _values(bytes(16 ** 3 * value))
    for origin in _node1_origins(n):
        cx, cy, cz = _node1_leaves(n, origin)
        child1 = np.zeros((16, 16, 16), dtype=bool)
        child1[:cx, :cy, :cz] = True
        out += [_mask(child1), empty1, values1]
        out += [_leaf_mask(n, (origin[0] + LEAF * i, origin[1] + LEAF * j, origin[2] + LEAF * k))
                for i in range(cx) for j in range(cy) for k in range(cz)]
    return b"".join(out)


def _write_buffers(f, volume: np.ndarray, n: int, density: bool) -> None:
    """Tree::writeBuffers: per leaf, in tree order: value mask, flag byte, zipped values
    ([x][y][z] order; RGB interleaved, or the luminance for ``density``). The volume is
    read one 4-level node at a time."""
    full = _leaf_mask(n, (0, 0, 0)) if n >= LEAF else None
    components = 1 if density else 3
    for ox, oy, oz in _node1_origins(n):
        cx, cy, cz = _node1_leaves(n, (ox, oy, oz))
        block = np.zeros((NODE1, NODE1, NODE1, components), dtype="<f4")   # [x][y][z][c]
        part = np.asarray(volume[oz:oz + NODE1, oy:oy + NODE1, ox:ox + NODE1], dtype="<f4")
        if density:
            part = (part @ LUMA_709)[..., None]
        block[:part.shape[2], :part.shape[1], :part.shape[0]] = part.transpose(2, 1, 0, 3)
        leaves = block.reshape(16, LEAF, 16, LEAF, 16, LEAF, components).transpose(0, 2, 4, 1, 3, 5, 6)
        for i in range(cx):
            for j in range(cy):
                for k in range(cz):
                    origin = (ox + LEAF * i, oy + LEAF * j, oz + LEAF * k)
                    inner = max(origin) + LEAF <= n
                    mask = full if inner else _leaf_mask(n, origin)
                    f.write(mask + _values(np.ascontiguousarray(leaves[i, j, k]).tobytes()))


def write_vdb(f, volume: np.ndarray, bounds: np.ndarray) -> None:
    """Write ``volume`` as an OpenVDB file (grids ``Cd`` and ``density``) to the seekable
    binary file ``f``.

    volume : (N, N, N, 3) float32 linear RGB, [z, y, x, channel] (a memmap is fine: it is
    read one 128^3 block at a time, once per grid). bounds : (2, 3) float64 world box (min, max).
    """
    n = volume.shape[0]
    if volume.shape != (n, n, n, 3) or not 1 <= n <= MAX_SIDE:
        raise ValueError(f"expected an (N, N, N, 3) volume with N <= {MAX_SIDE}, got {volume.shape}")
    bounds = np.asarray(bounds, dtype=np.float64)
    size = (bounds[1] - bounds[0]) / n
    key = f"texspace:{n}:{bounds.tolist()}"
    f.write(struct.pack("<QIII", 0x56444220, FILE_VERSION, *LIBRARY_VERSION) + b"\x01"
            + str(uuid.uuid5(uuid.NAMESPACE_URL, key)).encode()
            + _metadata({"creator": _meta_string("texspace")}) + struct.pack("<i", 2))
    translate = bounds[0] + 0.5 * size
    transform = _string("ScaleTranslateMap") + struct.pack(
        "<18d", *translate, *size, *np.abs(size), *(1 / size), *(1 / size ** 2), *(0.5 / size))
    for name, density in (("Cd", False), ("density", True)):
        components = 1 if density else 3
        f.write(_string(name) + _string(GRID_TYPES[components]) + _string(""))
        offsets_at = f.tell()
        f.write(bytes(24))                               # grid, block and end positions
        grid_pos = f.tell()
        entries = {
            "class": _meta_string("fog volume" if density else "unknown"), "name": _meta_string(name),
            "is_local_space": ("bool", b"\x00"),
            "texspace_bounds_min": _meta_vec3d(bounds[0]), "texspace_bounds_max": _meta_vec3d(bounds[1]),
            "texspace_colour": _meta_string("linear luminance" if density else "linear")}
        if not density:
            entries["vector_type"] = _meta_string("invariant")
        f.write(struct.pack("<I", COMPRESS_ZIP) + _metadata(entries) + transform + _topology(n, components))
        block_pos = f.tell()
        _write_buffers(f, volume, n, density)
        end_pos = f.tell()
        f.seek(offsets_at)
        f.write(struct.pack("<3q", grid_pos, block_pos, end_pos))
        f.seek(end_pos)
