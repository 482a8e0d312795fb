"""A minimal OpenVDB reader for the files worker/vdb.py writes (Vec3s and float grids, zip or no
compression, no active-mask compression, no tiles), written from the format as the
OpenVDB 10 library serialises it. The authoritative check is the library itself
(tests/worker/test_volumes.py runs Debian's pyopenvdb where it is installed); this one
runs everywhere, so a broken file fails the fast suite too."""
from __future__ import annotations

import struct
import zlib

import numpy as np


class Stream:
    def __init__(self, data: bytes, at: int = 0):
        self.data, self.at = data, at

    def take(self, n: int) -> bytes:
        out = self.data[self.at:self.at + n]
        assert len(out) == n, "truncated VDB"
        self.at += n
        return out

    def unpack(self, fmt: str):
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += struct.calcsize("<" + fmt)
        return values if len(values) > 1 else values[0]

    def string(self) -> str:
        return self.take(self.unpack("I")).decode()

    def metadata(self) -> dict:
        out = {}
        for _ in range(self.unpack("i")):
            name, kind = self.string(), self.string()
            raw = self.take(self.unpack("I"))
            out[name] = {"string": lambda b: b.decode(), "bool": lambda b: bool(b[0]),
                         "vec3d": lambda b: struct.unpack("<3d", b)}.get(kind, lambda b: b)(raw)
        return out

    def mask(self, bits: int) -> np.ndarray:
        return np.unpackbits(np.frombuffer(self.take(bits // 8), np.uint8), bitorder="little").astype(bool)

    def values(self, count: int, compression: int, components: int) -> np.ndarray:
        assert self.take(1)[0] == 6, "expected NO_MASK_AND_ALL_VALS"
        if compression & 1:
            size = self.unpack("q")
            raw = zlib.decompress(self.take(size)) if size > 0 else self.take(-size)
        else:
            raw = self.take(count * 4 * components)
        return np.frombuffer(raw, "<f4").reshape(count, components)


COMPONENTS = {"Tree_vec3s_5_4_3": 3, "Tree_float_5_4_3": 1}


def read_vdb(data: bytes) -> dict[str, tuple[dict, np.ndarray]]:
    """{grid name: (info, dense [x][y][z][c] float32 array of the active box from 0)}, in
    file order."""
    s = Stream(data)
    magic, version, major, minor = s.unpack("QIII")
    assert magic == 0x56444220 and s.take(1) == b"\x01"
    uuid = s.take(36).decode()
    file_meta = s.metadata()
    grids = {}
    for _ in range(s.unpack("i")):
        name, grid_type, parent = s.string(), s.string(), s.string()
        grid_pos, block_pos, end_pos = s.unpack("qqq")
        assert s.at == grid_pos
        c = COMPONENTS[grid_type]
        compression = s.unpack("I")
        meta = s.metadata()
        map_type = s.string()
        assert map_type == "ScaleTranslateMap"
        maps = np.array(s.unpack("18d")).reshape(6, 3)
        assert s.unpack("i") == 1 and s.take(4 * c) == bytes(4 * c)          # background 0
        tiles, children = s.unpack("II")
        assert (tiles, children) == (0, 1) and s.unpack("3i") == (0, 0, 0)
        child2 = s.mask(32 ** 3)
        assert not s.mask(32 ** 3).any() and not s.values(32 ** 3, compression, c).any()
        leaves = []                              # (origin, mask) in tree order
        for i2 in np.flatnonzero(child2):
            o1 = np.array([i2 >> 10, (i2 >> 5) & 31, i2 & 31]) * 128
            child1 = s.mask(16 ** 3)
            assert not s.mask(16 ** 3).any() and not s.values(16 ** 3, compression, c).any()
            for i1 in np.flatnonzero(child1):
                origin = o1 + np.array([i1 >> 8, (i1 >> 4) & 15, i1 & 15]) * 8
                leaves.append((origin, s.mask(512)))
        assert s.at == block_pos
        side = max(int(o.max()) for o, _ in leaves) + 8
        dense = np.zeros((side, side, side, c), np.float32)
        active = np.zeros((side, side, side), bool)
        for origin, mask in leaves:
            assert np.array_equal(s.mask(512), mask)
            x, y, z = origin
            dense[x:x + 8, y:y + 8, z:z + 8] = s.values(512, compression, c).reshape(8, 8, 8, c)
            active[x:x + 8, y:y + 8, z:z + 8] = mask.reshape(8, 8, 8)
        assert s.at == end_pos
        hi = np.argwhere(active).max(axis=0) + 1
        info = {"version": version, "library": (major, minor), "uuid": uuid, "file_meta": file_meta,
                "name": name, "type": grid_type, "parent": parent, "compression": compression,
                "meta": meta, "translation": maps[0], "scale": maps[1], "active": int(active.sum())}
        grids[name] = (info, dense[:hi[0], :hi[1], :hi[2]])
    assert s.at == len(data)
    return grids
