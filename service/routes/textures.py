"""Textures: upload (encode), list, read, rename, delete, exemplar, interpolate."""
from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Response, UploadFile, status
from fastapi.responses import StreamingResponse
from sqlalchemy import select

from worker.images import encode_image, read_image, sniff_format

from .. import auth
from ..db import session_scope
from ..deps import PageParams, ServicesDep, apply_cursor, page_of
from ..errors import Problem, not_found, problem_responses
from ..purge import purge_texture
from ..schemas import InterpolateIn, TextureOut, TexturePage, TexturePatch
from ..tables import Texture, new_id, utcnow
from ..uploads import IMAGE_MEDIA_TYPES, read_limited

router = APIRouter(prefix="/v1/textures", tags=["textures"])


def load_texture(services, texture_id: str) -> Texture:  # noqa: ANN001
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
    if texture is None or not auth.visible(texture):  # another tenant's texture does not exist for you
        raise not_found("texture", texture_id)
    return texture


@router.post("", status_code=status.HTTP_201_CREATED, response_model=TextureOut,
             responses=problem_responses(413, 422, 503))
def create_texture(
    services: ServicesDep,
    response: Response,
    image: Annotated[UploadFile, File(description="PNG, JPEG, TIFF, EXR or WebP; 8/16-bit, float, grey, RGBA")],
    name: Annotated[str | None, Form(max_length=200)] = None,
) -> TextureOut:
    """Encode an exemplar photo into a texture code and store it.

    The image is resized so its shorter side is the model's working resolution, then a
    3 x 3 grid of 128 x 128 crops is encoded and the codes averaged.
    """
    data = read_limited(image, services.settings.max_upload_bytes, "the image")
    pixels = read_image(data, max_pixels=services.settings.max_image_pixels)
    ext = sniff_format(data)
    runtime = services.registry.get(services.settings.default_model_version)
    code = encode_image(runtime, pixels)
    texture_id = new_id()
    key = f"textures/{texture_id}/exemplar.{ext}"
    services.storage.put_bytes(key, data)
    texture = Texture(id=texture_id, name=(name or image.filename or "")[:200], code=[float(c) for c in code],
                      model_version=runtime.version, source="upload", exemplar_key=key,
                      exemplar_media_type=IMAGE_MEDIA_TYPES.get(ext, "application/octet-stream"),
                      width=int(pixels.shape[1]), height=int(pixels.shape[0]), owner_id=auth.current_owner())
    try:
        with session_scope(services.sessions) as session:
            session.add(texture)
    except BaseException:  # no row, no file: nothing orphaned
        services.storage.delete_prefix(f"textures/{texture_id}")
        raise
    response.headers["Location"] = f"/v1/textures/{texture_id}"
    return TextureOut.of(texture)


@router.get("", response_model=TexturePage, responses=problem_responses(422))
def list_textures(services: ServicesDep, page: Annotated[PageParams, Depends()]) -> TexturePage:
    """Newest first, with cursor pagination."""
    with session_scope(services.sessions) as session:
        rows = list(session.scalars(apply_cursor(auth.scoped(select(Texture), Texture), Texture, page)))
    rows, cursor = page_of(rows, page)
    return TexturePage(items=[TextureOut.of(t) for t in rows], next_cursor=cursor)


@router.post("/interpolate", status_code=status.HTTP_201_CREATED, response_model=TextureOut,
             responses=problem_responses(404, 409, 422))
def interpolate(services: ServicesDep, body: InterpolateIn, response: Response) -> TextureOut:
    """A new texture whose code is (1 - t) a + t b, in the latent space of a and b's model."""
    a, b = load_texture(services, body.a), load_texture(services, body.b)
    if a.model_version != b.model_version:
        raise Problem(409, f"textures were encoded by different models ({a.model_version} and "
                           f"{b.model_version}); codes from different spaces cannot be blended",
                      slug="model-mismatch")
    if a.sampler_key or b.sampler_key:
        raise Problem(409, "fitted textures carry their own sampler and have no shared latent space; "
                           "interpolate the textures they were fitted from", slug="fitted-texture")
    code = (1.0 - body.t) * np.asarray(a.code, np.float64) + body.t * np.asarray(b.code, np.float64)
    texture = Texture(id=new_id(), name=body.name or f"{a.name or a.id} x {b.name or b.id} @ {body.t:g}",
                      code=[float(c) for c in code], model_version=a.model_version, source="interpolate",
                      parents={"a": a.id, "b": b.id, "t": body.t}, owner_id=auth.current_owner())
    with session_scope(services.sessions) as session:
        session.add(texture)
    response.headers["Location"] = f"/v1/textures/{texture.id}"
    return TextureOut.of(texture)


@router.get("/{texture_id}", response_model=TextureOut, responses=problem_responses(404))
def get_texture(services: ServicesDep, texture_id: str) -> TextureOut:
    return TextureOut.of(load_texture(services, texture_id))


@router.patch("/{texture_id}", response_model=TextureOut, responses=problem_responses(404, 422))
def patch_texture(services: ServicesDep, texture_id: str, body: TexturePatch) -> TextureOut:
    """Rename a texture (its code, and so its tiles, never change)."""
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
        if texture is None or not auth.visible(texture):
            raise not_found("texture", texture_id)
        texture.name = body.name
        texture.updated_at = utcnow()
    return TextureOut.of(texture)


@router.delete("/{texture_id}", status_code=status.HTTP_204_NO_CONTENT, responses=problem_responses(404))
def delete_texture(services: ServicesDep, texture_id: str) -> Response:
    """Delete the texture, cancel and delete its jobs, and remove all their stored files."""
    with session_scope(services.sessions) as session:
        texture = session.get(Texture, texture_id)
        if texture is None or not auth.visible(texture):
            raise not_found("texture", texture_id)
    purge_texture(services, texture_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{texture_id}/exemplar", response_class=StreamingResponse,
            responses={200: {"description": "the uploaded image, as uploaded",
                             "content": {"image/*": {}}}, **problem_responses(404)})
def get_exemplar(services: ServicesDep, texture_id: str) -> StreamingResponse:
    texture = load_texture(services, texture_id)
    if not texture.exemplar_key:
        raise Problem(404, f"texture {texture_id} was made by interpolation and has no exemplar",
                      slug="no-exemplar")
    size = services.storage.size(texture.exemplar_key)
    return StreamingResponse(services.storage.iter_chunks(texture.exemplar_key),
                             media_type=texture.exemplar_media_type,
                             headers={"Content-Length": str(size), "Cache-Control": "public, max-age=86400"})
