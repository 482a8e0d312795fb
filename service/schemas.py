"""Request and response bodies (pydantic). Links are absolute paths under /v1."""
from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from worker.contract import (DETAIL_SECONDS, MAX_VOLUME_RESOLUTION, MAX_WIDTH_M, MIN_BAKE_RESOLUTION,
                             MIN_TILE_SIZE, MIN_VOLUME_RESOLUTION)
from worker.files import OFFERED
from worker.derived_maps import DEFAULT_NORMAL_STRENGTH, MAP_NAMES, MAX_NORMAL_STRENGTH, MAX_WHOLE_PIXELS
from worker.bake import BAKE_FORMATS
from worker.triplanar import PROJECTIONS
from worker.gpu_textures import DDS_COMPRESSIONS, GPU_FORMATS
from worker.photo import LIGHTING
from worker.regions import REGION_FORMATS
from worker.tiles import COORD_LIMIT, MAX_TILE_SIZE, MAX_ZOOM, MIN_ZOOM, PLANES
from worker.volume_writers import VOLUME_FORMATS

from .deps import SafeText
from .settings import FIT_SECONDS, MAX_DETAIL_SECONDS, MAX_FIT_SECONDS, Settings
from .tables import Job, Texture
from .vocabulary import TERMINAL_STATES, JobKind, JobState

Seed = Annotated[int, Field(ge=0, le=2**31 - 1, description="texture instance; same seed, same texture")]


class TextureLinks(BaseModel):
    self: str
    exemplar: str | None
    tiles: str = Field(description="URL template: replace {z}/{x}/{y}; also .webp and .exr")
    tilejson: str
    volumes: str
    bakes: str
    fit: str
    regions: str


class Refinement(BaseModel):
    """An upload's in-place refinement: a fit job that, when it succeeds, makes the
    texture serve its own fitted sampler (same id and URLs, new tile bytes and ETags)."""

    job_id: str
    state: JobState
    progress: float = Field(ge=0, le=1, description="share of the fit's time budget spent (0 while queued)")
    stage: Literal["deferred", "queued", "fitting", "paused", "done"] = Field(
        description="deferred: not queued yet, the fit queue (or its owner's share of it) was full at upload; it is "
                    "queued as room frees, oldest upload first (its job does not exist until then); "
                    "queued: waiting for its first turn; fitting: running; paused: past its interim's second (the "
                    "interim served if it beat the encoder's code), waiting, its state stored, for its continuation "
                    "while other uploads get theirs; done: ended")
    queue_position: int | None = Field(
        None, ge=0, description="fits the fit lane runs before this one starts (0: next, or running); "
                                "null once it ended")
    interim_eta_seconds: float | None = Field(
        None, ge=0, description="estimated seconds until its first refined tiles (the interim) are served; "
                                "null once served, or when none will be")
    final_eta_seconds: float | None = Field(
        None, ge=0, description="estimated seconds until its final fitted sampler is served; null once it ended")


    @classmethod
    def of(cls, job: Job, wait: dict | None = None) -> "Refinement":
        wait = wait or {}
        stage = ("done" if job.state in TERMINAL_STATES else "fitting" if job.state == JobState.RUNNING
                 else "paused" if job.stage else "queued")
        return cls(job_id=job.id, state=job.state, progress=job.progress, stage=stage,
                   queue_position=wait.get("position"),
                   interim_eta_seconds=_rounded(wait.get("interim_eta_seconds")),
                   final_eta_seconds=_rounded(wait.get("final_eta_seconds")))


    @classmethod
    def deferred(cls, texture: Texture) -> "Refinement":
        """A refinement waiting for room in the fit queue (``Texture.refinement_deferred``)."""
        return cls(job_id=texture.refinement_job_id or "", state=JobState.QUEUED, progress=0.0, stage="deferred")


def _rounded(seconds: float | None) -> float | None:
    return None if seconds is None else round(max(0.0, seconds), 1)


