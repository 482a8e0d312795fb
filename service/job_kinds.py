"""What each job kind does: fetch inputs from storage, call worker/, store the result.

Each handler takes (services, job, workdir, progress, should_cancel) and returns the
job-row values to record on success. Results go to ``jobs/<job id>/result/<file>``, so a
re-run overwrites the same key with the same content (idempotent outputs).
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from worker.colour_match import COLOUR_CALIBRATION, calibrate_texture
from worker.derived_maps import map_file, read_height_range
from worker.errors import Canceled, FeatureUnavailable, InvalidParameter, Paused
from worker.files import extension, media_type
from worker.images import read_image, write_image
from worker.photo import working_photo
from worker.tiles import native_zoom_for

from . import jobs, keys
from .container import Services
from .db import session_scope
from .download_names import bake_name, region_name, sampler_name, volume_name
from .limits import bake_limits
from .samplers import sampler_inputs, tileable_inputs
from .schemas import BakeParams, FitParams, RegionIn, VolumeIn, bake_projection
from .tables import Job, Texture, utcnow
from .vocabulary import JobKind, JobState

Progress = Callable[[float], None]
ShouldCancel = Callable[[], bool]

def _texture(services: Services, job: Job) -> Texture:
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, job.texture_id)
    if texture is None:
        raise InvalidParameter(f"texture {job.texture_id} was deleted before the job ran")
    return texture


def _texture_to_render(services: Services, job: Job) -> Texture:
    """The job's texture, its sampler recorded on the job; a job submitted with
    ``after_refinement`` while the texture's refinement may still replace its sampler goes back
    to the queue instead (no attempt spent) until the refinement ends."""
    texture = _texture(services, job)
    sampler = jobs.served_sampler(services, texture.id, waiting=bool(job.params.get("after_refinement")))
    if sampler and sampler["waiting_for_refinement"]:
        raise Paused(f"waits for the refinement of texture {texture.id}", resend=False)
    jobs.record_sampler(services, job.id, sampler)
    return texture


def _store_result(services: Services, job: Job, path: Path, fmt: str, names: tuple[str, str],
                  height_range: tuple[float, float] | None = None,
                  texels_per_metre: float | None = None, scale: float | None = None) -> dict[str, Any]:
    """Store the result file at ``path``; ``names``: its download name's stem and that stem
    in ASCII (``service/download_names.py``), which the storage key uses. The extension is
    the file's own (a GLB bake with extra maps becomes a zip). ``height_range``: its height
    map's luminance range, ``texels_per_metre`` a bake's texel density at real size and
    ``scale`` the world units per mesh unit it used, shown with the result."""
    shown, stored = names
    key = keys.result_key(job.id, stored + path.suffix)
    size = services.storage.put_file(key, path)
    details = {}
    if height_range is not None:
        details["height_range"] = list(height_range)
    if texels_per_metre:
        details["texels_per_metre"] = round(texels_per_metre, 2)
    if scale is not None:
        details["scale"] = scale
    return {"result_key": key, "result_filename": shown + path.suffix, "result_size": size,
            "result_media_type": media_type(fmt), "result_details": details or None}


def zipped_height_range(path: Path) -> tuple[float, float] | None:
    """The luminance range stated in the height map of a zipped result (a region's maps), or None."""
    with zipfile.ZipFile(path) as z:
        height = next((name for name in z.namelist() if name.endswith(map_file("height"))), None)
        return read_height_range(z.read(height)) if height else None


def _names(build: Callable[..., str], texture: Texture, **parts: Any) -> tuple[str, str]:
    """(download name stem, its ASCII form) of a result named by ``build``."""
    return (build(texture.name, texture.id, ext="", **parts),
            build(texture.name, texture.id, ext="", ascii_only=True, **parts))


def run_volume(services: Services, job: Job, workdir: Path, progress: Progress,
               should_cancel: ShouldCancel) -> dict[str, Any]:
    from worker.volumes import render_volume

    texture = _texture_to_render(services, job)
    p = VolumeIn.model_validate(job.params)
    names = _names(volume_name, texture, resolution=p.resolution, seed=p.seed)
    out_path = workdir / f"{names[1]}{extension(p.format)}"
    inputs = sampler_inputs(services, texture)
    path = render_volume(inputs.sampler, inputs.code, p.seed, resolution=p.resolution,
                         bounds=p.bounds, fmt=p.format, out_path=out_path,
                         progress=progress, should_cancel=should_cancel)
    return _store_result(services, job, path, p.format, names)


def run_bake(services: Services, job: Job, workdir: Path, progress: Progress,
             should_cancel: ShouldCancel) -> dict[str, Any]:
    from worker.bake import PARSED_MESH, bake_mesh, mesh_from_npz, physical_scale

    texture = _texture_to_render(services, job)
    p = BakeParams.model_validate(job.params)
    stored = services.storage.get_bytes(job.input_key)
    # the API's parsed mesh (a job queued before it stored one holds the uploaded file)
    mesh = mesh_from_npz(stored) if job.input_key.endswith(PARSED_MESH) else None
    names = _names(bake_name, texture, mesh_filename=p.filename, resolution=p.resolution, seed=p.seed)
    out_path = workdir / f"{names[1]}{extension(p.format)}"   # zip members are named after it
    limits = bake_limits(services.settings)
    inputs = sampler_inputs(services, texture)
    scale = p.scale
    if p.unit_m is not None:  # at real size (the route checked the texture's width_m)
        scale = physical_scale(texture.width, texture.height, services.registry.get(texture.model_version).short_side,
                               inputs.pixels_per_unit, texture.width_m, p.unit_m)
    result = bake_mesh(inputs.sampler, inputs.code, p.seed, mesh_bytes=None if mesh else stored, mesh=mesh,
                       filename=p.filename, resolution=p.resolution, scale=scale, fmt=p.format,
                       out_path=out_path, limits=limits, pixels_per_unit=inputs.pixels_per_unit,
                       atlas_cache_dir=services.settings.resolved_atlas_cache_dir,
                       atlas_cache_bytes=services.settings.atlas_cache_bytes,
                       maps=tuple(p.maps), gpu_format=p.gpu_format, dds_compression=p.dds_compression,
                       normal_strength=p.normal_strength,
                       projection=bake_projection(p.projection, texture.served_structure()),
                       progress=progress, should_cancel=should_cancel)
    # texel density over the surface in metres, for a bake at real size
    density = (math.sqrt(float(result.covered.sum()) / (result.surface_area * p.unit_m ** 2))
               if p.unit_m is not None and result.surface_area > 0 else None)
    # a GLB or USDZ with a height map or a DDS comes back as a zip (a KTX2 goes inside the GLB)
    fmt = p.format if result.path.suffix == extension(p.format) else "zip"
    return _store_result(services, job, result.path, fmt, names,
                         result.height_range, texels_per_metre=density, scale=result.scale)


def run_region(services: Services, job: Job, workdir: Path, progress: Progress,
               should_cancel: ShouldCancel) -> dict[str, Any]:
    from worker.regions import RegionLimits, render_region

    texture = _texture_to_render(services, job)
    p = RegionIn.model_validate(job.params)
    maps = tuple(p.maps)
    fmt = "zip" if maps else p.format  # with derived maps, a zip of colour + maps
    names = _names(region_name, texture, z=p.z, width=p.width, height=p.height, seed=p.seed, plane=p.plane,
                   tileable=p.tileable)
    out_path = workdir / f"{names[1]}{extension(fmt)}"   # zip members are named after it
    limits = RegionLimits(max_pixels=services.settings.max_region_pixels,
                          max_tiles=services.settings.max_region_tiles)
    # tileable: the texture's sampler_tileable.onnx, its period the image's side
    inputs = (tileable_inputs(services, texture, zoom=p.z) if p.tileable
              else sampler_inputs(services, texture, zoom=p.z))
    path = render_region(inputs.sampler, inputs.code, p.seed, z=p.z, x0=p.x0, y0=p.y0, width=p.width,
                         height=p.height, fmt=p.format, out_path=out_path, size=p.size, min_zoom=p.min_zoom,
                         plane=p.plane, offset=p.offset, maps=maps, normal_strength=p.normal_strength,
                         wrap_maps=p.tileable, tileable=p.tileable, dds_compression=p.dds_compression,
                         pixels_per_unit=inputs.pixels_per_unit, limits=limits,
                         progress=progress, should_cancel=should_cancel)
    return _store_result(services, job, path, fmt, names, zipped_height_range(path) if "height" in maps else None)


def fitted_texture_id(job_id: str) -> str:
    """Deterministic id of a fit job's new texture, so a re-run cannot make two."""
    return hashlib.sha256(f"fit:{job_id}".encode()).hexdigest()[:32]


def torch_available() -> bool:
    return importlib.util.find_spec("torch") is not None


def auto_fit_params(services: Services, model_version: str) -> dict[str, Any] | None:
    """Params of an upload's in-place refinement (TEXSPACE_AUTO_FIT), or None where none
    can run here: the setting is off, torch is not installed, or the model ships no
    space.pt (the checkpoint a fit starts from)."""
    settings = services.settings
    if not settings.auto_fit or not torch_available():
        return None
    if not (services.registry.get(model_version).model_dir / "space.pt").is_file():
        return None
    return {"seconds": min(settings.fit_seconds, settings.max_fit_seconds), "grain": "auto", "lattice": "auto",
            "even": "auto", "lean": "auto", "in_place": True, "detail_seconds": settings.refine_detail_seconds}


def run_fit(services: Services, job: Job, workdir: Path, progress: Progress,
            should_cancel: ShouldCancel) -> dict[str, Any]:
    """Fit the texture's exemplar; ``params.in_place`` (an upload's automatic refinement)
    makes the texture itself serve the result, otherwise a new texture does."""
    if not torch_available():
        raise FeatureUnavailable("fitting needs PyTorch on the worker: pip install 'texspace[train]'")
    texture = _texture(services, job)
    if not texture.exemplar_key:
        raise InvalidParameter(f"texture {texture.id} has no exemplar image to fit")
    p = FitParams.model_validate(job.params)
    # keep the extension: the reader picks the decoder by it (model.fit reads with the same
    # reader, worker.decode, as this process)
    original = services.storage.get_file(texture.exemplar_key, workdir / Path(texture.exemplar_key).name)
    # the fit and its colour table see the photo as its encoding did (lighting included)
    image = working_photo(read_image(original.read_bytes(), max_pixels=services.settings.max_image_pixels),
                          services.registry.get(texture.model_version).short_side, texture.lighting)
    photo = photo_to_fit(original, image, texture.lighting, workdir)
    out_dir = workdir / "fit"

    def serve_interim(folder: Path, code: list[float], step: int, found: dict[str, Any]) -> None:
        # the fit's best state part way: the texture serves it until the final one replaces it
        _refine_in_place(services, job, texture, folder / keys.SAMPLER, [float(c) for c in code], image,
                         fit_structure(found), interim=True)

    in_place_interim = p.in_place and services.settings.fit_interim_seconds > 0
    # A refinement pauses at its interim's second while other uploads wait for theirs (its training
    # state stored); its continuation, on any worker, resumes that state with no interim of its own.
    paused_key = keys.paused_fit_key(job.id)
    run_dir = workdir / "run"
    resumed = in_place_interim and services.storage.exists(paused_key)
    if resumed:
        services.storage.get_file(paused_key, run_dir / "checkpoint.pt")

    def pause() -> bool:
        return jobs.fits_waiting_for_interim(services, job.id)

    def wants_detail() -> bool:  # an upload's refinement: its detail stage only while no other fit waits
        return not (p.in_place and jobs.other_fits_queued(services, job.id))

    first_stage = in_place_interim and not resumed
    fitted = _fit_exemplar(services, texture, p, photo, out_dir, progress, should_cancel,
                           serve_interim if first_stage else None, pause=pause if first_stage else None,
                           run_dir=run_dir, wants_detail=wants_detail)
    if fitted.get("paused"):
        services.storage.put_file(paused_key, run_dir / "checkpoint.pt")
        raise Paused(f"paused at its interim's second, step {fitted['steps']}: other uploads wait for theirs",
                     stage="interim")
    services.storage.delete(paused_key)
    structure = fit_structure(fitted)
    code = [float(c) for c in json.loads((out_dir / "code.json").read_text())["code"]]
    values = _store_result(services, job, out_dir / "sampler.onnx", "onnx",
                           (sampler_name(texture.name, texture.id).removesuffix(".onnx"),
                            sampler_name(texture.name, texture.id, ascii_only=True).removesuffix(".onnx")))
    if p.in_place:
        _refine_in_place(services, job, texture, out_dir / "sampler.onnx", code, image, structure)
        return {**values, "output_texture_id": texture.id}
    new_id = fitted_texture_id(job.id)
    sampler_key = keys.sampler_key(new_id)
    services.storage.put_file(sampler_key, out_dir / "sampler.onnx")
    _store_companions(services, sampler_key, out_dir)
    colour = fitted_colour(services.registry.fitted_sampler(out_dir / "sampler.onnx"), code, image)
    exemplar_key = keys.exemplar_key(new_id, Path(texture.exemplar_key).name)  # own copy: outlives the parent
    services.storage.put_file(exemplar_key, original)
    with session_scope(services.sessions) as session:
        current = session.get(Job, job.id)
        dropped = (session.get(Texture, texture.id) is None or current is None or current.state != JobState.RUNNING
                   or current.attempt != job.attempt)  # the texture deleted (with its jobs) meanwhile
        if not dropped and session.get(Texture, new_id) is None:
            session.add(Texture(id=new_id, name=f"{texture.name or texture.id} (fitted)",
                                code=code, colour=colour, colour_calibration=COLOUR_CALIBRATION,
                                model_version=texture.model_version,
                                source="fit", parents={"texture": texture.id, "job": job.id},
                                owner_id=texture.owner_id,
                                exemplar_key=exemplar_key,
                                exemplar_media_type=texture.exemplar_media_type,
                                width=texture.width, height=texture.height, sampler_key=sampler_key,
                                structure=structure, lighting=texture.lighting))
    if dropped:  # nothing of a deleted texture survives: not its fitted child, nor the files stored for it
        services.storage.delete_prefix(keys.texture_prefix(new_id))
        raise Canceled(f"texture {texture.id} was deleted while it was fitted; its fit was dropped")
    return {**values, "output_texture_id": new_id}


def photo_to_fit(original: Path, image: np.ndarray, lighting: str, folder: Path) -> Path:
    """The file model.fit reads: the photo as uploaded, or with ``lighting`` "even" its evened
    working photo ``image`` as a 16-bit sRGB TIFF in ``folder`` (model.fit reads it at its own
    resolution), so the fit sees the photo as its encoding did."""
    if lighting != "even":
        return original
    photo = folder / "evened.tiff"
    photo.write_bytes(write_image(image, "tiff", colour="srgb"))
    return photo


def fit_structure(found: dict[str, Any]) -> dict[str, Any]:
    """The texture's ``structure`` from what model.fit reports it built in (its result, or
    the interim's ``structure``, which has no detail stage)."""
    detail = found.get("detail") or {}
    return {"grain": found.get("grain"), "straightened": found.get("straightened", 0.0),
            "grain_stretch": found.get("grain_stretch"),
            "lattice": found.get("lattice"), "muted_octaves": found.get("muted_octaves", 0),
            "lean": found.get("lean"),
            "detail_zoom": native_zoom_for(detail["factor"]) if detail.get("sampler") else None}


def _fit_exemplar(services: Services, texture: Texture, p: FitParams, image_path: Path, out_dir: Path,
                  progress: Progress, should_cancel: ShouldCancel,
                  interim: Callable[..., None] | None = None, pause: Callable[[], bool] | None = None,
                  run_dir: Path | None = None, wants_detail: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Run model.fit.fit_exemplar (torch) from the texture's model's space.pt; its result
    (code, grain and lattice used, ...). ``interim``: model.fit's hook for its best state
    ``TEXSPACE_FIT_INTERIM_SECONDS`` in (an in-place refinement serves it); ``pause`` and
    ``run_dir``: model.fit's, to stop after the interim and to resume; ``wants_detail``: model.fit's,
    asked before the detail stage."""
    from model.fit import fit_exemplar  # torch lives in model/, imported only here

    def report(fraction: float, *_: Any, **__: Any) -> None:  # no cancel hook: stop at a report
        progress(float(fraction))
        if should_cancel():
            raise Canceled("fit canceled")

    checkpoint = services.registry.get(texture.model_version).model_dir / "space.pt"
    if not checkpoint.is_file():
        raise FeatureUnavailable(f"model {texture.model_version} ships no space.pt checkpoint to fit from")
    # TEXSPACE_FIT_THREADS (default every core): the worker is niced, so tiles still come first
    settings = services.settings
    extra = {"interim": interim, "interim_seconds": settings.fit_interim_seconds, "pause": pause} if interim else {}
    return fit_exemplar(image_path, out_dir, init_checkpoint=checkpoint, minutes=p.seconds / 60.0,
                        start_code=start_code(texture),
                        progress=report, grain=p.grain, lattice=p.lattice, even=p.even, lean=p.lean,
                        threads=settings.fit_threads, device=settings.fit_device, precision=settings.fit_precision,
                        run_dir=run_dir, detail_seconds=p.detail_seconds, wants_detail=wants_detail, **extra)


def start_code(texture: Texture) -> list[float] | None:
    """The code a fit of ``texture`` starts from: the one its upload stored (the encoder's,
    kept as ``encoder_code`` once a refinement replaced it); None for a texture whose code is
    a fitted sampler's own (the fit then takes the encoder's mean code)."""
    if texture.encoder_code is not None:
        return list(texture.encoder_code)
    return None if texture.sampler_key else list(texture.code)


def _refine_in_place(services: Services, job: Job, texture: Texture, sampler_path: Path, code: list[float],
                     image: np.ndarray, structure: dict[str, Any], interim: bool = False) -> None:
    """Make ``texture`` serve the fitted sampler: store it under a key of this attempt's own
    (so a tile ETag, which includes the key, never names two samplers' bytes), then update
    the row if this attempt still holds the job. The encoder's code is kept for blends.
    ``interim``: the fit's state part way (``sampler_interim``), in the attempt's ``interim``
    folder; it stays there once the final one is served, so a request that read the row
    before the swap still finds its sampler (it goes with the texture's refinements)."""
    folder = keys.refinement_prefix(texture.id, job.id, job.attempt) + ("/interim" if interim else "")
    sampler_key = f"{folder}/{keys.SAMPLER}"
    services.storage.put_file(sampler_key, sampler_path)
    _store_companions(services, sampler_key, sampler_path.parent)
    local = services.sampler_path(texture.id, sampler_key)  # where sampler_for looks: no second download
    local.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(sampler_path, local)
    colour = fitted_colour(services.registry.fitted_sampler(local), code, image)
    with session_scope(services.sessions) as session:
        current = session.get(Job, job.id)
        row = session.get(Texture, texture.id)
        moved = row is not None and row.model_version != texture.model_version
        if current is None or current.state != JobState.RUNNING or current.attempt != job.attempt or row is None or moved:
            services.storage.delete_prefix(folder)  # no row names it: leave no file behind
            local.unlink(missing_ok=True)
            if moved:  # texspace reencode moved it on (and queued a refinement of its own)
                raise Canceled(f"the texture moved from model {texture.model_version} to {row.model_version} "
                               "while it was refined; the refinement of the old model was dropped")
            raise Canceled("the job was taken over or deleted before its refinement was applied")
        if row.encoder_code is None:  # the first refinement: keep what the encoder gave, for blends
            row.encoder_code, row.encoder_colour = list(row.code), row.colour
        row.code, row.colour, row.sampler_key, row.updated_at = code, colour, sampler_key, utcnow()
        row.structure, row.sampler_interim = structure, interim


def _store_companions(services: Services, sampler_key: str, fit_dir: Path) -> None:
    """Store the fit's tileable sampler beside its sampler (``tileable_key``), where
    tileable regions look for it (a model.fit from before tileable textures writes none), and
    its detail sampler and that one's tileable twin (``detail_key``), where tiles and images above
    the native zoom look for them (a fit of a photo under twice the working size, an interim or a
    detail stage that gained nothing writes none)."""
    from worker.contract import DETAIL_SAMPLER, DETAIL_TILEABLE_SAMPLER, TILEABLE_SAMPLER

    for name in (TILEABLE_SAMPLER, DETAIL_SAMPLER, DETAIL_TILEABLE_SAMPLER):
        if (fit_dir / name).is_file():
            services.storage.put_file(keys.beside(sampler_key, name), fit_dir / name)


def fitted_colour(sampler, code: list[float], image: np.ndarray) -> list[float] | None:  # noqa: ANN001
    """The texture's colour table for its fitted ``sampler`` (a SamplerSession; the table
    matches the photo to a sampler's own raw output, so a new sampler needs a new table);
    None if it has no colour stage. ``image``: the exemplar as its encoding saw it
    (``working_photo``: float32 sRGB at the model's working resolution)."""
    colour = calibrate_texture(sampler, np.asarray(code, np.float32), image,
                               curves="linear")  # the transfer the fit was optimised under
    return [float(v) for v in colour] or None


KINDS: dict[JobKind, Callable[..., dict[str, Any]]] = {
    JobKind.VOLUME: run_volume, JobKind.BAKE: run_bake, JobKind.REGION: run_region, JobKind.FIT: run_fit,
}
