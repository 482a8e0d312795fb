"""A small Python client for the texspace HTTP API (needs only httpx and the stdlib).

Of the service it imports only the job vocabulary (standard library), so a script or
notebook that talks to a running server pays for no numpy, ONNX or FastAPI import::

    from service.client import Client

    with Client("http://127.0.0.1:8000") as ts:        # api_key="..." when keys are on
        texture = ts.upload("brick.jpg", name="brick")
        png = ts.tile(texture["id"], 6, 0, 0)           # bytes of one 256 px tile
        job = ts.volume(texture["id"], resolution=64, format="exr")
        job = ts.wait(job, progress=lambda j: print(f"{j['progress']:.0%}"))
        path = ts.download(job, "out/")                 # out/brick_volume_64px_seed0.exr

Every error answer (RFC 9457 problem+json) raises :class:`ApiError`; a job that ends
failed or canceled raises :class:`JobFailed` from :meth:`Client.wait`. A busy server's
answer (429 or 503 with ``Retry-After``: the request was refused before anything was
stored, uploads waiting their turn to be encoded, a full queue, a cold tile's render
queue) is retried after the wait it names, ``retries`` times (3 by default).
"""
from __future__ import annotations

import json
import os
import re
import time
from urllib.parse import quote, unquote
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from .vocabulary import TERMINAL_STATES, JobState

#: the response header of a zoomed-out tile's preview (openapi.yaml, getTile)
PREVIEW_HEADER = "X-Texspace-Tile"
Job = dict[str, Any]


class _ProgressBar:
    """A tqdm bar on stderr fed by :meth:`Client.wait`'s updates (tqdm: a service dependency,
    imported only when a bar is asked for)."""

    def __init__(self, description: str) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=100, desc=description, unit="%", bar_format="{l_bar}{bar}| {n:.0f}% [{elapsed}{postfix}]")

    def update(self, job: Job) -> None:
        self.bar.n = round(100 * float(job.get("progress", 0.0)), 1)
        stage = "paused after its interim" if job.get("stage") == "interim" and job.get("state") == JobState.QUEUED else None
        self.bar.set_postfix_str(stage or job.get("state", ""), refresh=False)
        self.bar.refresh()

    def __enter__(self) -> "_ProgressBar":
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()


class ApiError(Exception):
    """An error answer: ``status`` and the problem document (``title``, ``detail``, ``type``)."""

    def __init__(self, status: int, problem: dict[str, Any]) -> None:
        self.status, self.problem = status, problem
        super().__init__(f"{status} {problem.get('title', '')}: {problem.get('detail', '')}".strip(": "))


class JobFailed(Exception):
    """A job ended ``failed`` or ``canceled``; ``job`` is its last state (``job['error']``)."""

    def __init__(self, job: Job) -> None:
        self.job = job
        error = job.get("error") or {}
        super().__init__(f"job {job['id']} {job['state']}: {error.get('detail', '')}".rstrip(": "))


def _retry_after(res: httpx.Response) -> float | None:
    """Seconds to wait before asking again, for a busy answer that names them (the
    delay-seconds form of Retry-After, at most ``MAX_RETRY_WAIT``); None: do not ask again."""
    value = res.headers.get("retry-after", "")
    if res.status_code not in BUSY_STATUSES or not value.strip().isdigit():
        return None
    return min(float(value), MAX_RETRY_WAIT)


def _job_id(job: Job | str) -> str:
    """A job's id as one URL path segment (``_segment``)."""
    return _segment(job if isinstance(job, str) else job["id"])


def _disposition_name(header: str) -> str:
    """The file name of a Content-Disposition header: RFC 6266's UTF-8 ``filename*`` (a
    non-ASCII name) before the plain ASCII ``filename``; "" when it has neither."""
    star = re.search(r"filename\*=UTF-8''([^;\s]+)", header, re.IGNORECASE)
    if star:
        return unquote(star[1])
    plain = re.search(r'filename="([^"]+)"', header)
    return plain[1] if plain else ""


def _form_value(value: Any) -> str:
    """One multipart form value as the server reads it (booleans as true / false)."""
    return ("true" if value else "false") if isinstance(value, bool) else str(value)


def _form_fields(params: dict[str, Any]) -> dict[str, str | list[str]]:
    """Form fields of keyword arguments: a list or tuple (``maps=["height", "normal"]``)
    becomes the field repeated once per item, which is how the API takes list fields; None
    leaves the field out (the server's default)."""
    return {key: [_form_value(v) for v in value] if isinstance(value, (list, tuple)) else _form_value(value)
            for key, value in params.items() if value is not None}


