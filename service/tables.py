"""Database tables (SQLAlchemy 2 declarative). Alembic migrations mirror this file.

The job row is the truth about every job (docs/ARCHITECTURE.md, Contract 3); the queue only
carries job ids.
"""
from __future__ import annotations

import datetime as dt
import uuid
from typing import Any

from sqlalchemy import JSON, Boolean, DateTime, Float, Integer, String, Text, TypeDecorator, false
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from .vocabulary import JobState


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def new_id() -> str:
    """A random 32-hex-digit id (textures and jobs)."""
    return uuid.uuid4().hex


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend (SQLite forgets the zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect: Any) -> dt.datetime | None:
        if value is not None and value.tzinfo is not None:
            value = value.astimezone(dt.timezone.utc)
            if dialect.name == "sqlite":
                value = value.replace(tzinfo=None)
        return value

    def process_result_value(self, value: dt.datetime | None, dialect: Any) -> dt.datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=dt.timezone.utc)
        return value


class Base(DeclarativeBase):
    pass


class ModelVersion(Base):
    """One exported model (encoder + sampler) the service has loaded at least once."""

    __tablename__ = "models"

    version: Mapped[str] = mapped_column(String(64), primary_key=True)
    variant: Mapped[str] = mapped_column(String(32))
    manifest: Mapped[dict] = mapped_column(JSON)
    registered_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class Texture(Base):
    """A texture: a code in one model's latent space (plus, after a fit, its own sampler)."""

    __tablename__ = "textures"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), default="")
    code: Mapped[list] = mapped_column(JSON)
    model_version: Mapped[str] = mapped_column(String(64), index=True)
    source: Mapped[str] = mapped_column(String(16), default="upload")  # upload | interpolate | fit
    parents: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    exemplar_key: Mapped[str | None] = mapped_column(String(300), nullable=True)
    exemplar_media_type: Mapped[str | None] = mapped_column(String(100), nullable=True)
    width: Mapped[int | None] = mapped_column(Integer, nullable=True)
    height: Mapped[int | None] = mapped_column(Integer, nullable=True)
    sampler_key: Mapped[str | None] = mapped_column(String(300), nullable=True)
    owner_id: Mapped[str | None] = mapped_column(String(32), nullable=True, index=True)  # the API key id; NULL when keys are disabled
    # An upload's in-place refinement (TEXSPACE_AUTO_FIT): the fit job, and the encoder's code
    # in the model's latent space, kept when the job replaces code and sampler_key (blends use it).
    refinement_job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    # The params of a refinement not yet queued, because the fit lane's queue or the owner's
    # share of it was full at upload (``jobs.queue_deferred_refinements`` queues it as room
    # frees, oldest upload first); None once queued, or when none was deferred.
    # The photo's real width in metres, if the uploader said (bakes at real size: unit_m).
    width_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    refinement_deferred: Mapped[dict | None] = mapped_column(JSON(none_as_null=True), nullable=True)  # None: SQL NULL
    encoder_code: Mapped[list | None] = mapped_column(JSON, nullable=True)
    # The colour table the sampler applies last (worker/colour_match.py): the photo's colour
    # statistics matched to this texture's sampler. None: the identity table (rows from
    # before colour tables, and samplers without a colour stage). encoder_colour is the
    # table of encoder_code with the model's sampler, kept with it when a refinement replaces both.
    colour: Mapped[list | None] = mapped_column(JSON, nullable=True)
    encoder_colour: Mapped[list | None] = mapped_column(JSON, nullable=True)
    # The recipe both tables were made by (worker.colour_match.COLOUR_CALIBRATION); None:
    # an older one, from before it was recorded. ``texspace recolour`` updates stale rows.
    colour_calibration: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # The recipe an upload's code was chosen by (worker.encode.CODE_CHOICE; 1 the crops' mean);
    # None: not an upload's encoder code, or from before it was recorded (the mean). ``texspace
    # reencode --stale-codes`` chooses stale uploads' codes again.
    code_choice: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # What the fitted sampler was built with (model.fit): {"grain": "x" | "y" | None,
    # "straightened": degrees the photo was turned (absent in rows from before),
    # "grain_stretch": 8 | 16 | None (absent in rows from before: 8 with a grain),
    # "muted_octaves": n (absent in rows from before: 0),
    # "lean": [degrees, stretch] | None (absent in rows from before: None),
    # "lattice": [ax, ay, bx, by] world units | None}. None for the encoder's code.
    structure: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    # How its photo is taken when encoded or fitted (worker.photo.LIGHTING): "as-is", or
    # "even" (its smooth shading divided out). The stored photo itself is never changed.
    lighting: Mapped[str] = mapped_column(String(8), default="as-is", server_default="as-is")
    # True while sampler_key is the interim a running refinement published part way through
    # its fit (the best state after TEXSPACE_FIT_INTERIM_SECONDS): its final sampler replaces it.
    sampler_interim: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow, index=True)
    updated_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)

    def refinement_may_replace_sampler(self) -> bool:
        """True while an in-place refinement may still give this texture another sampler: it
        has one queued or running (``jobs.refinement_pending`` asks its job) and serves the encoder's code
        or the refinement's interim; False once it serves a final fitted sampler, or has none."""
        return bool(self.refinement_job_id) and (not self.sampler_key or self.sampler_interim)

    def served_structure(self) -> dict | None:
        """What the sampler it serves was fitted with (grain, repeat lattice); None when it
        serves its model's sampler (a re-encode keeps no stale structure either)."""
        return self.structure if self.structure and self.sampler_key else None

    def model_space(self) -> tuple[list, list | None] | None:
        """The code and colour table for its model's own sampler, what blends mix: a refined
        upload's kept encoder values, any other texture's own; None for a fit's new texture,
        which only its own sampler can draw."""
        if self.encoder_code is not None:
            return self.encoder_code, self.encoder_colour
        if self.sampler_key:
            return None
        return self.code, self.colour


