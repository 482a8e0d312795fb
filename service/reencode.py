"""Move textures onto another model: ``texspace reencode``.

A texture is drawn by the model that encoded it, so a model that is no longer loaded
(retired from ``TEXSPACE_MODEL_DIRS``) leaves its textures answering 503. Re-encoding
gives each one a code in the target model's space from the photo it keeps:

- a texture with an exemplar (uploads, fits' own textures) is encoded again, exactly as
  an upload is, and loses what was fitted in the old space (those sampler files are
  deleted); where refinement runs (``TEXSPACE_AUTO_FIT``), a new one is queued;
- a blend (``POST /v1/textures/interpolate``) is mixed again from its two parents' new
  codes, once both are on the target model;
- anything else (a blend whose parent was deleted) stays and is reported.

Tiles change (the model, and so the ETag, is new). Run it with the workers idle: a
refinement still running for the old model would fail anyway.

``--stale-codes`` (``choose_codes_again``) re-encodes in place instead: uploads on a loaded
model whose code was chosen by an older recipe (``worker.encode.CODE_CHOICE``; the
``code_choice`` column) get the code an upload of their photo gets today, on the same model.
A refined upload keeps its fitted sampler and what it serves; the new code replaces the
encoder's code it keeps for blends. Blends of such uploads are mixed again.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

from sqlalchemy import and_, false, func, or_, select
from sqlalchemy.orm import load_only

from worker.colour_match import COLOUR_CALIBRATION, blend_textures
from worker.encode import MEAN_CHOICE, choice_recipe, encode_texture
from worker.images import read_image

from . import jobs, keys
from .db import session_scope
from .job_kinds import auto_fit_params
from .tables import Texture, blend_calibration, new_id, utcnow

log = logging.getLogger(__name__)


@dataclass
class ReencodeReport:
    """What one run did (or, with ``dry_run``, would do), by texture id."""

    target: str
    encoded: list[str] = field(default_factory=list)
    blended: list[str] = field(default_factory=list)
    refinements: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # id -> why


def stale_textures(services, versions: set[str] | None = None) -> list[Texture]:  # noqa: ANN001
    """Textures of ``versions``, or (None) of every model that is not loaded; oldest first.
    Only the columns that decide what to do are loaded (not codes and colour tables: a
    database of a million textures fits in memory this way)."""
    loaded = set(services.registry.models)
    query = (select(Texture).order_by(Texture.created_at, Texture.id)
             .options(load_only(Texture.id, Texture.model_version, Texture.source, Texture.parents,
                                Texture.exemplar_key, Texture.sampler_key, Texture.lighting, Texture.created_at)))
    query = query.where(Texture.model_version.in_(versions) if versions is not None
                        else Texture.model_version.not_in(loaded))
    with session_scope(services.sessions) as session:
        return list(session.scalars(query))


def reencode_textures(services, versions: set[str] | None = None, *, target: str | None = None,  # noqa: ANN001
                      dry_run: bool = False) -> ReencodeReport:
    """Move the textures of ``versions`` (default: of every unloaded model) onto ``target``
    (default: the model new uploads get)."""
    runtime = services.registry.get(target if target is not None else services.settings.default_model_version)
    report = ReencodeReport(target=runtime.version)
    textures = [t for t in stale_textures(services, versions) if t.model_version != runtime.version]
    refine = auto_fit_params(services, runtime.version)
    for texture in textures:  # photos first: blends mix their parents' new codes
        if texture.exemplar_key:
            if not dry_run:
                try:
                    if not _encode_again(services, runtime, texture, refine):
                        continue  # deleted meanwhile
                except Exception as exc:  # one bad photo (missing, unreadable) must not stop the rest
                    log.warning("texture not re-encoded: %s", exc, extra={"texture_id": texture.id})
                    report.skipped[texture.id] = f"its photo could not be encoded again: {exc}"
                    continue
            report.encoded.append(texture.id)
            if refine:
                report.refinements.append(texture.id)
    moved = set(report.encoded)
    for texture in textures:
        if texture.exemplar_key:
            continue
        why = _blend_problem(services, texture, runtime.version, moved)
        if why:
            report.skipped[texture.id] = why
            continue
        if not dry_run:
            _blend_again(services, runtime, texture)
        report.blended.append(texture.id)
        moved.add(texture.id)
    return report


def _encode_again(services, runtime, texture: Texture, refine: dict | None) -> bool:  # noqa: ANN001
    """The texture's code and colour table from its photo in ``runtime``'s space; what it
    had fitted in the old space is dropped, and a refinement queued where they run. False:
    the texture was deleted meanwhile."""
    code, colour = _encoded_photo(services, runtime, texture)
    with session_scope(services.sessions) as session:
        row = session.get(Texture, texture.id)
        if row is None:
            return False
        row.code, row.colour = code, colour
        row.colour_calibration, row.code_choice = COLOUR_CALIBRATION, choice_recipe(runtime)
        row.encoder_code = row.encoder_colour = row.structure = row.sampler_key = None
        row.sampler_interim = False
        row.model_version, row.updated_at = runtime.version, utcnow()
        row.refinement_job_id = new_id() if refine else None
    # what was fitted in the old space: refinements, and a fit's own texture's sampler pair
    # (a refinement's pair is already gone with its folder: deleting it again finds nothing)
    services.storage.delete_prefix(keys.refinements_prefix(texture.id))
    if texture.sampler_key:
        services.storage.delete(texture.sampler_key)
        services.storage.delete(keys.tileable_key(texture.sampler_key))
    for path in services.cached_samplers(texture.id):
        path.unlink(missing_ok=True)
    log.info("texture re-encoded", extra={"texture_id": texture.id, "model_version": runtime.version})
    if refine:
        jobs.queue_refinement(services, row, refine)
    return True


def _encoded_photo(services, runtime, texture: Texture) -> tuple[list[float], list[float] | None]:  # noqa: ANN001
    """The texture's stored photo encoded on ``runtime`` as an upload of it is today (its
    lighting as uploaded): code and colour table as a row stores them (None: no table)."""
    pixels = read_image(services.storage.get_bytes(texture.exemplar_key),
                        max_pixels=services.settings.max_image_pixels)
    code, colour = encode_texture(runtime, pixels, texture.lighting)
    return [float(c) for c in code], [float(c) for c in colour] or None


def _blend_problem(services, texture: Texture, version: str, moved: set[str]) -> str | None:  # noqa: ANN001
    """Why ``texture`` cannot be mixed again on ``version`` (None: it can)."""
    parents = texture.parents or {}
    if texture.source != "interpolate" or not {"a", "b", "t"} <= set(parents):
        return "no exemplar and not a blend: nothing to encode again"
    with session_scope(services.sessions) as session:
        for end in ("a", "b"):
            parent = session.get(Texture, parents[end])
            if parent is None:
                return f"its parent {parents[end]} was deleted"
            if parent.id in moved:
                continue
            if parent.model_version != version:
                return f"its parent {parent.id} is on model {parent.model_version}, not {version}"
            if parent.model_space() is None:
                return f"its parent {parent.id} is a fitted texture, which has no code in the model's space"
    return None


def _blend_again(services, runtime, texture: Texture) -> None:  # noqa: ANN001
    """Mix the blend again from its parents' values in ``runtime``'s space, as
    ``POST /v1/textures/interpolate`` does."""
    parents = texture.parents
    with session_scope(services.sessions) as session:
        a, b = (session.get(Texture, parents[end]) for end in ("a", "b"))
        row = session.get(Texture, texture.id)
        row.code, row.colour = blend_textures(a.model_space(), b.model_space(), float(parents["t"]),
                                              runtime.sampler.colour_size)
        row.colour_calibration = blend_calibration(a, b)
        row.model_version, row.updated_at = runtime.version, utcnow()


@dataclass
class ChoiceReport:
    """What one ``choose_codes_again`` run did (or, with ``dry_run``, would do), by texture id."""

    encoded: list[str] = field(default_factory=list)
    blended: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # id -> why


def _stale_choice(query, services):  # noqa: ANN001, ANN202
    """``query`` narrowed to uploads on a loaded model whose code was chosen by an older
    recipe than that model's (``choice_recipe``; NULL: the mean, from before it was recorded)."""
    newer = [and_(Texture.model_version == version, or_(Texture.code_choice.is_(None), Texture.code_choice < recipe))
             for version, recipe in ((v, choice_recipe(m)) for v, m in services.registry.models.items())
             if recipe > MEAN_CHOICE]
    return query.where(Texture.source == "upload", Texture.exemplar_key.is_not(None), or_(false(), *newer))