def _segment(value: str) -> str:
    """An id as one URL path segment: percent-encoded, so '../../v1/jobs' cannot walk the API."""
    return quote(str(value), safe="")


#: answers that say "not now": the server refused before doing or storing anything, and
#: names in Retry-After when to ask again
BUSY_STATUSES = (429, 503)
#: the longest wait between two tries the client accepts from a Retry-After (seconds)
MAX_RETRY_WAIT = 30.0


class Client:
    """One connection pool to one texspace server. ``transport`` lets tests pass an
    ``httpx.ASGITransport`` or a mock; ``timeout`` is per request (seconds); ``retries``:
    how many times a busy answer (``BUSY_STATUSES`` with ``Retry-After``) is asked again
    after the wait it names (at most ``MAX_RETRY_WAIT``), before it raises."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", *, api_key: str | None = None,
                 timeout: float = 60.0, transport: httpx.BaseTransport | None = None, retries: int = 3) -> None:
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout,
                                 transport=transport)
        self.retries = retries
        self._limits: dict[str, Any] | None = None

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        for _ in range(self.retries):
            res = self.http.request(method, url, **kwargs)
            wait = _retry_after(res)
            if wait is None:
                break
            time.sleep(wait)
        else:
            res = self.http.request(method, url, **kwargs)
        if res.status_code >= 400:
            self._raise(res)
        return res

    @staticmethod
    def _key(idempotency_key: str | None) -> dict[str, str]:
        return {"Idempotency-Key": idempotency_key} if idempotency_key else {}

    def limits(self) -> dict[str, Any]:
        """The server's limits (``GET /v1/limits``: upload bytes and pixels, tile sizes and
        planes, volume and bake resolutions, a fit's default and longest budget, ...), read
        once per client: the server's own numbers, never copies of them."""
        if self._limits is None:
            self._limits = self._call("GET", "/v1/limits").json()
        return self._limits

    # --- textures -------------------------------------------------------------------
    def upload(self, image: str | os.PathLike | bytes, *, name: str | None = None,
               filename: str | None = None, lighting: str = "as-is", width_m: float | None = None) -> dict[str, Any]:
        """Upload a photo (a path, or bytes with ``filename``); returns the texture.
        ``lighting="even"``: its smooth shading is divided out before it is encoded and fitted.
        ``width_m``: the photo's real width in metres (bakes with ``unit_m`` then keep that size)."""
        if isinstance(image, bytes):
            data, filename = image, filename or "image.png"
        else:
            data, filename = Path(image).read_bytes(), filename or Path(image).name
        form = ({"lighting": lighting} | ({"name": name} if name is not None else {})
                | ({"width_m": str(width_m)} if width_m is not None else {}))
        return self._call("POST", "/v1/textures", files={"image": (filename, data)}, data=form).json()

    def texture(self, texture_id: str) -> dict[str, Any]:
        return self._call("GET", f"/v1/textures/{_segment(texture_id)}").json()

    def textures(self, *, page_size: int = 50) -> Iterator[dict[str, Any]]:
        """Every texture, newest first (follows the cursor pages)."""
        cursor = None
        while True:
            params = {"limit": page_size, **({"cursor": cursor} if cursor else {})}
            page = self._call("GET", "/v1/textures", params=params).json()
            yield from page["items"]
            if not (cursor := page.get("next_cursor")):
                return

    def rename(self, texture_id: str, name: str) -> dict[str, Any]:
        return self._call("PATCH", f"/v1/textures/{_segment(texture_id)}", json={"name": name}).json()

    def set_width(self, texture_id: str, width_m: float) -> dict[str, Any]:
        """Say how wide the texture's photo is in metres: bakes with ``unit_m`` keep that size."""
        return self._call("PATCH", f"/v1/textures/{_segment(texture_id)}", json={"width_m": width_m}).json()

    def delete(self, texture_id: str) -> None:
        """Delete a texture with its jobs and their files."""
        self._call("DELETE", f"/v1/textures/{_segment(texture_id)}")

    def tile(self, texture_id: str, z: int, x: int, y: int, *, fmt: str = "png", seed: int = 0,
             size: int = 256, plane: str = "xy", offset: float = 0.0, exact: bool = True,
             timeout: float = 300.0) -> bytes:
        """The bytes of tile (z, x, y) in ``fmt`` (png, webp, exr); ``size`` in pixels and ``plane``
        within the server's ``limits()`` (``min_tile_size``..``max_tile_size``, ``planes``).

        A zoomed-out tile the server does not hold yet may come first as a preview
        (header ``X-Texspace-Tile: preview``); with ``exact`` (the default) this asks again
        (If-None-Match: 304 while it is still rendering) until the exact tile arrives, at
        most ``timeout`` s (then TimeoutError); ``exact=False`` returns the preview."""
        url = f"/v1/textures/{_segment(texture_id)}/tiles/{z}/{x}/{y}.{fmt}"
        params = {"seed": seed, "size": size, "plane": plane, "offset": offset}
        res = self._call("GET", url, params=params)
        deadline, wait = time.monotonic() + timeout, 0.25
        while exact and res.headers.get(PREVIEW_HEADER) == "preview":
            if time.monotonic() > deadline:
                raise TimeoutError(f"tile {z}/{x}/{y} was still a preview after {timeout:g} s")
            time.sleep(wait)
            wait = min(2 * wait, 2.0)
            again = self._call("GET", url, params=params, headers={"If-None-Match": res.headers["ETag"]})
            if again.status_code != 304:
                res = again
        return res.content

    # --- jobs -----------------------------------------------------------------------
    def volume(self, texture_id: str, *, idempotency_key: str | None = None, **params: Any) -> Job:
        """Submit a volume job (``resolution``, ``bounds``, ``seed``, ``format``: see /docs)."""
        return self._call("POST", f"/v1/textures/{_segment(texture_id)}/volumes", json=params,
                          headers=self._key(idempotency_key)).json()

    def region(self, texture_id: str, *, idempotency_key: str | None = None, **params: Any) -> Job:
        """Submit a region export (``z``, ``x0``, ``y0``, ``width``, ``height``, ``format``,
        ``dds_compression`` (bc1, bc7) with format dds, ...)."""
        return self._call("POST", f"/v1/textures/{_segment(texture_id)}/regions", json=params,
                          headers=self._key(idempotency_key)).json()

    def bake(self, texture_id: str, mesh: str | os.PathLike | bytes, *, filename: str | None = None,
             idempotency_key: str | None = None, **params: Any) -> Job:
        """Submit a bake of a mesh file (OBJ, PLY, STL, GLB; bytes need ``filename``):
        ``resolution``, ``seed``, ``scale`` or ``unit_m`` (metres per mesh unit: at the photo's real
        size), ``format`` (glb, obj or usdz), ``projection`` (auto,
        solid or triplanar), ``maps`` (a list: ``["height", "normal", "roughness", "ao"]``),
        ``gpu_format`` (dds, ktx2) with ``dds_compression`` (bc1, bc7), ``normal_strength``,
        ``after_refinement`` and the other form fields of openapi.yaml."""
        if isinstance(mesh, bytes):
            data, filename = mesh, filename or "mesh.obj"
        else:
            data, filename = Path(mesh).read_bytes(), filename or Path(mesh).name
        return self._call("POST", f"/v1/textures/{_segment(texture_id)}/bakes", files={"mesh": (filename, data)},
                          data=_form_fields(params), headers=self._key(idempotency_key)).json()

    def fit(self, texture_id: str, *, seconds: float | None = None, grain: str | None = "auto",
            lattice: str | None = "auto", even: str | None = "auto", lean: str | None = "auto",
            detail_seconds: float | None = None, idempotency_key: str | None = None) -> Job:
        """Submit a fit (needs the train extra on the workers): refines the texture's sampler.
        ``seconds``: its time budget (None: the server's default, ``limits()["fit_seconds"]``;
        at most ``limits()["max_fit_seconds"]``);
        ``grain``: "x", "y", "auto" (detected from the photo) or None (isotropic);
        ``lattice``: "auto" (a repeat lattice detected from the photo) or None;
        ``even``: "auto" (an even photo's coarse octaves muted) or None;
        ``lean``: "auto" (a photo's lean, where it has no grain or lattice) or None;
        ``detail_seconds``: the detail stage of a photo of 512 px and up (None: the server's default, 20;
        0: none; its finer octaves are drawn above zoom 6, ``structure["detail_zoom"]``)."""
        return self._call("POST", f"/v1/textures/{_segment(texture_id)}/fit",
                          json={"grain": grain, "lattice": lattice, "even": even, "lean": lean}
                          | ({} if seconds is None else {"seconds": seconds})
                          | ({} if detail_seconds is None else {"detail_seconds": detail_seconds}),
                          headers=self._key(idempotency_key)).json()

    def job(self, job: Job | str) -> Job:
        return self._call("GET", f"/v1/jobs/{_job_id(job)}").json()

    def jobs(self, *, texture_id: str | None = None, state: str | None = None,
             page_size: int = 50) -> Iterator[Job]:
        """Every job (optionally of one texture or in one state), newest first."""
        cursor = None
        while True:
            params = {"limit": page_size, **{k: v for k, v in (("texture_id", texture_id), ("state", state),
                                                                ("cursor", cursor)) if v}}
            page = self._call("GET", "/v1/jobs", params=params).json()
            yield from page["items"]
            if not (cursor := page.get("next_cursor")):
                return

    def cancel(self, job: Job | str) -> Job:
        return self._call("POST", f"/v1/jobs/{_job_id(job)}/cancel").json()

    def wait(self, job: Job | str, *, timeout: float | None = None,
             progress: Callable[[Job], None] | bool | None = None) -> Job:
        """Follow a job's server-sent events until it ends; ``progress`` gets each update
        (a dict with ``state``, ``progress`` 0..1, ``attempt`` and a fit's ``stage``: null, or
        ``"interim"`` while an upload's refinement waits, paused after its interim);
        ``progress=True`` draws a bar on stderr instead. Returns the succeeded job, raises
        :class:`JobFailed` otherwise, ``TimeoutError`` after ``timeout`` seconds."""
        if progress is True:
            with _ProgressBar(f"job {_job_id(job)[:8]}") as bar:
                return self.wait(job, timeout=timeout, progress=bar.update)
        progress = progress or None
        job_id = _job_id(job)
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:  # a dropped stream (proxy timeout, restart) is picked up again
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"job {job_id} did not end within {timeout} s")
            try:
                end = self._follow(job_id, progress, remaining)
            except (httpx.TransportError, httpx.StreamError):
                end = None
            if end is None:
                now = self.job(job_id)
                end = now if now["state"] in TERMINAL_STATES else None
            if end is not None:
                if end["state"] != JobState.SUCCEEDED:
                    raise JobFailed(end)
                return end

    def wait_refined(self, texture: dict | str, *, timeout: float | None = None,
                     progress: Callable[[Job], None] | bool | None = None) -> dict:
        """Wait for an upload's refinement (its ``refinement`` fit job) to end; returns the texture
        as it is then (``sampler``: ``fitted`` when it succeeded). A texture without one is
        returned at once. ``progress``: as for :meth:`wait`."""
        texture_id = texture if isinstance(texture, str) else texture["id"]
        refinement = self.texture(texture_id).get("refinement")
        if refinement is not None:
            self.wait(refinement["job_id"], timeout=timeout, progress=progress)
        return self.texture(texture_id)

    def _follow(self, job_id: str, progress: Callable[[Job], None] | None, timeout: float | None) -> Job | None:
        """The final job from the event stream, or None when it closed before the end or
        ``timeout`` seconds passed (a read timeout alone restarts with every keep-alive)."""
        limit = httpx.Timeout(self.http.timeout.connect, read=timeout or 60.0)
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.http.stream("GET", f"/v1/jobs/{job_id}/events", timeout=limit) as res:
            if res.status_code >= 400:
                res.read()
                self._raise(res)
            event = "message"
            for line in res.iter_lines():
                if deadline is not None and time.monotonic() > deadline:
                    return None  # wait() then reads the job once and raises TimeoutError
                if line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data = json.loads(line[5:].strip())
                    if event in TERMINAL_STATES:
                        return data
                    if progress is not None:
                        progress(data)
        return None

    @staticmethod
    def _raise(res: httpx.Response) -> None:
        try:
            problem = res.json()
        except ValueError:
            problem = None
        if not isinstance(problem, dict):
            problem = {"title": res.reason_phrase, "detail": res.text[:200]}
        raise ApiError(res.status_code, problem)

    def download(self, job: Job | str, to: str | os.PathLike | None = None) -> Path:
        """Stream a succeeded job's result to a file: ``to`` is a file path, or a folder (an
        existing one, or a path ending in ``/``, made if missing) where it keeps the server's
        file name; default: the current folder."""
        with self.http.stream("GET", f"/v1/jobs/{_job_id(job)}/result") as res:
            if res.status_code >= 400:
                res.read()
                self._raise(res)
            name = Path(_disposition_name(res.headers.get("content-disposition", ""))).name or f"{_job_id(job)}.bin"
            target = Path(to) if to is not None else Path(".")
            if to is None or target.is_dir() or str(to).endswith(("/", os.sep)):
                target.mkdir(parents=True, exist_ok=True)
                target = target / name
            partial = target.with_name(target.name + ".part")
            with open(partial, "wb") as out:
                for chunk in res.iter_bytes():
                    out.write(chunk)
            partial.replace(target)
        return target