class Structure(BaseModel):
    """What a fit found in the photo (model/structure/) and built into its sampler (model/fit.py)."""

    grain: Literal["x", "y"] | None = Field(
        description="the axis the noise is stretched along (the photo's grain: x left-right, y up-down); "
                    "null: isotropic")
    straightened: float = Field(
        0.0, description="degrees the photo was turned before fitting so that its grain, leaning 3 to 45 degrees "
                         "off the nearer axis, runs along it (the tiles show it straight); 0: not turned")
    grain_stretch: float | None = Field(
        None, description="how many times longer the sampler's noise cells are along the grain: 16 for a strong "
                          "grain (gradients across it at least 9x those along it), else 8; null: no grain")
    lattice: list[float] | None = Field(
        None, min_length=4, max_length=4,
        description="the photo's repeat lattice the sampler follows, two basis vectors (ax, ay, bx, by) in "
                    "world units (x right, y down the photo); null: none")
    muted_octaves: int = Field(
        0, ge=0, description="how many of the coarsest noise octaves the sampler has muted (an even photo, the "
                             "fit's even option); 0: none")
    lean: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="the photo's lean the sampler's plane map started at (the fit's lean option): degrees from +x "
                    "towards +y (y down the photo) that its features run along, and how many times longer they are "
                    "along it; null: none")
    detail_zoom: int | None = Field(None, description="the deepest zoom at which tiles show the photo's own detail, one pixel per photo pixel: 7 or 8 where the fit's detail stage learned finer octaves on a photo of 512 or 1024 px and up (tiles and images above the native zoom 6 draw them); null: none, above zoom 6 the texture is magnified")

    @model_validator(mode="after")
    def _stretch_of_earlier_rows(self) -> "Structure":
        # rows stored before the stretch was chosen per photo: every grain fit was stretched 8x
        if self.grain and self.grain_stretch is None:
            self.grain_stretch = 8.0
        return self


class TextureOut(BaseModel):
    id: str
    name: str
    code: list[float] = Field(min_length=1, description="the texture's point in its model's space: as many numbers as "
                              "that model's code_size (GET /v1/models, each manifest; 8 for the shipped space)")
    colour: list[float] | None = Field(
        None, description="the colour table the sampler applies last: the photo's colour statistics matched to "
                          "this texture's sampler (docs/ARCHITECTURE.md, Contract 1); null: the identity")
    model_version: str
    source: Literal["upload", "interpolate", "fit"]
    parents: dict[str, Any] | None = None
    width: int | None = Field(None, description="exemplar width in pixels")
    height: int | None = None
    width_m: float | None = Field(None, description="the photo's real width in metres, if given (upload or PATCH): "
                                                    "bakes with unit_m texture meshes at that size")
    has_own_sampler: bool = Field(description="true for fitted textures (they carry their own sampler)")
    sampler: Literal["encoder", "interim", "fitted"] = Field(
        description="what tiles come from: the model's sampler at the encoder's code; an interim, the best state "
                    "of the upload's refinement part way through its fit (TEXSPACE_FIT_INTERIM_SECONDS), which "
                    "the finished fit replaces; or a sampler fitted to this exemplar (a fit's new texture, or an "
                    "upload once its refinement succeeded)")
    refinement: Refinement | None = Field(None, description="the upload's automatic refinement, if one was queued")
    structure: Structure | None = Field(
        None, description="what the fitted sampler was built with (grain, repeat lattice); null from the encoder")
    lighting: Literal[LIGHTING] = Field(
        "as-is", description="how its photo is encoded and fitted: as it is, or with its smooth shading (light "
                             "falling off, a vignette) divided out first; the stored photo is unchanged")
    created_at: dt.datetime
    updated_at: dt.datetime
    links: TextureLinks

    @classmethod
    def of(cls, t: Texture, refinement: Job | None = None, wait: dict | None = None) -> "TextureOut":
        """``refinement``: the job named by ``t.refinement_job_id``, if any; ``wait``: its place
        in the fit lane (``service.jobs.refinement_wait``)."""
        base = f"/v1/textures/{t.id}"
        return cls(id=t.id, name=t.name, code=t.code, colour=t.colour, model_version=t.model_version, source=t.source,
                   parents=t.parents, width=t.width, height=t.height, width_m=t.width_m, has_own_sampler=bool(t.sampler_key),
                   sampler=("interim" if t.sampler_interim else "fitted") if t.sampler_key else "encoder",
                   refinement=(Refinement.of(refinement, wait) if refinement is not None
                               else Refinement.deferred(t) if t.refinement_deferred and t.refinement_job_id else None),
                   structure=Structure(**t.served_structure()) if t.served_structure() else None,
                   lighting=t.lighting or "as-is",
                   created_at=t.created_at, updated_at=t.updated_at,
                   links=TextureLinks(self=base, exemplar=f"{base}/exemplar" if t.exemplar_key else None,
                                      tiles=f"{base}/tiles/{{z}}/{{x}}/{{y}}.png", tilejson=f"{base}/tilejson.json",
                                      volumes=f"{base}/volumes", bakes=f"{base}/bakes", fit=f"{base}/fit",
                                      regions=f"{base}/regions"))


