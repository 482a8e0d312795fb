"""Mesh files refused from their header (``worker/mesh_size.py``), before trimesh parses
them: in milliseconds and a few megabytes, whatever the parse would have cost."""
from __future__ import annotations

import io
import struct
import time
import tracemalloc
from unittest import mock

import numpy as np
import pytest
import trimesh

from tests.helpers import chained_glb, glb_file, instanced_glb, tetrahedra_glb
from worker.bake import BakeLimits, read_mesh
from worker.errors import InvalidMesh, LimitExceeded
from worker.mesh_size import MAX_GLTF_JSON_BYTES, check_mesh_size


CPU_SECONDS = 3.0  # see refused_quickly


def refused_quickly(data: bytes, ext: str, limits: BakeLimits, error: type, match: str) -> None:
    """``read_mesh`` raises ``error`` from the header, before any parse (trimesh is never
    called), within a few CPU seconds, and with a tracemalloc peak under 100 MB (measured in
    a second call: tracing slows allocations several times over). The figure the issue asked
    for, under 1 s, holds on an idle machine (0.2-0.34 s); the bound here leaves room for a
    CI machine whose two cores are shared (1.33 s seen there), and still fails on a parse
    (a 5,000-node chain took 22 minutes)."""
    started = time.process_time()
    with pytest.raises(error, match=match), mock.patch("trimesh.load", side_effect=AssertionError("parsed")):
        read_mesh(data, f"mesh.{ext}", limits)
    elapsed = time.process_time() - started
    tracemalloc.start()
    try:
        with pytest.raises(error, match=match):
            read_mesh(data, f"mesh.{ext}", limits)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert elapsed < CPU_SECONDS, f"{elapsed:.2f} s"
    assert peak < 100 * 2**20, f"{peak / 2**20:.0f} MB"


def test_a_deep_node_chain_is_refused_from_the_json():
    data = chained_glb(5000)
    refused_quickly(data, "glb", BakeLimits(), LimitExceeded, "the GLB has 5000 nodes, limit is 4096")
    refused_quickly(data, "glb", BakeLimits(max_nodes=10_000), LimitExceeded,
                    "node tree is 5000 levels deep, limit is 64")


def test_a_hundred_thousand_instances_are_refused_from_the_json():
    data = instanced_glb(100_000)
    refused_quickly(data, "glb", BakeLimits(), LimitExceeded, "has 100001 nodes, limit is 4096")
    started = time.process_time()
    with pytest.raises(LimitExceeded, match=r"scene places 400000 faces \(100000 mesh instances\), limit is 200000"), \
            mock.patch("trimesh.load", side_effect=AssertionError("parsed")):
        read_mesh(data, "mesh.glb", BakeLimits(max_nodes=200_000, max_faces=200_000))
    assert time.process_time() - started < CPU_SECONDS


def test_instanced_faces_count_every_placement():
    """300 placements of one 4-face mesh are 1,200 faces, though the file holds 4."""
    with pytest.raises(LimitExceeded, match=r"places 1200 faces \(300 mesh instances\), limit is 1000"):
        check_mesh_size(instanced_glb(300), "glb", BakeLimits(max_faces=1000))
    check_mesh_size(instanced_glb(250), "glb", BakeLimits(max_faces=1000))


@pytest.mark.parametrize("nodes, roots, match", [
    ([{"mesh": 0, "children": [1]}, {"mesh": 0, "children": [0]}], [0], "node 0 is reached twice"),  # a cycle
    ([{"children": [0]}], [0], "node 0 is reached twice"),                                         # its own child
    ([{"children": [2]}, {"children": [2]}, {"mesh": 0}], [0, 1], "node 2 is reached twice"),      # two parents
    ([{"children": [7]}], [0], "a child of node 0 is 7, not an index below 1"),
    ([{"mesh": 3}], [0], "node 0's mesh is 3, not an index below 1"),
    ([{"children": "1"}], [0], "node 0's children is not an array"),
    ([{"mesh": True}], [0], "node 0's mesh is True"),
    ([{}], [-1], "a scene root node is -1"),
])
def test_malformed_node_trees_are_invalid(nodes, roots, match):
    with pytest.raises(InvalidMesh, match=match):
        read_mesh(tetrahedra_glb(nodes, roots), "mesh.glb")


