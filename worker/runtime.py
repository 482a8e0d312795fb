"""ONNX Runtime sessions for the exported model (docs/ARCHITECTURE.md, Contract 1).

Load once, then arrays in, arrays out:

* ``SamplerSession(path)``: one ``sampler.onnx`` (a model's, or a fitted texture's own).
  ``.sample(points, code, seed)`` evaluates it in bounded chunks.
* ``ModelRuntime(model_dir)``: manifest + encoder + sampler of one model version, plus
  its tileable sampler (``sampler_tileable.onnx``) and its style statistics (``style.onnx``),
  each opened on first use.
* ``PeriodicSampler(session, period)``: a tileable sampler with its period bound, so it
  is a ``Sampler`` like the others (tileable regions).
* ``ModelRegistry(folders)``: every model version found under some folders, side by
  side, keyed by manifest ``version``, plus an LRU of extra sampler sessions for
  fitted textures.

Anything that has ``.sample(points, code, seed)`` is a ``Sampler``; tiles, volumes,
bakes and regions take one, so they work with either kind of session.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterable, Protocol

import numpy as np
import onnxruntime as ort

from worker.colour_match import identity_colour
from worker.contract import STYLE_FEATURES, TILEABLE_SAMPLER
from worker.errors import FeatureUnavailable, InvalidParameter, ModelInvalid, ModelNotFound

log = logging.getLogger(__name__)

MANIFEST_KEYS = (
    "version", "variant", "code_size", "pixels_per_unit", "encoder_input_size",
    "encoder_input_range", "exemplar_short_side", "output_colour", "training", "created_at",
)
# Points per sampler call. The noise makes a few dozen passes over arrays of
# chunk * 8 octaves * 8 corners int64 values; at 2048 points each is 1 MB and stays in
# this machine's caches (1 MB L2 per core). Measured, 2 threads, median of 5 on the
# shared 2-core machine: 1024: 0.33, 2048: 0.32, 4096: 0.28, 8192: 0.27 M points/s;
# 64k chunks (the old default) ~0.25. bench/run.py sweeps it again on every run.
DEFAULT_CHUNK = 2048


class Sampler(Protocol):
    """What synthesis functions need: a point function of (position, code, seed)."""

    def sample(self, points: np.ndarray, code: np.ndarray, seed: int) -> np.ndarray: ...


def session_options(threads: int | None = None) -> ort.SessionOptions:
    """CPU session options: all graph optimisations, sequential, ``threads`` intra-op.

    Idle pool threads sleep instead of spinning: on a shared 2-core machine spinning
    threads halved the sampler's throughput (bench/run.py).
    """
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3
    return opts


def _open_session(path: Path, threads: int | None, *, arena: bool = True) -> ort.InferenceSession:
    """``arena=False``: buffers go back to the system after each run, not into a pool the
    session keeps (for a graph run seldom, with large activations: the style statistics)."""
    if not path.is_file():
        raise ModelNotFound(f"missing ONNX file: {path}")
    options = session_options(threads)
    options.enable_cpu_mem_arena = arena
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own assorted exception types
        raise ModelInvalid(f"cannot load {path.name}: {exc}") from exc


class SamplerSession:
    """One ``sampler.onnx``: points float64 [P,3], z float32 [P|1,8], seed int64 -> rgb [P,3].

    A ``sampler_tileable.onnx`` has one more input, ``period`` float64 [] (world units):
    ``.periodic`` is then True and ``.sample`` needs ``period=`` (``PeriodicSampler`` binds it).

    Parallel over chunks, not inside them: the session runs one intra-op thread and
    ``threads`` chunks run at once (``session.run`` releases the GIL). The graph is
    mostly small elementwise ops, where ONNX Runtime's intra-op split cost more than it
    won (bench/run.py: 2 intra-op threads were slower than 1 on the shared machine).
    """

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None,
                 chunk: int = DEFAULT_CHUNK):
        self.path = Path(path)
        self.session = _open_session(self.path, 1)
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        self.chunk = int(chunk)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()
        inputs = {i.name: i for i in self.session.get_inputs()}
        missing = {"points", "z", "seed"} - inputs.keys()
        if missing:
            raise ModelInvalid(f"{self.path.name} lacks inputs {sorted(missing)}")
        # Contract allows seed of shape [] or [1]; feed whatever the graph declares.
        self._seed_shape = (1,) if len(inputs["seed"].shape) == 1 else ()
        self.code_size = int(inputs["z"].shape[1]) if isinstance(inputs["z"].shape[1], int) else 8
        # Samplers exported before the colour stage have no ``colour`` input (size 0): they
        # are served as they were, and a texture's colour table is dropped for them.
        colour = inputs.get("colour")
        self.colour_size = int(colour.shape[1]) if colour is not None else 0
        self._identity_colour = identity_colour(self.colour_size)[None] if self.colour_size else None
        self.periodic = "period" in inputs
        self._output = self.session.get_outputs()[0].name

    def sample(self, points: np.ndarray, code: np.ndarray, seed: int, *,
               period: float | None = None) -> np.ndarray:
        """Evaluate the texture at ``points``.

        points : (P, 3) float64 world positions (converted only if needed).
        code : (C,) or (1, C) float32 shared code, or (P, C) one code per point, where C is
            ``code_size`` (z alone: the identity colour table) or ``code_size +
            colour_size`` (z followed by the texture's colour table, worker/colour_match.py).
        seed : int, texture instance.
        period : float, world units; required by a tileable sampler (``.periodic``), refused
            by the others. The texture then repeats every ``period`` along x and y.
        Returns (P, 3) float32 linear RGB, computed ``self.chunk`` points at a time so
        temporary memory stays bounded whatever P is.
        """
        if self.periodic != (period is not None):
            raise InvalidParameter(f"{self.path.name}: a period is "
                                   f"{'required' if self.periodic else 'only for a tileable sampler'}")
        if period is not None and not (np.isfinite(period) and period > 0):
            raise InvalidParameter(f"period must be a positive number of world units, got {period}")
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InvalidParameter(f"points must have shape (P, 3), got {points.shape}")
        code = np.asarray(code, dtype=np.float32)
        if code.ndim == 1:
            code = code[None, :]
        per_point = code.shape[0] != 1
        widths = {self.code_size, self.code_size + self.colour_size}
        # a sampler without a colour stage ignores a texture's table
        width_ok = code.shape[1] in widths or (not self.colour_size and code.shape[1] > self.code_size)
        if code.ndim != 2 or not width_ok or (per_point and code.shape[0] != len(points)):
            raise InvalidParameter(f"code must be (C,), (1, C) or (P, C) with C in {sorted(widths)}; "
                                   f"got {code.shape}")
        z = np.ascontiguousarray(code[:, :self.code_size])
        colour = None
        if self.colour_size:
            colour = (np.ascontiguousarray(code[:, self.code_size:]) if code.shape[1] > self.code_size
                      else self._identity_colour)
            # Fitted samplers exported before 2026-12-02 took z and colour with the same rows
            # only (a shared table beside per-point codes failed there); they are still stored.
            if per_point and len(colour) == 1:
                colour = np.broadcast_to(colour, (len(points), self.colour_size))
        seed_arr = np.full(self._seed_shape, int(seed), dtype=np.int64)
        extra = {} if period is None else {"period": np.array(period, dtype=np.float64)}
        out = np.empty((len(points), 3), dtype=np.float32)

        def run(start: int) -> None:
            stop = min(start + self.chunk, len(points))
            feed = {"points": points[start:stop], "seed": seed_arr,
                    "z": z[start:stop] if per_point else z, **extra}
            if colour is not None:
                feed["colour"] = np.ascontiguousarray(colour[start:stop] if per_point else colour)
            out[start:stop] = self.session.run([self._output], feed)[0]

        starts = range(0, len(points), self.chunk)
        if self.threads == 1 or len(starts) == 1:
            for start in starts:
                run(start)
        else:
            for _ in self._executor().map(run, starts):  # re-raises a chunk's error
                pass
        return out

    def _executor(self) -> ThreadPoolExecutor:
        with self._pool_lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="sampler")
            return self._pool


class PeriodicSampler:
    """A tileable sampler with its period bound: a ``Sampler`` whose texture repeats every
    ``period`` world units along x and y. An image of N x N pixels at the native zoom
    (``pixels_per_unit`` per unit) with ``period = N / pixels_per_unit`` tiles seamlessly."""

    def __init__(self, session: SamplerSession, period: float):
        if not getattr(session, "periodic", False):
            raise InvalidParameter(f"{getattr(session, 'path', session)} is not a tileable sampler "
                                   f"({TILEABLE_SAMPLER})")
        if not (np.isfinite(period) and period > 0):
            raise InvalidParameter(f"period must be a positive number of world units, got {period}")
        self.session, self.period = session, float(period)

    def sample(self, points: np.ndarray, code: np.ndarray, seed: int) -> np.ndarray:
        """See ``SamplerSession.sample``, with this period."""
        return self.session.sample(points, code, seed, period=self.period)


def periodic_sampler(sampler: Sampler, period: float) -> PeriodicSampler:
    """``sampler`` made to repeat every ``period`` world units in x and y: a tileable
    ``SamplerSession`` itself, or a ``ModelRuntime``'s tileable sampler."""
    if hasattr(sampler, "tileable_sampler"):
        sampler = sampler.tileable_sampler()
    return PeriodicSampler(sampler, period)


def read_manifest(model_dir: Path) -> dict:
    """Read and check ``manifest.json`` (all keys of docs/ARCHITECTURE.md required)."""
    path = model_dir / "manifest.json"
    if not path.is_file():
        raise ModelNotFound(f"no manifest.json in {model_dir}")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ModelInvalid(f"unreadable manifest {path}: {exc}") from exc
    missing = [k for k in MANIFEST_KEYS if k not in manifest]
    if missing:
        raise ModelInvalid(f"manifest {path} lacks keys {missing}")
    if manifest["output_colour"] != "linear":
        raise ModelInvalid(f"manifest {path}: output_colour must be 'linear'")
    return manifest


def model_version(model_dir: Path) -> str:
    """16 hex chars of sha256(encoder.onnx bytes + sampler.onnx bytes)."""
    digest = hashlib.sha256()
    for name in ("encoder.onnx", "sampler.onnx"):
        digest.update((model_dir / name).read_bytes())
    return digest.hexdigest()[:16]


class ModelRuntime:
    """Encoder + sampler of one model version, loaded once.

    ``.version``, ``.manifest``, ``.pixels_per_unit``, ``.encode()``, ``.sample()``, ``.ready()``.
    """

    def __init__(self, model_dir: str | os.PathLike, threads: int | None = None, *,
                 chunk: int = DEFAULT_CHUNK):
        self.model_dir = Path(model_dir)
        self.manifest = read_manifest(self.model_dir)
        self.version: str = self.manifest["version"]
        actual = model_version(self.model_dir)
        if actual != self.version:
            # The manifest names the model everywhere (ETags, rows); a mismatch means
            # files were swapped by hand. Serve it, but say so loudly.
            log.warning("model %s: manifest version %s != file hash %s",
                        self.model_dir, self.version, actual)
        self.pixels_per_unit = float(self.manifest["pixels_per_unit"])
        self.code_size = int(self.manifest["code_size"])
        self.input_size = int(self.manifest["encoder_input_size"])
        self.short_side = int(self.manifest["exemplar_short_side"])
        self.encoder = _open_session(self.model_dir / "encoder.onnx", threads)
        self.sampler = SamplerSession(self.model_dir / "sampler.onnx", threads=threads, chunk=chunk)
        self._threads, self._chunk = threads, chunk
        self._tileable: SamplerSession | None = None
        self._open_lock = threading.Lock()
        self._style: ort.InferenceSession | None = None

    def _manifest_file(self, key: str) -> Path | None:
        """The file the manifest names under ``key``, beside it; None if unnamed or absent."""
        name = self.manifest.get(key)
        path = self.model_dir / Path(str(name)).name if name else None
        return path if path is not None and path.is_file() else None

    @property
    def tileable_path(self) -> Path | None:
        """The export's tileable sampler file, None if it has none (an older export)."""
        return self._manifest_file("tileable_sampler")

    def tileable_sampler(self) -> SamplerSession:
        """The tileable sampler (``period`` input), opened on first use; FeatureUnavailable
        if this export has none."""
        if self._tileable is None:
            path = self.tileable_path
            if path is None:
                raise FeatureUnavailable(f"model {self.version} has no tileable sampler ({TILEABLE_SAMPLER}): "
                                         "it was exported before tileable textures; re-export it "
                                         "(python -m model.export)")
            with self._open_lock:
                if self._tileable is None:
                    session = SamplerSession(path, threads=self._threads, chunk=self._chunk)
                    if not session.periodic:
                        raise ModelInvalid(f"{path.name} has no period input")
                    self._tileable = session
        return self._tileable

    @property
    def style_path(self) -> Path | None:
        """The export's style statistics (``style.onnx``), None if it has none (an older
        export: its uploads keep the mean of their crops' codes)."""
        return self._manifest_file("style_features")

    def style(self, images: np.ndarray, batch: int = 4) -> np.ndarray:
        """images : (N, H, W, 3) sRGB 0..1 -> (N, D) float32 style vectors: the squared distance
        of two is the Gram loss between their images (``model.export.StyleGraph``).
        FeatureUnavailable if this export has no style statistics."""
        if self._style is None:
            path = self.style_path
            if path is None:
                raise FeatureUnavailable(f"model {self.version} has no style statistics ({STYLE_FEATURES}): "
                                         "re-export it (python -m model.export)")
            with self._open_lock:
                if self._style is None:
                    # no arena: an upload's choice runs it once, and its activations (~0.1 GB
                    # a batch) would otherwise stay held in the API process for good
                    self._style = _open_session(path, self._threads, arena=False)
        chw = np.ascontiguousarray(np.asarray(images, np.float32).transpose(0, 3, 1, 2))
        return np.concatenate([self._style.run(None, {"image": chw[i:i + batch]})[0]
                               for i in range(0, len(chw), batch)])

    def encode(self, crops: np.ndarray, batch: int = 16) -> np.ndarray:
        """crops : (N, 3, S, S) float32 in [-1, 1] (S = encoder_input_size). Returns (N, code_size) float32."""
        crops = np.ascontiguousarray(crops, dtype=np.float32)
        s = self.input_size
        if crops.ndim != 4 or crops.shape[1:] != (3, s, s):
            raise InvalidParameter(f"crops must be (N, 3, {s}, {s}), got {crops.shape}")
        name = self.encoder.get_inputs()[0].name
        parts = [self.encoder.run(None, {name: crops[i:i + batch]})[0]
                 for i in range(0, len(crops), batch)]
        return np.concatenate(parts).astype(np.float32, copy=False)

    def sample(self, points: np.ndarray, code: np.ndarray, seed: int) -> np.ndarray:
        """See ``SamplerSession.sample``."""
        return self.sampler.sample(points, code, seed)

    def ready(self) -> bool:
        """True when a one-point evaluation works (for health checks)."""
        try:
            rgb = self.sample(np.zeros((1, 3)), np.zeros(self.code_size, np.float32), 0)
        except Exception:  # health check: any failure means not ready
            log.exception("model %s not ready", self.version)
            return False
        return bool(np.isfinite(rgb).all())


def find_model_dirs(folders: Iterable[str | os.PathLike]) -> list[Path]:
    """Each folder that holds a manifest.json, or its immediate subfolders that do."""
    found = []
    for folder in map(Path, folders):
        if (folder / "manifest.json").is_file():
            found.append(folder)
        elif folder.is_dir():
            found.extend(sorted(p.parent for p in folder.glob("*/manifest.json")))
    return found


class ModelRegistry:
    """Several model versions side by side, plus an LRU of fitted-texture samplers."""

    def __init__(self, folders: Iterable[str | os.PathLike], *, default: str | None = None,
                 threads: int | None = None, max_fitted: int = 8):
        self.threads = threads
        self.models: dict[str, ModelRuntime] = {}
        for model_dir in find_model_dirs(folders):
            runtime = ModelRuntime(model_dir, threads)
            self.models.setdefault(runtime.version, runtime)
        if not self.models:
            raise ModelNotFound(f"no model directory (with manifest.json) under {list(map(str, folders))}")
        if default is None:  # newest export wins
            default = max(self.models.values(), key=lambda m: str(m.manifest["created_at"])).version
        self.default = self.get(default)
        self._fitted: OrderedDict[str, SamplerSession] = OrderedDict()
        self._max_fitted = max_fitted
        self._lock = threading.Lock()

    def get(self, version: str | None = None) -> ModelRuntime:
        """The runtime of ``version`` (the default one if None); ModelNotFound otherwise."""
        if version is None:
            return self.default
        try:
            return self.models[version]
        except KeyError:
            raise ModelNotFound(f"model version {version!r} is not loaded (have {sorted(self.models)}); its "
                                "textures come back when it is loaded again or moved with `texspace reencode`") from None

    def fitted_sampler(self, path: str | os.PathLike) -> SamplerSession:
        """A fitted texture's own sampler.onnx (or its sampler_tileable.onnx), opened once and
        kept in a small LRU."""
        key = str(Path(path).resolve())
        with self._lock:
            if key in self._fitted:
                self._fitted.move_to_end(key)
                return self._fitted[key]
        session = SamplerSession(key, threads=self.threads)  # load outside the lock
        with self._lock:
            self._fitted[key] = session
            self._fitted.move_to_end(key)
            while len(self._fitted) > self._max_fitted:
                self._fitted.popitem(last=False)
        return session

    def ready(self) -> bool:
        """True when every loaded model answers a one-point evaluation."""
        return all(m.ready() for m in self.models.values())
