"""Textures: upload (encode), list, read, rename, delete, exemplar, interpolate, shader."""
from __future__ import annotations

import logging
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Request, Response, UploadFile, status
from fastapi.responses import StreamingResponse
from sqlalchemy import select

from worker.colour_match import COLOUR_CALIBRATION, blend_textures
from worker.contract import MAX_WIDTH_M
from worker.decode import sniff_format
from worker.encode import choice_recipe, encode_texture
from worker.files import media_type, media_type_of_extension
from worker.images import read_image
from worker.photo import LIGHTING
from worker.shader import LANGUAGES

from .. import auth, jobs, keys
from ..db import session_scope
from ..deps import PageParams, SafeText, ServicesDep, TextureId, apply_cursor, page_of, printable
from ..errors import Problem, not_found, problem_responses
from ..job_kinds import auto_fit_params
from ..purge import purge_texture
from ..schemas import InterpolateIn, TextureOut, TexturePage, TexturePatch
from ..shaders import shader_etag, shader_source
from ..tables import Job, Texture, blend_calibration, new_id, utcnow
from ..tiles import etag_matches
from ..uploads import read_limited
from ..vocabulary import JobState

router = APIRouter(prefix="/v1/textures", tags=["textures"])
log = logging.getLogger(__name__)
NAME_LENGTH = 200  # Texture.name's column
NOSNIFF = {"X-Content-Type-Options": "nosniff"}  # stored files are served as their media type, never sniffed


def checked_text(value: str, field: str) -> str:
    """``value``, or a 422 problem if it holds control characters (deps.printable)."""
    try:
        return printable(value)
    except ValueError as exc:
        raise Problem(422, f"{field}: {exc}", slug="validation-error", title="Request validation failed") from exc


def load_texture(services, texture_id: str) -> Texture:  # noqa: ANN001
    checked_text(texture_id, "texture_id")  # routes without the typed TextureId parameter
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
    if texture is None or not auth.visible(texture):  # another tenant's texture does not exist for you
        raise not_found("texture", texture_id)
    return texture


@router.post("", status_code=status.HTTP_201_CREATED, response_model=TextureOut,
             responses=problem_responses(413, 422, 503, 507))
def create_texture(
    services: ServicesDep,
    response: Response,
    image: Annotated[UploadFile, File(description="PNG, JPEG, TIFF, EXR or WebP; 8/16-bit, float, grey, RGBA")],
    name: Annotated[SafeText | None, Form(max_length=NAME_LENGTH)] = None,
    lighting: Annotated[Literal[LIGHTING], Form(
        description="as-is (default), or even: the photo's smooth shading (light falling off, a vignette) "
                    "divided out before it is encoded and fitted; the stored photo is unchanged")] = "as-is",
    width_m: Annotated[float | None, Form(gt=0, le=MAX_WIDTH_M, description="the photo's real width in metres "
                                          "(optional): bakes with unit_m texture meshes at that size")] = None,
) -> TextureOut:
    """Encode an exemplar photo into a texture code and store it.

    The image is resized so its shorter side is the model's working resolution (its
    shading evened out with ``lighting=even``), then a 3 x 3 grid of 128 x 128 crops, each
    in its eight orientations, is encoded; of their mean and a few other combinations of
    their codes, the one whose tile is nearest the photo in VGG16 style statistics is
    stored (worker/encode.py). Where fitting is available (TEXSPACE_AUTO_FIT), a fit job
    then refines the texture in place.
    """
    checked_text(image.filename or "", "image filename")
    data = read_limited(image, services.settings.max_upload_bytes, "the image")
    with services.upload_slots.slot():  # a burst of uploads waits its turn (limits.upload_slots)
        pixels = read_image(data, max_pixels=services.settings.max_image_pixels)
        runtime = services.registry.get(services.settings.default_model_version)
        code, colour = encode_texture(runtime, pixels, lighting)
    ext = sniff_format(data)
    texture_id = new_id()
    refine = auto_fit_params(services, runtime.version)
    key = keys.exemplar_key(texture_id, f"exemplar.{ext}")
    services.storage.put_bytes(key, data)
    colour = [float(c) for c in colour] or None
    texture = Texture(id=texture_id, name=(name or image.filename or "")[:NAME_LENGTH], code=[float(c) for c in code],
                      colour=colour, colour_calibration=COLOUR_CALIBRATION, code_choice=choice_recipe(runtime),
                      model_version=runtime.version, source="upload", exemplar_key=key,
                      exemplar_media_type=media_type_of_extension(ext), lighting=lighting,
                      width=int(pixels.shape[1]), height=int(pixels.shape[0]), width_m=width_m,
                      owner_id=auth.current_owner(),
                      refinement_job_id=new_id() if refine else None)
    try:
        with session_scope(services.sessions) as session:
            session.add(texture)
    except BaseException:  # no row, no file: nothing orphaned
        services.storage.delete_prefix(keys.texture_prefix(texture_id))
        raise
    if refine:
        jobs.queue_refinement(services, texture, refine)
    response.headers["Location"] = f"/v1/textures/{texture_id}"
    return texture_out(services, load_texture(services, texture_id))


