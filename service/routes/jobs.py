"""Jobs: submit (volumes, bakes, fit, regions), list, read, cancel, result, events."""
from __future__ import annotations

import asyncio
import json
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Query, Request, Response, UploadFile, status
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import BaseModel
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from worker.bake import BAKE_FORMATS, PARSED_MESH, mesh_npz
from worker.contract import MAX_BAKE_RESOLUTION, MAX_UNIT_M, MIN_BAKE_RESOLUTION
from worker.derived_maps import DEFAULT_NORMAL_STRENGTH, MAP_NAMES, MAX_NORMAL_STRENGTH
from worker.errors import Canceled, FeatureUnavailable, InvalidParameter, LimitExceeded
from worker.gpu_textures import DDS_COMPRESSIONS, GPU_FORMATS, check_gpu_options
from worker.tiles import MIN_ZOOM

from .. import auth, jobs, keys
from ..db import session_scope
from ..download_names import content_disposition
from ..deps import JobId, PageParams, SafeText, ServicesDep, TextureId, apply_cursor, idempotency_key, page_of
from ..errors import Problem, not_found, problem_for, problem_responses
from ..job_kinds import torch_available
from ..limits import check_mesh, check_queue_room
from ..schemas import (BAKE_PROJECTIONS, DDS_COMPRESSION_HELP, NORMAL_STRENGTH_HELP, BakeParams, FitIn, JobOut, JobPage,
                       RegionIn, VolumeIn)
from ..tables import Job, new_id
from ..uploads import read_limited, safe_filename, sha256
from ..vocabulary import TERMINAL_STATES, JobKind, JobState
from .textures import NOSNIFF, checked_text, load_texture

router = APIRouter(tags=["jobs"])
IdempotencyKey = Annotated[str | None, Depends(idempotency_key)]
ACCEPTED = {"status_code": status.HTTP_202_ACCEPTED, "response_model": JobOut}


def accepted(response: Response, job: Job, created: bool) -> JobOut:
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    if not created:
        response.headers["Idempotent-Replayed"] = "true"
    return JobOut.of(job)


def _submit(services, response: Response, kind: str, texture_id: str, body: BaseModel,  # noqa: ANN001
            key: str | None) -> JobOut:
    job, created = jobs.submit(services, kind=kind, texture_id=texture_id, params=body.model_dump(),
                               idempotency_key=key, fingerprint=jobs.request_hash(kind, texture_id, body))
    return accepted(response, job, created)


@router.post("/v1/textures/{texture_id}/volumes", **ACCEPTED, responses=problem_responses(404, 413, 422, 503, 507))
def submit_volume(services: ServicesDep, response: Response, texture_id: TextureId, body: VolumeIn,
                  key: IdempotencyKey) -> JobOut:
    """Render an N x N x N block of the solid texture (a job)."""
    load_texture(services, texture_id)
    if body.resolution > services.settings.max_volume_resolution:
        raise LimitExceeded(f"resolution {body.resolution} exceeds the limit of "
                            f"{services.settings.max_volume_resolution}")
    return _submit(services, response, JobKind.VOLUME, texture_id, body, key)


