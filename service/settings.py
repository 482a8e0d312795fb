"""All service configuration in one typed object, read from ``TEXSPACE_*`` variables.

Every process (api, worker, CLI) builds one :class:`Settings`; nothing else reads the
environment. Paths default to a ``./data`` folder so ``make run`` needs no set-up.
"""
from __future__ import annotations

import os
import re
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from worker.contract import (DETAIL_SECONDS, MAX_BAKE_RESOLUTION, MAX_TILE_SIZE, MAX_VOLUME_RESOLUTION,
                             MIN_BAKE_RESOLUTION, MIN_TILE_SIZE, MIN_VOLUME_RESOLUTION)

from .vocabulary import JobKind

#: a fit's time budget unless one is asked for: an upload's refinement and ``POST .../fit``.
#: 70 s on every core: as many steps as the 90-s one-thread fit before it, at the same style
#: error, so that four uploads at once have their finals in about 330 s instead of 420 s
#: (docs/DECISIONS.md, "An upload's fit is 70 s"). Fits have a queue of their own
#: (service/queue.py), so a longer one holds up no tile, volume or bake.
FIT_SECONDS = 70.0
#: the longest detail stage (model/detail.py) a fit job may ask for
MAX_DETAIL_SECONDS = 120.0
#: the longest fit any server may allow (``max_fit_seconds`` is its own limit, at most this)
MAX_FIT_SECONDS = 3600.0
#: the model export shipped inside the package (``model/weights``)
PACKAGED_MODEL_DIR = Path(__file__).resolve().parent.parent / "model" / "weights"


