"""A texture's shader source for the API: generated once per version, a bounded few at a time.

``worker.shader.emit_shader`` writes ~740 kB of text in ~0.15 s of Python holding the GIL:
16 concurrent requests slowed the texture list from 0.013 s to 2.34 s and a cold tile to
3.24 s. The text is a function of the texture's id, model, sampler and vector, so each is
generated once (``ShaderSources``: an LRU keyed by the texture and its ETag, one
generation per key however many ask at once), at most ``SHADER_WORKERS`` at a time, with
at most ``SHADER_QUEUE_DEPTH`` requests waiting; beyond, Busy (503 + Retry-After).
"""
from __future__ import annotations

import hashlib
import math
import threading
import time
from collections.abc import Callable

from worker.errors import Busy
from worker.shader import emit_shader, shader_name

from .container import Services
from .samplers import sampler_inputs, sampling_code
from .tables import Texture
from .tilecache import TileCache

#: bump when worker/shader.py emits different text for the same texture
SHADER_VERSION = "1"
#: generations at once: each holds the GIL, so more would only slow the rest of the API
SHADER_WORKERS = 1
#: requests that may wait for a generation (their own, or the same shader's); beyond, Busy
SHADER_QUEUE_DEPTH = 8
#: the longest a request waits for a generation before Busy
SHADER_WAIT_SECONDS = 10.0
#: bytes of generated sources kept (~45 shaders of 740 kB)
SHADER_CACHE_BYTES = 32 << 20


class ShaderSources:
    """Generated sources by key: an LRU bounded in bytes; a missing key is made by one
    caller while the others asking for it wait; at most ``workers`` made at once and
    ``depth`` callers waiting (for a slot or for their key), else Busy."""

    def __init__(self, max_bytes: int = SHADER_CACHE_BYTES, workers: int = SHADER_WORKERS,
                 depth: int = SHADER_QUEUE_DEPTH, wait_seconds: float = SHADER_WAIT_SECONDS) -> None:
        self.cache = TileCache(max_bytes)
        self.workers, self.depth, self.wait_seconds = workers, depth, wait_seconds
        self.seconds_each = 0.2     # measured: seconds of one generation
        self._cond = threading.Condition()
        self._making: set[str] = set()
        self._waiting = 0

    def _busy(self, why: str) -> Busy:
        wait = self.seconds_each * (self._waiting + len(self._making)) / self.workers
        return Busy(f"{why}; estimated wait {wait:.1f} s", retry_after=max(1, math.ceil(wait)))

    def _free(self, key: str) -> bool:
        return key not in self._making and len(self._making) < self.workers

    def get(self, key: str, make: Callable[[], bytes]) -> bytes:
        """The bytes under ``key``: cached, or ``make()`` (called by one caller at a time per key)."""
        data = self.cache.get(key)
        if data is not None:
            return data
        with self._cond:
            if not self._free(key):
                if self._waiting >= self.depth:
                    raise self._busy(f"{self._waiting} shader requests are waiting (limit {self.depth})")
                self._waiting += 1
                try:
                    deadline = time.monotonic() + self.wait_seconds
                    while not self._free(key):
                        remaining = deadline - time.monotonic()
                        if remaining <= 0:
                            raise self._busy(f"no shader generation started within {self.wait_seconds:g} s")
                        self._cond.wait(remaining)
                        if (data := self.cache.get(key)) is not None:   # made meanwhile by another caller
                            return data
                finally:
                    self._waiting -= 1
            self._making.add(key)
        started = time.perf_counter()
        try:
            data = make()
            self.cache.put(key, data)
            self.seconds_each = 0.7 * self.seconds_each + 0.3 * (time.perf_counter() - started)
            return data
        finally:
            with self._cond:
                self._making.discard(key)
                self._cond.notify_all()


SOURCES = ShaderSources()


def shader_etag(texture: Texture, language: str) -> str:
    """Strong ETag of a texture's shader: the inputs of its text (the texture's id is in the URL)."""
    key = "|".join((SHADER_VERSION, language, texture.model_version, texture.sampler_key or ""))
    return '"' + hashlib.sha256(key.encode() + sampling_code(texture).tobytes()).hexdigest()[:32] + '"'


def shader_source(services: Services, texture: Texture, language: str) -> bytes:
    """The texture's shader in ``language`` (UTF-8), from SOURCES or generated (Busy when
    too many wait)."""
    def make() -> bytes:
        inputs = sampler_inputs(services, texture)
        path = getattr(inputs.sampler, "sampler", inputs.sampler).path  # a model's runtime, or a fitted SamplerSession
        header = f"texspace texture {texture.id}, model {texture.model_version}"
        return emit_shader(path, inputs.code, shader_name(texture.id), language, header=header).encode()

    return SOURCES.get(f"{texture.id}|{shader_etag(texture, language)}", make)