class TexturePage(BaseModel):
    items: list[TextureOut]
    next_cursor: str | None = Field(None, description="pass as ?cursor= for the next page")


class TexturePatch(BaseModel):
    """What a PATCH changes: the fields given (at least one)."""
    model_config = {"extra": "forbid"}
    name: SafeText | None = Field(None, max_length=200)
    width_m: float | None = Field(None, gt=0, le=MAX_WIDTH_M, description="the photo's real width in metres")

    @model_validator(mode="after")
    def _something(self) -> "TexturePatch":
        if not self.model_fields_set:
            raise ValueError("give name, width_m or both")
        if "name" in self.model_fields_set and self.name is None:
            raise ValueError("name cannot be null")
        return self


class InterpolateIn(BaseModel):
    model_config = {"extra": "forbid"}
    a: SafeText = Field(description="texture id at t = 0")
    b: SafeText = Field(description="texture id at t = 1")
    t: float = Field(ge=0.0, le=1.0)
    name: SafeText | None = Field(None, max_length=200)


Bounds = Annotated[list[list[float]], Field(min_length=2, max_length=2, description="[[x0,y0,z0],[x1,y1,z1]] world units")]


class VolumeIn(BaseModel):
    model_config = {"extra": "forbid"}
    after_refinement: bool = Field(
        False, description="if the texture's refinement may still replace its sampler (it is queued or running), "
                           "wait for it to end and render with the refined sampler; false: render now with what the "
                           "texture serves (the job's sampler says which)")
    resolution: int = Field(64, ge=MIN_VOLUME_RESOLUTION, le=MAX_VOLUME_RESOLUTION,
                            description="voxels per side (N); capped by the server limit")
    bounds: Bounds = Field(default_factory=lambda: [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    seed: Seed = 0
    format: Literal[VOLUME_FORMATS] = Field(
        "npy", description="npy: float32 linear RGB [N,N,N,3] in (z, y, x) order; exr / tiff: one z slice per "
                           "part / page (EXR: one Blender layer per slice), with bounds and voxel size in each header; raw: zip of raw float32 + "
                           "JSON header; nrrd; dds volume; flipbook: one PNG with the slices in a grid (Unity 3D "
                           "texture import); vdb: OpenVDB, a float RGB (vec3s) grid 'Cd' and a float grid "
                           "'density' (luminance) placed by the bounds (Blender, Houdini)")

    @field_validator("bounds")
    @classmethod
    def _box(cls, value: list[list[float]]) -> list[list[float]]:
        if any(len(corner) != 3 for corner in value):
            raise ValueError("each corner needs 3 coordinates")
        if any(not (abs(c) < 1e9) for corner in value for c in corner):
            raise ValueError("coordinates must be finite and below 1e9 in magnitude")
        if any(hi <= lo for lo, hi in zip(value[0], value[1])):
            raise ValueError("the second corner must be greater than the first on every axis")
        return value


class FitIn(BaseModel):
    model_config = {"extra": "forbid"}
    seconds: float = Field(FIT_SECONDS, gt=0, le=MAX_FIT_SECONDS, description="optimisation time budget; capped by the server")
    grain: Literal["x", "y", "auto"] | None = Field(
        "auto", description="anisotropic exemplar (wood, brushed metal): the direction its grain runs in the photo, "
                            "x = left-right, y = up-down; the fitted solid's noise cells are stretched 8x along "
                            "that axis (16x for a strong grain: gradients >= 9x) so tiles keep the grain in the "
                            "photo's orientation. auto (default): "
                            "detected from the photo (luminance gradients >= 3x stronger across one axis than "
                            "along it at 1, 2 and 4 px, or so on the photo turned by its main orientation); "
                            "a grain leaning 3 to 45 degrees off the nearer axis is straightened first. null: "
                            "isotropic")
    lattice: Literal["auto"] | None = Field(
        "auto", description="regular exemplar (bricks, tile grids, perforated metal): auto (default) detects the "
                            "2D lattice the photo repeats on (two independent autocorrelation peaks >= 0.3 "
                            "spanning a lattice whose other points show peaks too; a weak one gives way to "
                            "grain), else on a photo with grain its boards (the luminance averaged along the "
                            "grain repeating across it: plank floors, decking, planks of uneven width at their "
                            "mean width; they keep their grain), on one without stripes (corrugation) or rows "
                            "seen in the luminance averaged along them (crop rows, brick courses), and where "
                            "nothing was found, large cells (tiles over a third of the photo: 2 to 3 across, "
                            "looked for up to half of it) or a module grid (slabs of several sizes on one "
                            "module), and the fitted sampler, its shader and its tileable twin also read each "
                            "point's phase on it, so tiles show rows, grids and board joints (read on the photo "
                            "with its smooth shading divided out). null: off")
    even: Literal["auto"] | None = Field(
        "auto", description="auto (default): a photo with no grain or lattice that is even at large scales (its "
                            "32-px block means vary by under 3% of its luminance variance: gravel, asphalt, "
                            "fine grass) is fitted with the noise octaves of 32 px cells and coarser muted, so "
                            "its tiles keep no blotches the photo lacks; the fit still ends on its unmuted start "
                            "when none of its muted states scores better. null: never muted")
    lean: Literal["auto"] | None = Field(
        "auto", description="auto (default): a photo with no grain or lattice is fitted with a learned linear map "
                            "of the plane (x, y) that starts at the photo's lean: the direction its features run "
                            "and how much longer they are along it (from its luminance structure tensor: the "
                            "validation granite, 1.26x along -39 degrees), so tiles lean as the photo does. "
                            "null: never")
    detail_seconds: float = Field(DETAIL_SECONDS, ge=0, le=MAX_DETAIL_SECONDS, description=(
        "a photo at least twice the working size (512 px and up on its short side): seconds of a detail stage after the fit, which learns finer noise octaves on the photo at up to 4x the working size (1024 px) while the fit itself stays as it was; tiles and images above the native zoom 6 (zoom 7 for a 512 px photo, up to 8 for 1024 px: one pixel per photo pixel) are drawn with them, at and below zoom 6 without. Kept only where it beats the fit on the photo at that size. 0: none. An upload's automatic refinement uses the server's TEXSPACE_REFINE_DETAIL_SECONDS (default 20), and only when no other fit waits for the lane as its fit ends"))


class FitParams(FitIn):
    """A fit job's stored parameters: the request, plus ``in_place`` for an upload's
    automatic refinement (the texture itself then serves the result)."""
    in_place: bool = False


# auto: triplanar for a texture fitted on a 2D repeat lattice (its pattern lies in xy only;
# worker/triplanar.py), the solid texture itself for every other
BAKE_PROJECTIONS = ("auto", *PROJECTIONS)


def bake_projection(requested: str, structure: dict | None) -> str:
    """The projection a bake uses: ``requested``, or for "auto" what suits the texture's
    ``structure`` (the served sampler's, as ``TextureOut.structure`` shows it)."""
    if requested != "auto":
        return requested
    return "triplanar" if structure and structure.get("lattice") else "solid"


DDS_COMPRESSION_HELP = ("a DDS's blocks: bc1 (the default: BC1, 4 bits a texel, BC3 where a texel is not "
                        "opaque, in the legacy header every DDS reader knows) or bc7 (8 bits a texel, about "
                        "half BC1's error; DX10 header, DXGI_FORMAT_BC7_UNORM_SRGB: Debian 12's Blender 3.4, "
                        "ImageMagick 6 and iinfo 2.4 cannot read it, docs/API.md)")

NORMAL_STRENGTH_HELP = ("normal map: how many pixels the height map's full range rises (its gradient times this); "
                        "the default gives a mean |xy| of 0.14-0.46 (median 0.25) on the validation photos")


class BakeParams(BaseModel):
    """A bake job's stored parameters (the multipart form's fields, validated by the route)."""
    model_config = {"extra": "forbid"}
    resolution: int
    seed: int
    scale: float | None = None
    unit_m: float | None = None
    format: Literal[BAKE_FORMATS] = "glb"
    filename: str = "mesh.obj"
    maps: list[Literal[MAP_NAMES]] = []
    gpu_format: Literal[GPU_FORMATS] | None = None
    dds_compression: Literal[DDS_COMPRESSIONS] = "bc1"
    normal_strength: float = DEFAULT_NORMAL_STRENGTH
    projection: Literal[BAKE_PROJECTIONS] = "auto"
    after_refinement: bool = False


RASTER_LIMIT = COORD_LIMIT * MAX_TILE_SIZE  # the raster window worker/tiles.py renders exactly


class RegionIn(BaseModel):
    """A large 2D export of the infinite plane, rendered by a job."""

    model_config = {"extra": "forbid"}
    after_refinement: bool = Field(
        False, description="if the texture's refinement may still replace its sampler (it is queued or running), "
                           "wait for it to end and render with the refined sampler; false: render now with what the "
                           "texture serves (the job's sampler says which)")
    z: int = Field(ge=MIN_ZOOM, le=MAX_ZOOM, description="zoom level, as for tiles")
    x0: int = Field(ge=-RASTER_LIMIT, le=RASTER_LIMIT, description="first raster column at zoom z")
    y0: int = Field(ge=-RASTER_LIMIT, le=RASTER_LIMIT, description="first raster row at zoom z")
    width: int = Field(ge=1, le=16384)
    height: int = Field(ge=1, le=16384)
    seed: Seed = 0
    plane: Literal[PLANES] = "xy"
    offset: float = Field(0.0, ge=-1e9, le=1e9)
    format: Literal[REGION_FORMATS] = Field(
        "png", description="png: 8-bit sRGB; tiff: scanline 16-bit sRGB; exr: tiled half linear; pyramid: zip of "
                           "{z}/{x}/{y}.png tiles from min_zoom to z plus tilejson.json; dds: BC1 (legacy DXT1 "
                           "header) or BC7 (DX10 header, dds_compression); ktx2: Basis Universal UASTC + Zstandard; GPU textures with the full mip chain (averaged in linear light)")
    dds_compression: Literal[DDS_COMPRESSIONS] = Field("bc1", description=DDS_COMPRESSION_HELP + "; format dds only")
    size: int = Field(256, ge=MIN_TILE_SIZE, le=MAX_TILE_SIZE, description="pyramid tile size")
    min_zoom: int | None = Field(None, ge=MIN_ZOOM, le=MAX_ZOOM,
                                 description="pyramid: lowest zoom, at most z (default: the minimum zoom)")
    maps: list[Literal[MAP_NAMES]] = Field(
        default_factory=list, max_length=len(MAP_NAMES),
        description="derived maps to add (not with pyramid): height = linear luminance stretched to the 16-bit "
                    "range (result.height_range), normal = tangent-space from its gradient, OpenGL convention "
                    "(+Y up), roughness and ao = estimates. The result is then a zip of <stem>_basecolor.<ext> "
                    "and <stem>_<map>.png for each")
    normal_strength: float = Field(DEFAULT_NORMAL_STRENGTH, gt=0, le=MAX_NORMAL_STRENGTH,
                                   description=NORMAL_STRENGTH_HELP)
    tileable: bool = Field(
        False, description="a seamlessly tiling image: square (width = height), plane xy, one image (not "
                           "pyramid), any zoom (above the native 6, the same period's worth of texture in more "
                           "pixels); the texture is made periodic with the image's side at its zoom as its period (each octave's frequency rounded to whole cells per period: "
                           "coarse octaves change most, and small images most). A normal map then wraps too")

    @model_validator(mode="after")
    def _within_raster(self) -> RegionIn:
        if max(abs(self.x0 + self.width), abs(self.y0 + self.height)) > RASTER_LIMIT:
            raise ValueError(f"the region must stay within +-{RASTER_LIMIT} raster pixels")
        if self.min_zoom is not None and self.min_zoom > self.z:
            raise ValueError(f"min_zoom {self.min_zoom} is above z {self.z}")
        if self.maps and self.format == "pyramid":
            raise ValueError("derived maps come with a single image, not a pyramid")
        if self.dds_compression != "bc1" and self.format != "dds":
            raise ValueError(f"dds_compression {self.dds_compression} applies to format dds only")
        if (self.maps or self.format in GPU_FORMATS) and self.width * self.height > MAX_WHOLE_PIXELS:
            raise ValueError(f"{', '.join(GPU_FORMATS)} and derived maps are limited to {MAX_WHOLE_PIXELS} pixels")
        return self


class JobResult(BaseModel):
    filename: str = Field(description="the download name: texture, kind, size, seed, tileable "
                                      "(oak-planks_region_z6_1024px_seed7.png)")
    media_type: str
    size: int
    scale: float | None = Field(None, description="a bake: the world units per mesh unit it used (given, fitted to "
                                                  "the mesh's bounds, or from unit_m and the texture's width_m)")
    texels_per_metre: float | None = Field(
        None, description="a bake at real size (unit_m): atlas texels per metre of the surface (the square root "
                          "of covered texels over its area in square metres)")
    height_range: list[float] | None = Field(
        None, min_length=2, max_length=2,
        description="with a height map: the [min, max] Rec. 709 linear luminance its 16-bit range 0..65535 "
                    "spans (height = min + value / 65535 * (max - min)); also in the PNG's "
                    "texspace:height_min / texspace:height_max text")


class JobLinks(BaseModel):
    self: str
    events: str
    cancel: str
    result: str | None
    texture: str | None
    output_texture: str | None


class JobSampler(BaseModel):
    kind: Literal["encoder", "interim", "fitted"] = Field(
        description="encoder: the model's sampler at the encoder's code; interim: a refinement's state part way; "
                    "fitted: a sampler fitted to the exemplar")
    version: str = Field(description="the model's version, and for a fitted or interim sampler its own (+fit.HASH)")
    refining: bool = Field(
        description="the texture's refinement may still replace this sampler: the job was (or will be) rendered "
                    "before it ended; submit with after_refinement to wait for it")
    waiting_for_refinement: bool = Field(
        False, description="queued until the texture's refinement ends (after_refinement)")


class JobOut(BaseModel):
    id: str
    kind: JobKind
    state: JobState
    texture_id: str | None
    params: dict[str, Any]
    progress: float = Field(ge=0, le=1)
    attempt: int
    max_attempts: int
    cancel_requested: bool
    worker_id: str | None = Field(None, description="host:pid of the worker holding (or last holding) the job")
    error: dict[str, Any] | None = Field(None, description="problem document of the failure")
    result: JobResult | None
    output_texture_id: str | None
    sampler: JobSampler | None = Field(
        None, description="what the job renders with: while queued, what its texture serves now; from its start, "
                          "what it used; null for fits")
    created_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None
    heartbeat_at: dt.datetime | None
    lease_expires_at: dt.datetime | None
    links: JobLinks

    @classmethod
    def of(cls, j: Job) -> "JobOut":
        base = f"/v1/jobs/{j.id}"
        done = j.state == JobState.SUCCEEDED and j.result_key
        return cls(id=j.id, kind=j.kind, state=j.state, texture_id=j.texture_id, params=j.params,
                   progress=j.progress, attempt=j.attempt, max_attempts=j.max_attempts,
                   cancel_requested=j.cancel_requested, worker_id=j.worker_id, error=j.error,
                   result=JobResult(filename=j.result_filename, media_type=j.result_media_type,
                                    size=j.result_size,
                                    height_range=(j.result_details or {}).get("height_range"),
                                    texels_per_metre=(j.result_details or {}).get("texels_per_metre"),
                                    scale=(j.result_details or {}).get("scale"))
                   if done else None,
                   output_texture_id=j.output_texture_id, created_at=j.created_at, started_at=j.started_at,
                   sampler=JobSampler(**j.sampler) if j.sampler else None,
                   finished_at=j.finished_at, heartbeat_at=j.heartbeat_at, lease_expires_at=j.lease_expires_at,
                   links=JobLinks(self=base, events=f"{base}/events", cancel=f"{base}/cancel",
                                  result=f"{base}/result" if done else None,
                                  texture=f"/v1/textures/{j.texture_id}" if j.texture_id else None,
                                  output_texture=f"/v1/textures/{j.output_texture_id}" if j.output_texture_id else None))


class JobPage(BaseModel):
    items: list[JobOut]
    next_cursor: str | None = None


class ModelOut(BaseModel):
    version: str
    variant: str
    loaded: bool
    default: bool
    pixels_per_unit: float | None
    manifest: dict[str, Any]


class ModelList(BaseModel):
    items: list[ModelOut]
    default: str | None


class Limits(BaseModel):
    """The limits in force on this server (``TEXSPACE_MAX_*`` and the fit budget), so that
    the page and clients read them instead of copying numbers."""

    max_upload_bytes: int = Field(description="bytes of an uploaded photo")
    max_image_pixels: int = Field(description="pixels of an uploaded photo, decoded")
    max_mesh_bytes: int = Field(description="bytes of a bake's mesh")
    max_mesh_faces: int
    max_mesh_vertices: int
    min_tile_size: int = Field(description="tile side in pixels")
    max_tile_size: int
    max_tile_samples: int = Field(description="sampler calls of one tile: (size x supersampling factor)^2")
    planes: list[Literal[PLANES]] = Field(description="the slice planes of tiles and regions")
    min_volume_resolution: int = Field(description="a volume's voxels per side")
    max_volume_resolution: int
    min_bake_resolution: int = Field(description="a bake's texture atlas side in pixels")
    max_bake_resolution: int
    max_region_pixels: int = Field(description="pixels of one region export")
    max_region_tiles: int = Field(description="tiles of one region pyramid")
    fit_seconds: float = Field(description="the time budget of a fit request that names none")
    max_fit_seconds: float = Field(description="the longest time budget a fit request may name")
    refinement_seconds: float = Field(description="the time budget of an upload's automatic refinement")
    formats: dict[str, list[str]] = Field(description="the formats each output offers (tile, volume, region, bake, "
                                                      "gpu_texture, shader), the default first")

    @classmethod
    def of(cls, settings: Settings) -> "Limits":
        """The limits ``settings`` set, with the bounds no setting can raise."""
        s = settings
        return cls(max_upload_bytes=s.max_upload_bytes, max_image_pixels=s.max_image_pixels,
                   max_mesh_bytes=s.max_mesh_bytes, max_mesh_faces=s.max_mesh_faces,
                   max_mesh_vertices=s.max_mesh_vertices, min_tile_size=MIN_TILE_SIZE, max_tile_size=s.max_tile_size,
                   max_tile_samples=s.max_tile_samples, planes=list(PLANES),
                   min_volume_resolution=MIN_VOLUME_RESOLUTION, max_volume_resolution=s.max_volume_resolution,
                   min_bake_resolution=MIN_BAKE_RESOLUTION, max_bake_resolution=s.max_bake_resolution,
                   max_region_pixels=s.max_region_pixels, max_region_tiles=s.max_region_tiles,
                   fit_seconds=FitIn.model_fields["seconds"].default, max_fit_seconds=s.max_fit_seconds,
                   refinement_seconds=min(s.fit_seconds, s.max_fit_seconds),
                   formats={output: list(names) for output, names in OFFERED.items()})


class TileJSON(BaseModel):
    tilejson: str = "3.0.0"
    name: str
    scheme: Literal["xyz"] = "xyz"
    tiles: list[str]
    minzoom: int
    maxzoom: int
    tileSize: int  # noqa: N815 - TileJSON spells it so
    bounds: list[float]
    center: list[float]  # [x, y, zoom]; zoom = the native zoom (one tile pixel = one exemplar pixel)


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = Field(default_factory=dict)
