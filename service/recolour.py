"""Bring stored colour tables up to date: ``texspace recolour``.

A texture's colour table (worker/colour_match.py) matches its photo's colour statistics to
its sampler's raw output, and is computed once, when the texture is made. When the recipe
improves (``COLOUR_CALIBRATION`` goes up), textures made before keep their old tables:
same model, same code, older colours. Recolouring computes them again, as they would be
made today, on the textures' own models (the codes and samplers stay):

- an upload: its code's table from its photo, as an upload gets it (``worker.encode.code_colour``:
  quantile curves, or linear ones where they draw nearer the photo); if it was refined in
  place, also the fitted sampler's table, with linear curves (the transfer the fit was
  optimised under), and the kept encoder code's table, for blends;
- a fit's own texture: its fitted sampler's table from its own copy of the photo;
- a blend: its parents' (new) tables mixed at its t again;
- anything else (a blend whose parent was deleted) keeps its tables and is reported.

Textures on a model that is not loaded are left to ``texspace reencode``, which makes
new tables anyway. Tiles of a recoloured texture change, and so do their ETags (they
hash the table). Safe beside running workers: a row that changes while its table is
computed (a refinement landed) is skipped and reported; run again.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy import func, or_, select
from sqlalchemy.orm import load_only

from worker.colour_match import COLOUR_CALIBRATION, blend_textures
from worker.encode import code_colour
from worker.images import read_image
from worker.photo import working_photo

from .db import session_scope
from .job_kinds import fitted_colour
from .tables import Texture, blend_calibration, utcnow

log = logging.getLogger(__name__)


@dataclass
class RecolourReport:
    """What one run did (or, with ``dry_run``, would do), by texture id."""

    calibration: int
    recoloured: list[str] = field(default_factory=list)  # from their photos
    blended: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # id -> why


def _stale(query, services):  # noqa: ANN001, ANN202
    """``query`` narrowed to textures on a loaded model with tables of an older (or unknown) recipe."""
    return (query.where(Texture.model_version.in_(set(services.registry.models)))
            .where(or_(Texture.colour_calibration.is_(None), Texture.colour_calibration < COLOUR_CALIBRATION)))


def stale_colour_textures(services) -> list[Texture]:  # noqa: ANN001
    """Textures on a loaded model whose tables are of an older (or unknown) recipe, oldest
    first; only the columns that decide what to do are loaded."""
    query = (_stale(select(Texture), services).order_by(Texture.created_at, Texture.id)
             .options(load_only(Texture.id, Texture.model_version, Texture.source, Texture.parents,
                                Texture.exemplar_key, Texture.sampler_key, Texture.created_at)))
    with session_scope(services.sessions) as session:
        return list(session.scalars(query))


def warn_if_stale(services) -> int:  # noqa: ANN001
    """Log a warning naming the command when textures have tables of an older recipe (at
    the API's start: an upgrade that changed the recipe says so where operators look);
    how many there are."""
    with session_scope(services.sessions) as session:
        count = session.scalar(_stale(select(func.count()).select_from(Texture), services))
    if count:
        log.warning("%d textures have colour tables of an older recipe (their tiles keep the old colours): "
                    "run `texspace recolour`", count)
    return count


def recolour_textures(services, *, dry_run: bool = False) -> RecolourReport:  # noqa: ANN001
    """Compute again the colour tables of every stale texture (``stale_colour_textures``)."""
    report = RecolourReport(calibration=COLOUR_CALIBRATION)
    textures = stale_colour_textures(services)
    for texture in textures:  # photos first: blends mix their parents' new tables
        if not texture.exemplar_key:
            continue
        if not dry_run:
            try:
                why = _calibrate_again(services, texture.id)
            except Exception as exc:  # one bad photo (missing, unreadable) must not stop the rest
                log.warning("texture not recoloured: %s", exc, extra={"texture_id": texture.id})
                why = f"its photo could not be read or calibrated: {exc}"
            if why:
                report.skipped[texture.id] = why
                continue
        report.recoloured.append(texture.id)
    done = set(report.recoloured)
    for texture in textures:  # oldest first: a blend of blends after its parents
        if texture.exemplar_key:
            continue
        why = _blend_problem(services, texture, done, planned=dry_run)
        if not why and not dry_run:
            why = _blend_again(services, texture.id)
        if why:
            report.skipped[texture.id] = why
            continue
        report.blended.append(texture.id)
        done.add(texture.id)
    return report


def _calibrate_again(services, texture_id: str) -> str | None:  # noqa: ANN001
    """The texture's tables from its photo with today's recipe; why not (None: done)."""
    with session_scope(services.sessions) as session:
        row = session.get(Texture, texture_id)
        if row is None:
            return "deleted meanwhile"
        session.expunge(row)
    runtime = services.registry.get(row.model_version)
    image = working_photo(read_image(services.storage.get_bytes(row.exemplar_key),
                                     max_pixels=services.settings.max_image_pixels),
                          runtime.short_side, row.lighting)
    encoder_colour, space = None, row.model_space()  # the code the model's own sampler draws, if any
    if space:
        encoder_colour = _table(code_colour(runtime, image, np.asarray(space[0], np.float32)))
    colour = fitted_colour(services.sampler_for(row), row.code, image) if row.sampler_key else encoder_colour
    with session_scope(services.sessions) as session:
        current = session.get(Texture, texture_id)
        if current is None:
            return "deleted meanwhile"
        if (current.sampler_key, current.code, current.model_version) != (row.sampler_key, row.code,
                                                                        row.model_version):
            return "refined or re-encoded while its table was computed: run recolour again"
        current.colour = colour
        if current.encoder_code is not None:
            current.encoder_colour = encoder_colour
        current.colour_calibration, current.updated_at = COLOUR_CALIBRATION, utcnow()
    log.info("texture recoloured", extra={"texture_id": texture_id})
    return None


def _table(values: np.ndarray) -> list[float] | None:
    """A table as stored: floats, or None for a sampler without a colour stage."""
    return [float(v) for v in values] or None


def _blend_problem(services, texture: Texture, done: set[str], planned: bool) -> str | None:  # noqa: ANN001
    """Why ``texture`` cannot be mixed again from up-to-date parents (None: it can).
    ``planned``: a dry run, where ``done`` holds what would have been recoloured."""
    parents = texture.parents or {}
    if texture.source != "interpolate" or not {"a", "b", "t"} <= set(parents):
        return "no photo and not a blend: nothing to calibrate from"
    with session_scope(services.sessions) as session:
        for end in ("a", "b"):
            parent = session.get(Texture, parents[end])
            if parent is None:
                return f"its parent {parents[end]} was deleted"
            if parent.model_version != texture.model_version:
                return f"its parent {parent.id} is on model {parent.model_version}, not {texture.model_version}"
            if parent.model_space() is None:
                return f"its parent {parent.id} is a fitted texture, which has no table in the model's space"
            if parent.colour_calibration != COLOUR_CALIBRATION and not (planned and parent.id in done):
                return f"its parent {parent.id} could not be recoloured"
    return None


def _blend_again(services, texture_id: str) -> str | None:  # noqa: ANN001
    """Mix the blend's tables again from its parents', as ``POST /v1/textures/interpolate`` does."""
    with session_scope(services.sessions) as session:
        row = session.get(Texture, texture_id)
        if row is None:
            return "deleted meanwhile"
        a, b = (session.get(Texture, row.parents[end]) for end in ("a", "b"))
        colour_size = services.registry.get(row.model_version).sampler.colour_size
        _, row.colour = blend_textures(a.model_space(), b.model_space(), float(row.parents["t"]), colour_size)
        row.colour_calibration, row.updated_at = blend_calibration(a, b), utcnow()
    return None