class Settings(BaseSettings):
    """Typed settings; each field is the env variable ``TEXSPACE_<FIELD>``."""

    model_config = SettingsConfigDict(env_prefix="TEXSPACE_", extra="ignore")

    # --- where things live ---------------------------------------------------------
    data_dir: Path = Field(Path("data"), description="root of the SQLite db, queue and local storage")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    database_url: str | None = Field(None, description="SQLAlchemy URL; default SQLite (WAL) under data_dir")

    # --- queue -----------------------------------------------------------------------
    queue_backend: Literal["sqlite", "redis", "postgres", "memory"] = "sqlite"
    queue_url: str | None = Field(None, description="redis:// or postgresql:// URL of the queue broker")
    queue_name: str = "texspace"

    # --- storage ---------------------------------------------------------------------
    storage_backend: Literal["local", "s3"] = "local"
    storage_dir: Path | None = Field(None, description="local storage root; default data_dir/storage")
    s3_endpoint_url: str | None = None
    s3_bucket: str = "texspace"
    s3_prefix: str = ""
    s3_access_key: str | None = None
    s3_secret_key: str | None = None
    s3_region: str = "us-east-1"
    min_free_bytes: int = Field(64 * 2**20, ge=0, description="/readyz answers 503 when the data folder's "
                                "volume, or the local storage folder's, has less free space than this (0: not checked)")

    # --- models ----------------------------------------------------------------------
    model_dirs: Annotated[list[Path], NoDecode] = Field(
        default_factory=lambda: [PACKAGED_MODEL_DIR],
        description="model export folders (or folders of them), separated by the OS path separator",
    )
    default_model_version: str | None = Field(None, description="new uploads use this model; default: newest export")

    # --- limits (checked while streaming uploads and before queueing work) -----------
    max_upload_bytes: int = Field(64 * 2**20, ge=1024)
    max_image_pixels: int = Field(64 * 2**20, ge=64 * 64)
    max_mesh_bytes: int = Field(64 * 2**20, ge=1024)
    max_mesh_faces: int = Field(200_000, ge=1)
    max_mesh_vertices: int = Field(200_000, ge=3)
    max_mesh_nodes: int = Field(4096, ge=1, description="nodes of a GLB's scene, and its mesh primitives (each "
                                "costs the flattening ~0.3 ms: 4,096 about 1 s)")
    max_mesh_depth: int = Field(64, ge=1, description="levels of a GLB's node tree")
    max_tile_size: int = Field(MAX_TILE_SIZE, ge=MIN_TILE_SIZE, le=MAX_TILE_SIZE)
    max_tile_samples: int = Field(4 * 2**20, ge=64 * 64, description="sampler calls of one tile: "
                                  "(size x supersampling factor)^2, the factor 2^(6 - z) capped at 4")
    decode_budget_pixels: int = Field(64 * 2**20, ge=64 * 64, description="pixels the API's decoded "
                                      "uploads may hold together; a decode waits for room")
    decode_wait_seconds: float = Field(30.0, gt=0, description="an upload waits at most this long for "
                                       "room in the decode budget, then gets 503 + Retry-After")
    decode_max_waiting: int = Field(4, ge=0, description="uploads that may wait for decode room at once "
                                    "(each holds a thread and its bytes); one more gets 503 + Retry-After")
    max_region_pixels: int = Field(64 * 2**20, ge=64 * 64)
    max_region_tiles: int = Field(4096, ge=1)
    max_volume_resolution: int = Field(256, ge=MIN_VOLUME_RESOLUTION, le=MAX_VOLUME_RESOLUTION)
    max_bake_resolution: int = Field(4096, ge=MIN_BAKE_RESOLUTION, le=MAX_BAKE_RESOLUTION)
    atlas_cache_dir: Path | None = Field(None, description="UV atlases of baked meshes, per mesh content, so a "
                                         "second bake of a mesh skips xatlas; default data_dir/cache/atlas")
    atlas_cache_bytes: int = Field(512 * 2**20, ge=0, description="size bound of atlas_cache_dir (least "
                                   "recently used entries go first); 0 disables the cache")
    fit_seconds: float = Field(FIT_SECONDS, gt=0, description="time budget of an upload's automatic refinement")
    max_fit_seconds: float = Field(900.0, gt=0, le=MAX_FIT_SECONDS)

    # --- jobs --------------------------------------------------------------------------
    workers: int = Field(2, ge=1, description="huey worker threads per worker process")
    worker_nice: int = Field(10, ge=0, le=19, description="niceness a worker process adds to itself at start: "
                             "jobs are batch work and yield the CPU to the API's tiles")
    lease_seconds: float = Field(30.0, gt=0)
    heartbeat_seconds: float = Field(1.0, gt=0)
    reaper_interval_seconds: float = Field(5.0, gt=0)
    requeue_after_seconds: float = Field(120.0, gt=0, description="re-send queued jobs whose message was lost")
    max_attempts: int = Field(3, ge=1)
    max_queued_jobs: int = Field(1000, ge=1, description="back-pressure: submissions beyond this many "
                                 "queued jobs get 503 + Retry-After")
    max_queued_fits: int = Field(100, ge=1, description="back-pressure on the fit lane, counted apart from the "
                                 "other jobs: uploads beyond this many queued fits defer their refinement (queued as "
                                 "room frees), fit requests get 503 + Retry-After")
    tenant_queue_share: float = Field(0.5, gt=0, le=1, description="the share of max_queued_jobs and of "
                                      "max_queued_fits one tenant (API key) may fill, with API keys on: beyond it 429 + "
                                      "Retry-After, an upload's refinement deferred")
    queue_full_retry_after_seconds: int = Field(30, ge=1)
    worker_kinds: Annotated[list[JobKind], NoDecode] = Field(
        default_factory=lambda: list(JobKind), description="job kinds this worker process runs, comma-separated; "
        "fits have a queue of their own (volume, bake and region share the other: list all three or none)")

    # --- per-exemplar fits (the train extra) ------------------------------------------
    auto_fit: bool = Field(True, description="refine every upload in place with a fit job; effective where "
                           "torch is installed on the API and the model ships its space.pt")
    fit_threads: int = Field(0, ge=0, description="torch threads of a fit job (0: torch's default, every core; the "
                             "worker's niceness gives tiles the cores first)")
    fit_device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="where a fit job's steps run: auto takes the worker's CUDA GPU when torch sees one")
    fit_precision: Literal["auto", "bf16", "fp32"] = Field(
        "auto", description="arithmetic of a fit's VGG loss and decoder: auto is bfloat16 on CUDA and on CPUs "
        "with native bfloat16 (AVX-512 BF16, AMX), float32 elsewhere")
    refine_detail_seconds: float = Field(
        DETAIL_SECONDS, ge=0, le=MAX_DETAIL_SECONDS, description="an upload's automatic refinement: seconds of the "
        "detail stage after its fit (model/detail.py: finer octaves for photos of 512 px and up, drawn above the "
        "native zoom), run only when no other fit waits for the lane then, so uploads queued together get their "
        "final samplers as soon as without it; 0: none; a fit job asks for its own")
    fit_interim_seconds: float = Field(
        10.0, ge=0, description="an upload's refinement serves its fit's best state this many seconds in (if it "
        "beats the encoder's code by then, or is its start with a lattice, grain or lean built in), until the "
        "finished fit replaces it; 0: only the finished fit")

    # --- HTTP ----------------------------------------------------------------------------
    tile_cache_bytes: int = Field(64 * 2**20, ge=0)
    tile_linear_cache_bytes: int = Field(64 * 2**20, ge=0, description="linear-light copies of recent tiles "
                                         "at and one zoom out from native, from which zoomed-out parents are "
                                         "built without sampling (0: off)")
    upload_encodes: int = Field(2, ge=1, description="uploads one API process decodes and encodes at once "
                                "(about a second of CPU each at 1024^2); 4 per slot may wait up to 30 s, then "
                                "503 busy + Retry-After")
    tile_workers: int = Field(2, ge=1, description="cold tiles one API process renders at once (each over "
                              "the sampler's threads); the others wait in order")
    tile_queue_depth: int = Field(64, ge=0, description="cold tiles that may wait for a render, in units "
                                  "of a 256 px native tile's samples (a 512 px tile is 4); beyond, 503 + Retry-After")
    tile_queue_max_wait_seconds: float = Field(2.0, gt=0, description="a cold tile whose estimated wait "
                                               "for a render is longer gets 503 + Retry-After at once")
    tile_zoom_out: Literal["progressive", "supersample", "bounded"] = Field(
        "progressive", description="zoomed-out tiles: 'supersample' averages every sub-sample (children "
        "downsampled equal the parent; cost x4 per level, capped at x16); 'bounded' evaluates one hashed "
        "sub-sample per pixel (a native tile's cost at every zoom; equal to the parent in expectation); "
        "'progressive' answers a cold zoomed-out tile with the bounded one as a preview (no-cache, header "
        "X-Texspace-Tile: preview) and renders the supersampled one behind it, served from then on")
    http_read_timeout_seconds: float = Field(60.0, gt=0, description="a request's headers and body must "
                                             "arrive within this long of the connection opening or "
                                             "of the request's first byte")
    http_keep_alive_seconds: float = Field(5.0, gt=0, description="idle keep-alive connections close after")
    http_limit_concurrency: int = Field(256, ge=1, description="connections + running requests of one API "
                                        "process; beyond, 503")
    public_base_url: str | None = Field(None, description="scheme://host[:port][/prefix] clients reach the API "
                                        "at; tilejson's tile URLs use it (default: the request's own URL)")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="origins (scheme://host[:port]) whose pages may call the API "
        "(tiles, jobs) from a browser, comma-separated; * for any; empty: CORS off")
    api_keys_enabled: bool = False
    api_key_pepper: str = Field("texspace-dev-pepper", description="server-side secret mixed into "
                                "API key hashes; set your own in production")
    rate_limit_per_minute: float = Field(600.0, gt=0, description="requests per API key per minute "
                                         "(each API process), when API keys are enabled")
    rate_limit_burst: int = Field(60, ge=1)
    log_level: str = "INFO"
    log_json: bool = True

    @field_validator("model_dirs", mode="before")
    @classmethod
    def _split_dirs(cls, value: object) -> object:
        if isinstance(value, str):
            return [Path(p) for p in value.split(os.pathsep) if p.strip()]
        return value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            return [o.strip().rstrip("/") for o in value.split(",") if o.strip()]
        return value

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, value: list[str]) -> list[str]:
        for origin in value:
            if origin != "*" and not re.fullmatch(r"https?://[^/\s?#]+", origin):
                raise ValueError(f"{origin!r} is not an origin: scheme://host[:port] (no path), or *")
        return value

    @field_validator("worker_kinds", mode="before")
    @classmethod
    def _split_kinds(cls, value: object) -> object:
        if isinstance(value, str):
            return [k.strip() for k in value.split(",") if k.strip()]
        return value

    @field_validator("worker_kinds")
    @classmethod
    def _whole_queues(cls, value: list[JobKind]) -> list[JobKind]:
        shared = set(JobKind) - {JobKind.FIT}  # one queue carries these (service/queue.py)
        if not value:
            raise ValueError("name at least one job kind")
        if 0 < len(shared & set(value)) < len(shared):
            raise ValueError(f"{', '.join(sorted(shared))} share one queue: list all of them or none")
        return list(dict.fromkeys(value))

    @cached_property
    def resolved_database_url(self) -> str:
        """The database URL in force (the SQLite default lives under data_dir)."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'texspace.db').resolve()}"

    @cached_property
    def resolved_atlas_cache_dir(self) -> Path | None:
        """Where bakes cache UV atlases (None: no cache)."""
        if self.atlas_cache_bytes == 0:
            return None
        return (self.atlas_cache_dir or self.data_dir / "cache" / "atlas").resolve()

    @cached_property
    def resolved_storage_dir(self) -> Path:
        return (self.storage_dir or self.data_dir / "storage").resolve()

    def ensure_dirs(self) -> None:
        """Create the data folder (SQLite database, SQLite queue, local storage)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if self.storage_backend == "local":
            self.resolved_storage_dir.mkdir(parents=True, exist_ok=True)