def texture_outs(services, textures: list[Texture]) -> list[TextureOut]:  # noqa: ANN001
    """The representations of ``textures``, with their refinement jobs (one query)."""
    job_ids = [t.refinement_job_id for t in textures if t.refinement_job_id]
    found: dict[str, Job] = {}
    if job_ids:
        with session_scope(services.sessions) as session:
            found = {j.id: j for j in session.scalars(select(Job).where(Job.id.in_(job_ids)))}
    waiting = [job for job in found.values() if job.state in (JobState.QUEUED, JobState.RUNNING)]
    lane = jobs.fit_lane(services) if waiting else None  # read once for the whole page
    waits = {job.id: jobs.refinement_wait(services, job, lane) for job in waiting}
    return [TextureOut.of(t, found.get(t.refinement_job_id or ""), waits.get(t.refinement_job_id or ""))
            for t in textures]


def texture_out(services, texture: Texture) -> TextureOut:  # noqa: ANN001
    return texture_outs(services, [texture])[0]


@router.get("", response_model=TexturePage, responses=problem_responses(422))
def list_textures(services: ServicesDep, page: Annotated[PageParams, Depends()]) -> TexturePage:
    """Newest first, with cursor pagination."""
    with session_scope(services.sessions) as session:
        rows = list(session.scalars(apply_cursor(auth.scoped(select(Texture), Texture), Texture, page)))
    rows, cursor = page_of(rows, page)
    return TexturePage(items=texture_outs(services, rows), next_cursor=cursor)


@router.post("/interpolate", status_code=status.HTTP_201_CREATED, response_model=TextureOut,
             responses=problem_responses(404, 409, 422, 507))
def interpolate(services: ServicesDep, body: InterpolateIn, response: Response) -> TextureOut:
    """A new texture whose code is (1 - t) a + t b, in the latent space of a and b's model."""
    a, b = load_texture(services, body.a), load_texture(services, body.b)
    if a.model_version != b.model_version:
        raise Problem(409, f"textures were encoded by different models ({a.model_version} and "
                           f"{b.model_version}); codes from different spaces cannot be blended",
                      slug="model-mismatch")
    ends = [t.model_space() for t in (a, b)]
    if None in ends:
        raise Problem(409, "fitted textures carry their own sampler and have no shared latent space; "
                           "interpolate the textures they were fitted from", slug="fitted-texture")
    code, colour = blend_textures(*ends, body.t, services.registry.get(a.model_version).sampler.colour_size)
    parents = {"a": a.id, "b": b.id, "t": body.t}
    # A refined parent's fitted sampler has a decoder of its own: two cannot be mixed, so the
    # blend is of the codes its encoder gave (the model's space); the blend says so.
    refined = [t.id for t in (a, b) if t.encoder_code is not None]
    if refined:
        parents["encoder_codes_of"] = refined
    texture = Texture(id=new_id(), name=body.name or blend_name(a.name or a.id, b.name or b.id, body.t),
                      code=code, colour=colour, colour_calibration=blend_calibration(a, b),
                      model_version=a.model_version, source="interpolate",
                      parents=parents, owner_id=auth.current_owner())
    with session_scope(services.sessions) as session:
        session.add(texture)
    response.headers["Location"] = f"/v1/textures/{texture.id}"
    return TextureOut.of(texture)


