"""What a texture is drawn with: its sampler, the code the sampler takes, the world scale.

Tiles, volume / bake / region jobs, the shader route and the CLI all draw a stored texture
from the same three things; they are assembled here, once, so that a database row
(service/tables.py) stays data and computes nothing of worker/.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from worker.colour_match import texture_vector
from worker.tiles import NATIVE_ZOOM

from .container import Services
from .tables import Texture


def sampling_code(texture: Texture) -> np.ndarray:
    """What the texture's sampler takes as its code: float32 [code_size + K], z then the
    colour table if it has one (Contract 1 in docs/ARCHITECTURE.md)."""
    return texture_vector(texture.code, texture.colour)


@dataclass
class SamplerInputs:
    """A texture's sampler, the code it is given and, read on first use, the world scale."""

    sampler: Any  # worker.runtime.Sampler: a model's runtime, or a fitted SamplerSession
    code: np.ndarray  # sampling_code(texture)
    services: Services = field(repr=False)
    texture: Texture = field(repr=False)

    @functools.cached_property
    def pixels_per_unit(self) -> float:
        """Exemplar pixels per world unit of the texture's model (fitted samplers share their
        parent's). Asked only by renderers that need it: a volume of a fitted texture needs
        no loaded model."""
        return self.services.pixels_per_unit(self.texture)


def sampler_inputs(services: Services, texture: Texture, zoom: int | None = None) -> SamplerInputs:
    """The sampler (its own fitted one, or its model's), code and scale that draw ``texture``.
    At a ``zoom`` above the native one, a fit's detail sampler where it has one (model/detail.py:
    the same texture with finer octaves learned on the photo at up to 4x the working size)."""
    code = sampling_code(texture)
    detail = services.detail_sampler_for(texture) if zoom is not None and zoom > NATIVE_ZOOM else None
    return SamplerInputs(detail or services.sampler_for(texture), code, services, texture)


def tileable_inputs(services: Services, texture: Texture, zoom: int | None = None) -> SamplerInputs:
    """``sampler_inputs`` with the texture's tileable sampler (``period`` input) instead;
    FeatureUnavailable if it has none. Above the native ``zoom``, the detail sampler's tileable
    twin where the fit has one."""
    code = sampling_code(texture)
    detail = services.detail_sampler_for(texture, tileable=True) if zoom is not None and zoom > NATIVE_ZOOM else None
    return SamplerInputs(detail or services.tileable_sampler_for(texture), code, services, texture)
