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
#: a model's VGG16 style statistics (sRGB images -> vectors whose squared distance is the Gram
#: loss) beside its encoder: an upload chooses its code by them. The manifest names it under
#: ``style_features``
STYLE_FEATURES = "style.onnx"
#: a fit's sampler with finer octaves for a photo above the working size (model/detail.py), beside
#: sampler.onnx; tiles above the native zoom draw with it. The fit's manifest names it under ``detail``
DETAIL_SAMPLER = "sampler_detail.onnx"
#: its tileable twin (``period`` input), beside it: tileable images above the native zoom draw with it
DETAIL_TILEABLE_SAMPLER = "sampler_detail_tileable.onnx"
#: seconds of a fit job's detail stage by default (model.fit, the service's fit jobs)
DETAIL_SECONDS = 20.0

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
#: a photo's real width in metres, and a mesh unit in metres (bakes at real size): a
#: kilometre-wide aerial photo or a light-year-sized unit is a typo, not a texture
MAX_WIDTH_M = 10_000.0
MAX_UNIT_M = 1_000.0