def blend_name(a: str, b: str, t: float) -> str:
    """``"{a} x {b} @ t"`` within the name column: long names are cut, each to half the room."""
    suffix = f" @ {t:g}"
    room = (NAME_LENGTH - len(suffix) - len(" x ")) // 2
    a, b = (n if len(n) <= room else n[:room - 1] + "\u2026" for n in (a, b))
    return f"{a} x {b}{suffix}"


@router.get("/{texture_id}", response_model=TextureOut, responses=problem_responses(404))
def get_texture(services: ServicesDep, texture_id: TextureId) -> TextureOut:
    return texture_out(services, load_texture(services, texture_id))


@router.patch("/{texture_id}", response_model=TextureOut, responses=problem_responses(404, 422, 507))
def patch_texture(services: ServicesDep, texture_id: TextureId, body: TexturePatch) -> TextureOut:
    """Rename a texture, or say how wide its photo is in metres (its code, and so its tiles,
    never change)."""
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
        if texture is None or not auth.visible(texture):
            raise not_found("texture", texture_id)
        for field in body.model_fields_set:
            setattr(texture, field, getattr(body, field))
        texture.updated_at = utcnow()
    return texture_out(services, texture)


@router.delete("/{texture_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses=problem_responses(404, 507))
def delete_texture(services: ServicesDep, texture_id: TextureId) -> Response:
    """Delete the texture, cancel and delete its jobs, and remove all their stored files."""
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
        if texture is None or not auth.visible(texture):
            raise not_found("texture", texture_id)
    if purge_texture(services, texture_id) is None:  # a concurrent DELETE took it first: one 204
        raise not_found("texture", texture_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{texture_id}/exemplar", response_class=StreamingResponse,
            responses={200: {"description": "the uploaded image, as uploaded",
                             "content": {"image/*": {}}}, **problem_responses(404)})
def get_exemplar(services: ServicesDep, texture_id: TextureId) -> StreamingResponse:
    texture = load_texture(services, texture_id)
    if not texture.exemplar_key:
        raise Problem(404, f"texture {texture_id} was made by interpolation and has no exemplar",
                      slug="no-exemplar")
    size = services.storage.size(texture.exemplar_key)
    return StreamingResponse(services.storage.iter_chunks(texture.exemplar_key),
                             media_type=texture.exemplar_media_type,
                             headers={"Content-Length": str(size), "Cache-Control": "public, max-age=86400", **NOSNIFF})


@router.get("/{texture_id}/shader.{language}", response_class=Response,
            responses={200: {"description": "GLSL ES 3.00 or WGSL source (docs/SHADER.md)",
                             "content": {media_type(lang).split(";")[0]: {} for lang in LANGUAGES}},
                       304: {"description": "unchanged (If-None-Match)"}, **problem_responses(404, 422, 503)})
def get_shader(services: ServicesDep, request: Request, texture_id: TextureId,
               language: Literal[LANGUAGES]) -> Response:
    """The texture as a real-time shader: ``vec3 texspace_<id>(vec3 p, uint seed)`` (GLSL ES
    3.00) or its WGSL twin, the same function as the texture's sampler (linear RGB at world
    point p), with the weights and the texture's constants embedded. Generated once per
    version of the texture; 503 + Retry-After while too many others are being generated."""
    texture = load_texture(services, texture_id)
    headers = {"ETag": shader_etag(texture, language), "Cache-Control": "public, no-cache", **NOSNIFF}
    if etag_matches(request.headers.get("if-none-match"), headers["ETag"]):
        return Response(status_code=304, headers=headers)
    text = shader_source(services, texture, language)
    return Response(text, media_type=media_type(language), headers=headers)