@router.post("/v1/textures/{texture_id}/bakes", **ACCEPTED, responses=problem_responses(404, 413, 422, 503, 507))
def submit_bake(
    services: ServicesDep,
    response: Response,
    texture_id: TextureId,
    key: IdempotencyKey,
    mesh: Annotated[UploadFile, File(description="OBJ, PLY, STL or GLB mesh (by file extension)")],
    resolution: Annotated[int, Form(ge=MIN_BAKE_RESOLUTION, le=MAX_BAKE_RESOLUTION,
                                     description="texture atlas side in pixels")] = 1024,
    seed: Annotated[int, Form(ge=0, le=2**31 - 1)] = 0,
    scale: Annotated[float | None, Form(gt=0, le=1e6, description="world units per mesh unit; default: "
                                                                   "the mesh spans 512 exemplar pixels")] = None,
    unit_m: Annotated[float | None, Form(gt=0, le=MAX_UNIT_M, description="metres per mesh unit (1: a mesh in "
                                         "metres, 0.01: in centimetres): the texture is baked at its photo's real "
                                         "size (the texture's width_m); not with scale")] = None,
    format: Annotated[Literal[BAKE_FORMATS], Form(
        description="glb; a zip of obj + mtl + mtlx (MaterialX standard_surface) + png; or usdz (mesh and "
                    "UsdPreviewSurface material with its textures inside)")] = "glb",
    maps: Annotated[list[Literal[MAP_NAMES]], Form(
        description="derived maps of the atlas (repeat the field for each): normal = tangent-space, OpenGL "
                    "convention (+Y up), embedded in a GLB as its normalTexture (with TANGENTs) or added to "
                    "the OBJ zip; roughness, ao = estimates, in a GLB its metallicRoughnessTexture (G) and "
                    "occlusionTexture (R), in the OBJ zip MTL map_Pr and a comment; height = linear luminance "
                    "stretched to 16 bits, <stem>_height.png (a GLB result becomes a zip; its range: "
                    "result.height_range)")] = [],
    gpu_format: Annotated[Literal[GPU_FORMATS] | None, Form(
        description="add a mipmapped <stem>_basecolor.dds (BC1, or BC7: dds_compression) / .ktx2 (Basis "
                    "Universal UASTC) of the atlas "
                    "(<stem>: the result's name); a GLB embeds the KTX2 (KHR_texture_basisu, PNG fallback) "
                    "and stays a GLB, with dds it becomes a zip of <stem>.glb and the texture")] = None,
    dds_compression: Annotated[Literal[DDS_COMPRESSIONS], Form(
        description=DDS_COMPRESSION_HELP + "; with gpu_format dds only")] = "bc1",
    normal_strength: Annotated[float, Form(gt=0, le=MAX_NORMAL_STRENGTH,
                                           description=NORMAL_STRENGTH_HELP)] = DEFAULT_NORMAL_STRENGTH,
    projection: Annotated[Literal[BAKE_PROJECTIONS], Form(
        description="solid: the solid texture at each surface point; triplanar: the texture's xy plane "
                    "projected along x, y and z, blended by the surface normal; auto: triplanar for a "
                    "texture fitted on a repeat lattice (structure.lattice), else solid")] = "auto",
    after_refinement: Annotated[bool, Form(
        description="if the texture's refinement may still replace its sampler, wait for it to end and bake "
                    "with the refined sampler; false: bake now with what the texture serves")] = False,
) -> JobOut:
    """UV-unwrap a mesh and bake the solid texture into its atlas (a job)."""
    checked_text(mesh.filename or "", "mesh filename")  # a NUL is refused, as in an upload's name, not cleaned
    texture = load_texture(services, texture_id)
    if unit_m is not None and scale is not None:
        raise InvalidParameter("give scale (world units per mesh unit) or unit_m (metres per mesh unit), not both")
    if unit_m is not None and texture.width_m is None:
        raise InvalidParameter(f"texture {texture_id} has no width_m: say how wide its photo is in metres "
                               f"(PATCH /v1/textures/{texture_id} {{\"width_m\": ...}}) to bake it at real size")
    check_gpu_options(gpu_format, dds_compression)  # a BC7 DDS asked for without a DDS: 422 before the upload
    if resolution > services.settings.max_bake_resolution:
        raise LimitExceeded(f"resolution {resolution} exceeds the limit of {services.settings.max_bake_resolution}")
    data = read_limited(mesh, services.settings.max_mesh_bytes, "the mesh")
    filename = safe_filename(mesh.filename, "mesh.obj")
    params = BakeParams(resolution=resolution, seed=seed, scale=scale, unit_m=unit_m, format=format, filename=filename,
                        maps=sorted(set(maps)), gpu_format=gpu_format, dds_compression=dds_compression,
                        normal_strength=normal_strength,
                        projection=projection, after_refinement=after_refinement)
    fingerprint = jobs.request_hash(JobKind.BAKE, texture_id, params, sha256(data).encode())
    params = params.model_dump()
    if key and (existing := jobs.find_by_idempotency_key(services, key)) is not None:
        return accepted(response, jobs.same_request(existing, fingerprint), False)
    parsed = check_mesh(services.settings, data, filename)  # a bad mesh is refused now, nothing stored
    check_queue_room(services, JobKind.BAKE)
    job_id = new_id()
    input_key = keys.job_input_key(job_id, PARSED_MESH)  # parsed once, here: the worker reads the arrays
    services.storage.put_bytes(input_key, mesh_npz(parsed))
    try:
        job, created = jobs.submit(services, kind=JobKind.BAKE, texture_id=texture_id, params=params,
                                   input_key=input_key, idempotency_key=key, fingerprint=fingerprint, job_id=job_id)
    except BaseException:  # no row, no file: nothing orphaned
        services.storage.delete_prefix(keys.job_prefix(job_id))
        raise
    if not created:
        services.storage.delete_prefix(keys.job_prefix(job_id))
    return accepted(response, job, created)