def stale_choice_textures(services) -> list[Texture]:  # noqa: ANN001
    """Uploads whose code an upload of their photo would choose differently today, oldest first."""
    query = (_stale_choice(select(Texture), services).order_by(Texture.created_at, Texture.id)
             .options(load_only(Texture.id, Texture.model_version, Texture.exemplar_key, Texture.lighting,
                                Texture.created_at)))
    with session_scope(services.sessions) as session:
        return list(session.scalars(query))


def warn_if_stale_choice(services) -> int:  # noqa: ANN001
    """Log a warning naming the command when uploads have codes of an older choice (at the
    API's start, as ``service.recolour.warn_if_stale`` does for tables); how many there are."""
    with session_scope(services.sessions) as session:
        count = session.scalar(_stale_choice(select(func.count()).select_from(Texture), services))
    if count:
        log.warning("%d uploads have codes chosen by an older recipe (their tiles keep the old code): "
                    "run `texspace reencode --stale-codes`", count)
    return count


def choose_codes_again(services, *, dry_run: bool = False) -> ChoiceReport:  # noqa: ANN001
    """Encode every ``stale_choice_textures`` upload again on its own model, then mix again
    the blends (oldest first: blends of blends after their parents) with a parent that moved."""
    report = ChoiceReport()
    textures = stale_choice_textures(services)
    for texture in textures:
        if not dry_run:
            try:
                why = _choose_again(services, texture)
            except Exception as exc:  # one bad photo (missing, unreadable) must not stop the rest
                log.warning("upload's code not chosen again: %s", exc, extra={"texture_id": texture.id})
                why = f"its photo could not be encoded again: {exc}"
            if why:
                report.skipped[texture.id] = why
                continue
        report.encoded.append(texture.id)
    moved = set(report.encoded)
    versions = {t.model_version for t in textures}
    blends = select(Texture).where(Texture.source == "interpolate", Texture.model_version.in_(versions))
    with session_scope(services.sessions) as session:
        blends = list(session.scalars(blends.order_by(Texture.created_at, Texture.id)
                                      .options(load_only(Texture.id, Texture.parents, Texture.source,
                                                         Texture.model_version, Texture.created_at))))
    for blend in blends:
        if not {(blend.parents or {}).get("a"), (blend.parents or {}).get("b")} & moved:
            continue
        why = _blend_problem(services, blend, blend.model_version, set())
        if why:
            report.skipped[blend.id] = why
            continue
        if not dry_run:
            _blend_again(services, services.registry.get(blend.model_version), blend)
        report.blended.append(blend.id)
        moved.add(blend.id)
    return report


def _choose_again(services, texture: Texture) -> str | None:  # noqa: ANN001
    """The upload's code as an upload of its photo gets it today, on its own model; why not
    (None: done). A refined upload keeps its fit: the new code is the encoder code it keeps."""
    runtime = services.registry.get(texture.model_version)
    with session_scope(services.sessions) as session:
        row = session.get(Texture, texture.id)
        if row is None:
            return "deleted meanwhile"
        before = (row.code, row.sampler_key, row.encoder_code, row.model_version)
    code, colour = _encoded_photo(services, runtime, texture)
    with session_scope(services.sessions) as session:
        row = session.get(Texture, texture.id)
        if row is None:
            return "deleted meanwhile"
        if (row.code, row.sampler_key, row.encoder_code, row.model_version) != before:
            return "refined or re-encoded while its code was chosen: run the command again"
        if row.encoder_code is not None:  # refined: the fit stays what it serves
            row.encoder_code, row.encoder_colour = code, colour
        else:
            row.code, row.colour = code, colour
            row.colour_calibration = COLOUR_CALIBRATION
        row.code_choice, row.updated_at = choice_recipe(runtime), utcnow()
    log.info("upload's code chosen again", extra={"texture_id": texture.id, "model_version": runtime.version})
    return None
