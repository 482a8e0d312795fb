"""The services container: the long-lived things every process needs.

:class:`Services` holds the database engine and session factory, storage, the huey
queue and the model registry (loaded lazily so the API starts and answers ``/readyz``
honestly even while a model export is missing). It sits at the bottom of the service's
imports: domain modules (auth, jobs, limits, purge, job_kinds) take it from here, and
:func:`service.context.build_services` fills it in from the settings.
"""
from __future__ import annotations

import hashlib
import os
import socket
import threading
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import Engine, select
from sqlalchemy.orm import Session, sessionmaker

from worker.errors import FeatureUnavailable

from . import db
from .keys import detail_key, tileable_key
from .metrics import Metrics
from .queue import lane_of
from .settings import Settings
from .storage import Storage
from .tables import ModelVersion, Texture
from .tilecache import TileCache


@dataclass
class Services:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    storage: Storage
    huey: object  # the main lane: volume, bake and region jobs (queue.lane_of)
    run_job: object = None  # huey task wrapper: run_job(job_id) enqueues
    fit_huey: object = None  # the fit lane: fits, minutes of torch each
    run_fit_job: object = None
    metrics: Metrics = field(default_factory=Metrics)
    tile_cache: TileCache | None = None
    upload_slots: object = None  # limits.CpuSlots: uploads decoded and encoded at once (upload_encodes)
    worker_id: str = field(default_factory=lambda: f"{socket.gethostname()}:{os.getpid()}")
    # set when this worker process begins to stop: it claims nothing from then on
    stopping: threading.Event = field(default_factory=threading.Event)
    _registry: object | None = None
    # detail sampler keys storage does not hold (a key names one attempt's files, which never change)
    _no_detail: set[str] = field(default_factory=set)
    _registry_lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def registry(self):  # -> worker.runtime.ModelRegistry
        """The model registry, loaded on first use (raises ModelNotFound if no export exists)."""
        if self._registry is None:
            with self._registry_lock:
                if self._registry is None:
                    from worker.runtime import ModelRegistry

                    registry = ModelRegistry(self.settings.model_dirs,
                                             default=self.settings.default_model_version)
                    self._record_models(registry)
                    self._registry = registry
        return self._registry

    def _record_models(self, registry) -> None:  # noqa: ANN001
        """Remember every loaded model version in the ``models`` table."""
        with db.session_scope(self.sessions) as session:
            known = set(session.scalars(select(ModelVersion.version)))
            for version, runtime in registry.models.items():
                if version not in known:
                    session.add(ModelVersion(version=version, variant=str(runtime.manifest["variant"]),
                                             manifest=runtime.manifest))

    def task_for(self, kind: str | None):  # -> huey task wrapper
        """The task wrapper of the lane that carries ``kind`` jobs: calling it enqueues."""
        return self.run_fit_job if lane_of(kind) == "fit" and self.run_fit_job else self.run_job

    def pending_count(self) -> int:
        """Messages waiting in the broker, over both lanes."""
        return sum(int(h.pending_count()) for h in (self.huey, self.fit_huey) if h is not None)

    def sampler_path(self, texture_id: str, sampler_key: str) -> Path:
        """Local copy of a texture's own sampler, named by its storage key: a refinement
        stores a new key, so a copy of an earlier sampler is never served for it."""
        digest = hashlib.sha256(sampler_key.encode()).hexdigest()[:16]
        return self.cache_dir / "samplers" / f"{texture_id}-{digest}.onnx"

    def cached_samplers(self, texture_id: str) -> list[Path]:
        """Every local sampler copy of ``texture_id`` (``sampler_path``), to remove with it."""
        return list((self.cache_dir / "samplers").glob(f"{texture_id}*.onnx"))

    def stored_sampler(self, texture: Texture, key: str):  # -> worker.runtime.SamplerSession
        """The sampler stored under ``key`` for ``texture``, from its local copy (``sampler_path``),
        downloaded on first use."""
        cached = self.sampler_path(texture.id, key)
        if not cached.is_file():
            self.storage.get_file(key, cached)
        return self.registry.fitted_sampler(cached)

    def sampler_for(self, texture: Texture):  # -> worker.runtime.Sampler
        """The sampler that renders ``texture``: its own fitted one, or its model's."""
        if texture.sampler_key:
            return self.stored_sampler(texture, texture.sampler_key)
        return self.registry.get(texture.model_version)

    def tileable_available(self, texture: Texture) -> str | None:
        """None if ``texture`` can render tileable regions, else why not (the fix to make)."""
        if texture.sampler_key:
            if self.storage.exists(tileable_key(texture.sampler_key)):
                return None
            return (f"texture {texture.id} has a fitted sampler without a tileable twin: it was fitted before "
                    "tileable textures existed (or, on a repeat lattice, before lattice fits got one); refit it "
                    f"(POST /v1/textures/{texture.id}/fit) to get one")
        if self.registry.get(texture.model_version).tileable_path is None:
            return (f"model {texture.model_version} has no tileable sampler: it was exported before "
                    "tileable textures; re-export it (python -m model.export)")
        return None

    def tileable_sampler_for(self, texture: Texture):  # -> worker.runtime.SamplerSession
        """The tileable sampler (``period`` input) of ``texture``: the one stored beside its
        fitted sampler, or its model's. FeatureUnavailable if it has none."""
        if not texture.sampler_key:
            return self.registry.get(texture.model_version).tileable_sampler()
        key = tileable_key(texture.sampler_key)
        if not self.sampler_path(texture.id, key).is_file() and not self.storage.exists(key):
            raise FeatureUnavailable(self.tileable_available(texture) or f"no tileable sampler at {key}")
        return self.stored_sampler(texture, key)

    def detail_sampler_for(self, texture: Texture, tileable: bool = False):  # -> SamplerSession | None
        """The detail sampler (finer octaves learned on the photo above the working size,
        model/detail.py), or its tileable twin, stored beside ``texture``'s fitted sampler, or None
        where its fit has none."""
        if not texture.sampler_key:
            return None
        key = detail_key(texture.sampler_key, tileable)
        if not self.sampler_path(texture.id, key).is_file():
            if key in self._no_detail:
                return None
            if not self.storage.exists(key):
                self._no_detail.add(key)
                return None
        return self.stored_sampler(texture, key)

    def pixels_per_unit(self, texture: Texture) -> float:
        """World scale of the texture's model (fitted samplers share their parent's)."""
        return self.registry.get(texture.model_version).pixels_per_unit

    @property
    def cache_dir(self) -> Path:
        path = (self.settings.data_dir / "cache").resolve()
        path.mkdir(parents=True, exist_ok=True)
        return path

    @property
    def work_dir(self) -> Path:
        """Scratch space for jobs (inputs downloaded, outputs before upload)."""
        path = (self.settings.data_dir / "work").resolve()
        path.mkdir(parents=True, exist_ok=True)
        return path