@router.post("/v1/textures/{texture_id}/fit", **ACCEPTED,
             responses=problem_responses(404, 409, 413, 422, 501, 503, 507))
def submit_fit(services: ServicesDep, response: Response, texture_id: TextureId, key: IdempotencyKey,
               body: FitIn | None = None) -> JobOut:
    """Optimise a sampler for this one exemplar (needs the torch extra on the workers)."""
    body = body or FitIn()
    if not torch_available():
        raise FeatureUnavailable("fitting needs PyTorch: install the train extra (pip install 'texspace[train]')")
    if body.seconds > services.settings.max_fit_seconds:
        raise LimitExceeded(f"seconds {body.seconds:g} exceeds the limit of {services.settings.max_fit_seconds:g}")
    texture = load_texture(services, texture_id)
    if not texture.exemplar_key:
        raise Problem(409, "this texture has no exemplar image to fit", slug="no-exemplar")
    return _submit(services, response, JobKind.FIT, texture_id, body, key)


@router.post("/v1/textures/{texture_id}/regions", **ACCEPTED,
             responses=problem_responses(404, 409, 413, 422, 501, 503, 507))
def submit_region(services: ServicesDep, response: Response, texture_id: TextureId, body: RegionIn,
                  key: IdempotencyKey) -> JobOut:
    """Render a large rectangle of the infinite plane to one image (a job); ``tileable``: a
    square image that repeats seamlessly."""
    texture = load_texture(services, texture_id)
    if body.width * body.height > services.settings.max_region_pixels:
        raise LimitExceeded(f"{body.width}x{body.height} exceeds the limit of "
                            f"{services.settings.max_region_pixels} pixels")
    if body.format == "pyramid":  # the worker's own count, checked now rather than after queueing
        from worker.regions import pyramid_tile_count

        low = MIN_ZOOM if body.min_zoom is None else body.min_zoom
        tiles = pyramid_tile_count(body.z, low, body.x0, body.y0, body.width, body.height, body.size)
        if tiles > services.settings.max_region_tiles:
            raise LimitExceeded(f"pyramid of {tiles} tiles exceeds the limit of "
                                f"{services.settings.max_region_tiles}")
    if body.tileable:  # 422 for a shape the tileable sampler cannot make, 409 for a texture without one
        from worker.regions import check_tileable

        check_tileable(z=body.z, width=body.width, height=body.height, fmt=body.format, plane=body.plane)
        if (reason := services.tileable_available(texture)) is not None:
            raise Problem(409, reason, slug="not-tileable", title="This texture has no tileable sampler")
    return _submit(services, response, JobKind.REGION, texture_id, body, key)


@router.get("/v1/jobs", response_model=JobPage, responses=problem_responses(422))
def list_jobs(
    services: ServicesDep,
    page: Annotated[PageParams, Depends()],
    state: Annotated[JobState | None, Query()] = None,
    texture_id: Annotated[SafeText | None, Query(max_length=64)] = None,
) -> JobPage:
    query = auth.scoped(select(Job), Job)
    if state:
        query = query.where(Job.state == state)
    if texture_id:
        query = query.where(Job.texture_id == texture_id)
    with session_scope(services.sessions) as session:
        rows = list(session.scalars(apply_cursor(query, Job, page)))
    rows, cursor = page_of(rows, page)
    return JobPage(items=[JobOut.of(j) for j in rows], next_cursor=cursor)