def blend_calibration(*parents: Texture) -> int | None:
    """The colour recipe of a blend's tables: its parents' oldest (None if any is unknown)."""
    recipes = [p.colour_calibration for p in parents]
    return None if None in recipes else min(recipes)


class Job(Base):
    """A long-running job (volume, bake, fit, region): the single source of truth."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    kind: Mapped[str] = mapped_column(String(16))  # a JobKind
    texture_id: Mapped[str | None] = mapped_column(String(32), index=True, nullable=True)
    state: Mapped[str] = mapped_column(String(16), default=JobState.QUEUED, index=True)  # a JobState
    params: Mapped[dict] = mapped_column(JSON, default=dict)
    input_key: Mapped[str | None] = mapped_column(String(300), nullable=True)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    worker_id: Mapped[str | None] = mapped_column(String(100), nullable=True)
    lease_expires_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True, index=True)
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    enqueued_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    error: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    result_key: Mapped[str | None] = mapped_column(String(300), nullable=True)
    result_filename: Mapped[str | None] = mapped_column(String(200), nullable=True)
    result_media_type: Mapped[str | None] = mapped_column(String(100), nullable=True)
    result_size: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # {"height_range": [min, max]}: a height map's luminance range (migration 0010)
    result_details: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    output_texture_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    # "interim": an upload's fit paused at its interim's second, waiting for its continuation
    stage: Mapped[str | None] = mapped_column(String(16), nullable=True)
    # what it synthesised with: {"kind": "encoder" | "interim" | "fitted", "version", "key"}
    sampler: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    idempotency_key: Mapped[str | None] = mapped_column(String(200), unique=True, nullable=True)
    request_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    owner_id: Mapped[str | None] = mapped_column(String(32), nullable=True, index=True)  # the API key id; NULL when keys are disabled
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow, index=True)
    started_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    updated_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)


class ApiKey(Base):
    """API keys: tenants. Only a hash of the key is stored."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    key_hash: Mapped[str] = mapped_column(String(128), unique=True)
    note: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
