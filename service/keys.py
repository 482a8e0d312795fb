"""Storage keys: where every stored file lives, spelled once.

A texture owns everything under ``textures/<id>/`` and a job everything under
``jobs/<id>/``, so deleting one is deleting its prefix (``service/purge.py``). Keys are
``/``-separated relative paths (``service/storage.py``).
"""
from __future__ import annotations

SAMPLER = "sampler.onnx"  # a fitted texture's sampler (model.fit writes it under this name)


def texture_prefix(texture_id: str) -> str:
    """Every file of a texture: exemplar, fitted samplers, refinements."""
    return f"textures/{texture_id}"


def exemplar_key(texture_id: str, filename: str) -> str:
    """The texture's own copy of its exemplar photo (``exemplar.<ext>`` for an upload)."""
    return f"{texture_prefix(texture_id)}/{filename}"


def sampler_key(texture_id: str) -> str:
    """The sampler of a fit's new texture."""
    return f"{texture_prefix(texture_id)}/{SAMPLER}"


def refinements_prefix(texture_id: str) -> str:
    """Every in-place refinement of a texture, one folder per attempt."""
    return f"{texture_prefix(texture_id)}/refined"


def refinement_prefix(texture_id: str, job_id: str, attempt: int) -> str:
    """The folder of one attempt of an in-place refinement: its own key per attempt, so a
    tile ETag (which includes the sampler key) never names two samplers' bytes."""
    return f"{refinements_prefix(texture_id)}/{job_id}-{attempt}"


def beside(sampler_key: str, name: str) -> str:
    """Storage key of the file ``name`` stored beside a fitted texture's sampler."""
    folder = sampler_key.rpartition("/")[0]
    return f"{folder}/{name}" if folder else name


def tileable_key(sampler_key: str) -> str:
    """Storage key of the tileable sampler stored beside a fitted texture's sampler."""
    from worker.contract import TILEABLE_SAMPLER

    return beside(sampler_key, TILEABLE_SAMPLER)


def detail_key(sampler_key: str, tileable: bool = False) -> str:
    """Storage key of the detail sampler (model/detail.py), or its tileable twin, stored beside a
    fitted texture's sampler."""
    from worker.contract import DETAIL_SAMPLER, DETAIL_TILEABLE_SAMPLER

    return beside(sampler_key, DETAIL_TILEABLE_SAMPLER if tileable else DETAIL_SAMPLER)


def job_prefix(job_id: str) -> str:
    """Every file of a job: its input and its result."""
    return f"jobs/{job_id}"


def job_input_key(job_id: str, filename: str) -> str:
    """An uploaded job input (a bake's mesh)."""
    return f"{job_prefix(job_id)}/input/{filename}"


def paused_fit_key(job_id: str) -> str:
    """A paused fit's training state (weights, Adam moments, best state), which its
    continuation, on any worker, resumes."""
    return f"{job_prefix(job_id)}/paused/checkpoint.pt"


def result_key(job_id: str, filename: str) -> str:
    """A job's result: the same key on every run, so a re-run overwrites it (idempotent)."""
    return f"{job_prefix(job_id)}/result/{filename}"