def load_job(services, job_id: str) -> Job:  # noqa: ANN001
    job = jobs.get(services, job_id)
    if job is None or not auth.visible(job):
        raise not_found("job", job_id)
    return job


@router.get("/v1/jobs/{job_id}", response_model=JobOut, responses=problem_responses(404))
def get_job(services: ServicesDep, job_id: JobId) -> JobOut:
    return JobOut.of(load_job(services, job_id))


@router.post("/v1/jobs/{job_id}/cancel", **ACCEPTED, responses=problem_responses(404, 409, 507))
def cancel_job(services: ServicesDep, response: Response, job_id: JobId) -> JobOut:
    """Cancel: a queued job at once; a running one stops at its next slab (poll the job)."""
    load_job(services, job_id)  # 404 for another tenant's job
    job = jobs.cancel(services, job_id)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return JobOut.of(job)


@router.get("/v1/jobs/{job_id}/result",
            responses={200: {"description": "the result file (its own media type)", "content": {"*/*": {}}},
                       **problem_responses(404, 409)})
def get_result(services: ServicesDep, job_id: JobId) -> Response:
    job = load_job(services, job_id)
    if job.state != JobState.SUCCEEDED or not job.result_key:
        raise Problem(409, f"job {job_id} is {job.state}; the result exists once it has succeeded",
                      slug="result-not-ready")
    headers = {"Content-Disposition": content_disposition(job.result_filename or f"{job.id}.bin"), **NOSNIFF}
    local = services.storage.local_path(job.result_key)
    if local is not None:
        return FileResponse(local, media_type=job.result_media_type, headers=headers)
    size = services.storage.size(job.result_key)
    return StreamingResponse(services.storage.iter_chunks(job.result_key), media_type=job.result_media_type,
                             headers={**headers, "Content-Length": str(size)})


SSE_POLL_SECONDS = 0.25
SSE_KEEPALIVE_SECONDS = 15.0
DELETED = problem_for(Canceled("the job was deleted with its texture")).to_dict()


@router.get("/v1/jobs/{job_id}/events",
            responses={200: {"description": "server-sent events: `progress` while running, then one "
                                            "final event named after the end state, with the job (a job deleted "
                                            "with its texture ends with `canceled`)",
                             "content": {"text/event-stream": {}}}, **problem_responses(404)})
async def job_events(services: ServicesDep, request: Request, job_id: JobId) -> StreamingResponse:
    first = await run_in_threadpool(load_job, services, job_id)

    async def stream():  # noqa: ANN202
        last, idle, event_id, seen = None, 0.0, 0, first
        while True:
            job = await run_in_threadpool(jobs.get, services, job_id)
            if job is None:  # deleted with its texture while running: it ends canceled
                event_id += 1
                gone = JobOut.of(seen).model_copy(update={"state": JobState.CANCELED, "error": DELETED})
                yield f"id: {event_id}\nevent: {JobState.CANCELED}\ndata: {gone.model_dump_json()}\n\n"
                return
            seen = job
            snapshot = (job.state, round(job.progress, 4), job.attempt, job.stage)
            if job.state in TERMINAL_STATES:
                event_id += 1
                yield f"id: {event_id}\nevent: {job.state}\ndata: {JobOut.of(job).model_dump_json()}\n\n"
                return
            if snapshot != last:
                event_id += 1
                idle = 0.0
                data = json.dumps({"state": job.state, "progress": job.progress, "attempt": job.attempt,
                                   "stage": job.stage})
                yield f"id: {event_id}\nevent: progress\ndata: {data}\n\n"
                last = snapshot
            elif idle >= SSE_KEEPALIVE_SECONDS:
                idle = 0.0
                yield ": keep-alive\n\n"
            if await request.is_disconnected():
                return
            await asyncio.sleep(SSE_POLL_SECONDS)
            idle += SSE_POLL_SECONDS

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
