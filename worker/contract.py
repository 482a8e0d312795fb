"""Names and bounds the parts agree on, each defined here once (docs/ARCHITECTURE.md,
Contracts 1 and 2): the tileable sampler's file name, the slice planes, and the hard bounds
of tiles, volumes and bakes.

A leaf (standard library only): the model's export and training (``model/``), the worker
and the service's settings, schemas and CLI read these from here; the service's own limits
(``TEXSPACE_MAX_*``) may be set lower, never higher, and ``GET /v1/limits`` tells clients
the ones in force.
"""
from __future__ import annotations

#: the tileable sampler's file name beside sampler.onnx (a model export, a fit's folder, a
#: fitted texture's storage folder); the manifest names it under ``tileable_sampler``
TILEABLE_SAMPLER = "sampler_tileable.onnx"

#: the axis-aligned slice planes: the world axes that receive a plane's u (columns), v (rows)
#: and its offset
PLANE_AXES = {"xy": (0, 1, 2), "xz": (0, 2, 1), "yz": (1, 2, 0)}
PLANES = tuple(PLANE_AXES)

#: a tile's side in pixels
MIN_TILE_SIZE = 64
MAX_TILE_SIZE = 1024
#: a volume's voxels per side
MIN_VOLUME_RESOLUTION = 2
MAX_VOLUME_RESOLUTION = 1024
#: a bake's texture atlas side in pixels
MIN_BAKE_RESOLUTION = 16
MAX_BAKE_RESOLUTION = 8192