def test_malformed_json_chunks_are_invalid():
    header = b"glTF" + struct.pack("<II", 2, 40)
    for data, match in [(header + struct.pack("<I4s", 8, b"JSON") + b"{\"a\":[1 ", "does not parse"),
                        (header + struct.pack("<I4s", 4, b"JSON") + b"[1] ", "not an object"),
                        (header + struct.pack("<I4s", 4, b"BIN\0") + b"\0" * 4, "first chunk is not the JSON"),
                        (header + struct.pack("<I4s", 90, b"JSON") + b"{}", "runs past the end"),
                        (b"glTF" + struct.pack("<II", 1, 40) + b"\0" * 12, "version 1"),
                        (glb_file({"meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                                   "accessors": [{"count": -4}]}), "accessor 0 has count -4")]:
        with pytest.raises(InvalidMesh, match=match):
            check_mesh_size(data, "glb", BakeLimits())


def test_json_that_would_take_too_much_memory_is_refused_unparsed():
    nested = b"[" * 300_000 + b"]" * 300_000            # 2^18+ arrays (and a recursion bomb)
    wide = b"{\"a\":\"" + b"x" * MAX_GLTF_JSON_BYTES + b"\"}"
    for text, match in [(nested, "arrays and objects"), (wide, "JSON chunk has")]:
        data = b"glTF" + struct.pack("<II", 2, 20 + len(text)) + struct.pack("<I4s", len(text), b"JSON") + text
        refused_quickly(data, "glb", BakeLimits(), LimitExceeded, match)


def test_the_costliest_json_within_the_limits_parses_under_100_mb():
    """Short strings cost the most per byte parsed (~13x): a chunk of them at the size limit."""
    text = b'{"extras":[' + b'"ab",' * ((MAX_GLTF_JSON_BYTES - 20) // 5) + b'"ab"]}'
    data = b"glTF" + struct.pack("<II", 2, 20 + len(text)) + struct.pack("<I4s", len(text), b"JSON") + text
    tracemalloc.start()
    try:
        check_mesh_size(data, "glb", BakeLimits())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 100 * 2**20, f"{peak / 2**20:.0f} MB"


def test_a_tree_within_the_limits_flattens_as_trimesh_does():
    """Each placement turned by its node's transform (rotations, scales, mirrors that flip
    the winding) in the order trimesh's ``to_mesh`` gives, which multiplies every path anew."""
    rng = np.random.default_rng(5)
    nodes = []
    for i in range(40):
        quaternion = rng.normal(size=4)
        nodes.append({"translation": rng.normal(size=3).tolist(),
                      "rotation": (quaternion / np.linalg.norm(quaternion)).tolist(),
                      "scale": (rng.uniform(0.5, 2, 3) * rng.choice([-1, 1], 3)).tolist(),
                      **({"mesh": 0} if i % 3 else {})})
        if i:
            nodes[int(rng.integers(0, i))].setdefault("children", []).append(i)
    data = tetrahedra_glb(nodes, [0])
    expected = trimesh.load(io.BytesIO(data), file_type="glb", process=False).to_mesh()
    mesh = read_mesh(data, "tree.glb")
    assert np.array_equal(mesh.faces, expected.faces)
    np.testing.assert_allclose(mesh.vertices, expected.vertices, rtol=0, atol=1e-12)


def test_a_deep_chain_within_raised_limits_flattens_in_linear_time():
    """1,000 levels: a fraction of a second (trimesh's own flattening took minutes)."""
    started = time.process_time()
    mesh = read_mesh(chained_glb(1000), "chain.glb", BakeLimits(max_depth=1000))
    assert len(mesh.faces) == 4000 and mesh.vertices[:, 0].max() == pytest.approx(501)
    assert time.process_time() - started < 5.0


def test_obj_ply_stl_counts_come_from_lines_and_headers():
    many_faces = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 1_000_000
    refused_quickly(many_faces, "obj", BakeLimits(max_faces=200_000), LimitExceeded,
                    r"at least 1000000 faces \(one per f line\), limit is 200000")
    refused_quickly(b"v 0 0 0\n" * 300_000 + b"f\t1 2 3\n", "obj", BakeLimits(max_vertices=200_000),
                    LimitExceeded, "300000 vertices")
    ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n" \
          b"property float z\nelement face 2000000000\nproperty list uchar int vertex_indices\nend_header\n"
    refused_quickly(ply, "ply", BakeLimits(), LimitExceeded, "declares 2000000000 faces")
    stl = b"\0" * 80 + struct.pack("<I", 300_000) + b"\0" * 50 * 300_000
    refused_quickly(stl, "stl", BakeLimits(), LimitExceeded, r"900000 vertices \(three per triangle\), limit is 500000")
    refused_quickly(b"solid x\n" + b"facet normal 0 0 1\nendfacet\n" * 600_000, "stl", BakeLimits(),
                    LimitExceeded, "600000 triangles")
