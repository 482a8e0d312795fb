"""The ``texspace`` command: processes (api, worker, serve, migrate) and offline tools
(encode, tile, volume, bake, tileable, shader) that work without a server.

As careful as the API: the offline tools take the API's ranges and the same
``TEXSPACE_MAX_*`` limits; an output's format follows its ``-o`` extension (a
``--format`` that disagrees is refused); every refusal is one line on stderr and exit
status 2 (bad input) or 1 (the work failed), never a traceback, with nothing written.
"""
from __future__ import annotations

import argparse
import atexit
import json
import logging
import math
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from worker.bake import BAKE_FORMATS
from worker.contract import (DETAIL_SECONDS, MAX_BAKE_RESOLUTION, MAX_VOLUME_RESOLUTION, MIN_BAKE_RESOLUTION,
                             MIN_VOLUME_RESOLUTION)
from worker.files import extensions
from worker.gpu_textures import DDS_COMPRESSIONS
from worker.photo import LIGHTING
from worker.regions import REGION_FORMATS
from worker.shader import LANGUAGES
from worker.tiles import COORD_LIMIT, NATIVE_ZOOM, PLANES, TILE_FORMATS
from worker.volume_writers import VOLUME_FORMATS

from . import auth, db, processes
from .context import build_services
from .logs import setup_logging
from .samplers import sampler_inputs
from .schemas import BAKE_PROJECTIONS, FitIn, bake_projection
from .settings import FIT_SECONDS, MAX_FIT_SECONDS, Settings
from .tables import Texture

log = logging.getLogger(__name__)

#: the API's ranges (service/deps.py, service/schemas.py, routes/jobs.py); TEXSPACE_MAX_*
#: settings lower the upper ends further, as they do for the API
SEED_MAX = 2**31 - 1
OFFSET_LIMIT = 1e9
SCALE_MAX = 1e6
#: the longest `upload --timeout`, seconds per photo: a wait of this client, no server limit
UPLOAD_WAIT_MAX = 60.0 * 60
#: output formats by extension (tile: the tile route's; bake: obj is a zip of obj + mtl + mtlx + png)
TILE_EXTENSIONS = extensions(TILE_FORMATS)
BAKE_EXTENSIONS = extensions(BAKE_FORMATS)
TILEABLE_EXTENSIONS = extensions(f for f in REGION_FORMATS if f != "pyramid")
SHADER_EXTENSIONS = extensions(LANGUAGES)
VOLUME_EXTENSIONS = extensions(VOLUME_FORMATS)
#: the files ``upload`` takes from a folder: the photo formats the API reads
UPLOAD_EXTENSIONS = frozenset(ext for exts in extensions(("png", "jpeg", "tiff", "exr", "webp", "gif", "bmp")).values()
                              for ext in exts) | {".jpeg"}
#: refusals of the input (exit 2); every other domain error is a failure of the work (exit 1)
INPUT_ERRORS = ("InvalidImage", "InvalidMesh", "InvalidParameter", "LimitExceeded")


class CliError(Exception):
    """A refusal: one line on stderr and exit ``code`` (2: bad input, 1: the work failed)."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, unless there is none or the help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if any(action.default is v for v in (None, False, argparse.SUPPRESS)) or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def ranged(kind: type, lo: float | None = None, hi: float | None = None, *, above: bool = False):  # noqa: ANN201
    """argparse ``type=``: an int or finite float in [lo, hi] ((lo, hi] with ``above``)."""

    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{'an integer' if kind is int else 'a number'} is needed, "
                                             f"got {text!r}") from None
        low_ok = lo is None or (value > lo if above else value >= lo)
        if not math.isfinite(value) or not low_ok or (hi is not None and value > hi):
            show = (lambda v: f"{v:g}") if kind is float else str
            interval = f"{'(' if above else '['}{show(lo)}, {show(hi)}]"
            raise argparse.ArgumentTypeError(f"must be in {interval}, got {text}")
        return value

    return parse


def _settings(args: argparse.Namespace) -> Settings:
    """Settings from the environment; flags override (and reach child processes)."""
    for flag, env in (("data_dir", "TEXSPACE_DATA_DIR"), ("host", "TEXSPACE_HOST"),
                      ("port", "TEXSPACE_PORT"), ("workers", "TEXSPACE_WORKERS")):
        value = getattr(args, flag, None)
        if value is not None:
            os.environ[env] = str(value)
    from pydantic import ValidationError

    try:
        return Settings()
    except ValidationError as exc:
        problems = "; ".join(f"TEXSPACE_{'_'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in exc.errors())
        raise CliError(f"bad setting: {problems}") from None


def _registry(settings: Settings):  # noqa: ANN202
    from worker.runtime import ModelRegistry

    return ModelRegistry(settings.model_dirs, default=settings.default_model_version)


def _sqlite_file(url: str) -> Path | None:
    """The database file of a SQLite URL (None for other databases and :memory:)."""
    if url.startswith("sqlite:///") and url != "sqlite:///:memory:":
        return Path(url[len("sqlite:///"):])
    return None


class TextureSource:
    """A texture named on the command line: an image file (encoded now, and with ``refine``
    seconds fitted as an upload's refinement is) or a stored id. Looking an id up never
    creates a database: a mistyped path is refused instead. ``zoom`` (a tile's): above the
    native one, the fit's detail sampler (and its tileable twin) draws (model/detail.py; ``refine``
    then runs the fit's detail stage too, for a photo of twice the working size and more)."""

    def __init__(self, settings: Settings, ref: str, lighting: str = "as-is", refine: float | None = None,
                 zoom: int | None = None) -> None:
        path = Path(ref)
        above_native = zoom is not None and zoom > NATIVE_ZOOM
        if path.is_file():
            self._encode(settings, path, lighting)
            if refine:
                self._refine(settings, path, lighting, refine, DETAIL_SECONDS if above_native else 0.0)
            return
        if refine:
            raise CliError(f"--refine applies to an image file; a stored texture ({ref!r}) is refined by the "
                           "service (its refinement, or POST /v1/textures/{id}/fit)")
        url = settings.resolved_database_url
        database = _sqlite_file(url)
        if database is not None and not database.is_file():  # a mistyped path: no database made for it
            raise CliError(f"{ref!r} is neither an image file nor a texture id (no database at {database})")
        if path.exists():
            raise CliError(f"{ref!r} is a folder, not an image file")
        services = build_services(settings, immediate=True)
        services._registry = _registry(settings)
        with db.session_scope(services.sessions) as session:
            texture = session.get(Texture, ref)
        if texture is None:
            raise CliError(f"{ref!r} is neither an image file nor a texture id in {url}")
        inputs = sampler_inputs(services, texture, zoom=zoom)
        self.z = np.asarray(texture.code, np.float32)
        self.sampler, self.code, self.ppu = inputs.sampler, inputs.code, inputs.pixels_per_unit
        self.model_version = texture.model_version
        self.structure = texture.served_structure()
        self.tileable_sampler = lambda: ((above_native and services.detail_sampler_for(texture, tileable=True))
                                         or services.tileable_sampler_for(texture))

    def _encode(self, settings: Settings, path: Path, lighting: str) -> None:
        from worker.colour_match import texture_vector
        from worker.encode import encode_texture
        from worker.images import read_image

        if path.stat().st_size > settings.max_upload_bytes:
            raise CliError(f"{path}: {path.stat().st_size} bytes exceeds the limit of {settings.max_upload_bytes} "
                           "(TEXSPACE_MAX_UPLOAD_BYTES)")
        with _quiet_native_stderr():  # libpng prints its own line before the error we report
            image = read_image(path.read_bytes(), max_pixels=settings.max_image_pixels)
        runtime = _registry(settings).get(settings.default_model_version)
        self.z, colour = encode_texture(runtime, image, lighting)
        self.code, self.sampler, self.ppu = texture_vector(self.z, colour), runtime, runtime.pixels_per_unit
        self.model_version = runtime.version
        self.structure = None
        self.tileable_sampler = runtime.tileable_sampler
        self.image = image

    def _refine(self, settings: Settings, path: Path, lighting: str, seconds: float, detail_seconds: float) -> None:
        """Fit the photo for ``seconds`` (model.fit, the train extra) and draw with the fitted
        sampler, its code and a colour table made for it, as a refined upload is drawn; with
        ``detail_seconds``, the fit's detail sampler where its stage made one."""
        try:
            from model.fit import fit_exemplar  # torch lives in model/, imported only here
        except ImportError:
            raise CliError("--refine needs PyTorch: pip install 'texspace[train]'", code=1) from None
        from worker.colour_match import texture_vector
        from worker.contract import DETAIL_SAMPLER, DETAIL_TILEABLE_SAMPLER, TILEABLE_SAMPLER
        from worker.photo import working_photo

        from .job_kinds import fit_structure, fitted_colour, photo_to_fit

        registry = _registry(settings)
        runtime = registry.get(settings.default_model_version)
        checkpoint = runtime.model_dir / "space.pt"
        if not checkpoint.is_file():
            raise CliError(f"model {runtime.version} ships no space.pt checkpoint to refine from", code=1)
        image = working_photo(self.image, runtime.short_side, lighting)  # as the encoding saw it
        folder = Path(tempfile.mkdtemp(prefix="texspace-refine-"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)  # the samplers are read until the end
        photo = photo_to_fit(path, image, lighting, folder)  # as the service's fit sees it
        # the structure an upload's fit builds in (grain, lattice, even, lean: FitIn's defaults, "auto");
        # fit_exemplar's own defaults leave grain and lattice off, and a brick photo came out without bricks
        structure = FitIn().model_dump(include={"grain", "lattice", "even", "lean"})
        bar, report = _progress_bar(f"refine ({seconds:g} s)")
        with bar, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the ONNX exporter's tracer warnings say nothing to a user
            fitted = fit_exemplar(photo, folder / "fit", init_checkpoint=checkpoint, minutes=seconds / 60.0,
                                  progress=report, threads=settings.fit_threads, device=settings.fit_device,
                                  precision=settings.fit_precision, detail_seconds=detail_seconds, **structure)
        code = json.loads((folder / "fit" / "code.json").read_text())["code"]
        self.sampler = registry.fitted_sampler(folder / "fit" / "sampler.onnx")
        colour = fitted_colour(self.sampler, code, image)
        self.z, self.code = np.asarray(code, np.float32), texture_vector(code, colour)
        self.structure = fit_structure(fitted)
        self.tileable_sampler = lambda: registry.fitted_sampler(folder / "fit" / TILEABLE_SAMPLER)
        if (folder / "fit" / DETAIL_SAMPLER).is_file():  # (its colour table is the fit's, made above)
            self.sampler = registry.fitted_sampler(folder / "fit" / DETAIL_SAMPLER)
            self.tileable_sampler = lambda: registry.fitted_sampler(folder / "fit" / DETAIL_TILEABLE_SAMPLER)


@contextmanager
def _quiet_native_stderr() -> Iterator[None]:
    """Silence what C libraries write to file descriptor 2 (Python's own errors still raise)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def output(args: argparse.Namespace, extensions: dict[str, tuple[str, ...]], stem: str) -> tuple[Path, str]:
    """(path, format) of a command's output. The format follows ``-o``'s extension;
    ``--format`` must agree with it; without ``-o``, ``stem`` + the format's extension.
    The folder must exist (nothing is created before the work succeeds)."""
    default = next(iter(extensions))
    if args.output is None:
        fmt = args.format or default
        return Path(f"{stem}{extensions[fmt][0]}"), fmt
    out = Path(args.output)
    if out.is_dir():
        raise CliError(f"-o {out} is a folder; name a file in it")
    by_suffix = {ext: fmt for fmt, exts in extensions.items() for ext in exts}
    guessed = by_suffix.get(out.suffix.lower())
    known = ", ".join(f"{exts[0]} ({fmt})" for fmt, exts in extensions.items())
    if args.format is not None and guessed != args.format:
        raise CliError(f"-o {out}: a {args.format} file ends in {' or '.join(extensions[args.format])}, "
                       f"not {out.suffix or 'no extension'!r}")
    if guessed is None:
        raise CliError(f"-o {out}: cannot tell the format from {out.suffix or 'no extension'!r}; use {known}")
    if not out.parent.is_dir():
        raise CliError(f"-o {out}: the folder {out.parent} does not exist")
    return out, guessed


def _at_most(value: int, limit: int, what: str, env: str) -> None:
    if value > limit:
        raise CliError(f"{what} {value} exceeds the limit of {limit} ({env})")


def _progress_bar(description: str):  # noqa: ANN202
    from tqdm import tqdm

    bar = tqdm(total=100, desc=description, unit="%", file=sys.stderr, disable=None)

    def report(fraction: float) -> None:
        bar.n = round(100 * fraction, 1)
        bar.refresh()

    return bar, report


def cmd_api(args: argparse.Namespace, settings: Settings) -> None:
    processes.run_api(settings)


def cmd_worker(args: argparse.Namespace, settings: Settings) -> None:
    processes.run_worker(settings, migrate=not args.no_migrate)


def cmd_serve(args: argparse.Namespace, settings: Settings) -> None:
    processes.run_serve(settings)


def cmd_migrate(args: argparse.Namespace, settings: Settings) -> None:
    settings.ensure_dirs()
    db.migrate(settings.resolved_database_url)
    print(f"database at head: {settings.resolved_database_url}")


def cmd_reencode(args: argparse.Namespace, settings: Settings) -> None:
    """``texspace reencode [--from VERSION]... [--to VERSION] [--dry-run]``: move textures onto
    a loaded model (:mod:`service.reencode`); refinements go to the queue for the workers.
    ``--stale-codes``: choose again the codes of uploads made by an older choice recipe."""
    from worker.errors import ModelNotFound

    from .reencode import choose_codes_again, reencode_textures

    services = build_services(settings)
    if args.stale_codes:
        if args.versions or args.to:
            raise CliError("--stale-codes chooses codes again on the textures' own models: drop --from and --to")
        choice = choose_codes_again(services, dry_run=args.dry_run)
        verb = "would choose" if args.dry_run else "chose"
        print(f"{verb} the codes of {len(choice.encoded)} uploads again (their photos encoded again on their own "
              f"models) and {'would mix' if args.dry_run else 'mixed'} {len(choice.blended)} blends again")
        _report_skipped(choice.skipped, args.dry_run, "chosen again")
        return
    try:
        report = reencode_textures(services, set(args.versions) if args.versions else None, target=args.to,
                                   dry_run=args.dry_run)
    except ModelNotFound as exc:
        raise CliError(str(exc)) from None
    verb = "would move" if args.dry_run else "moved"
    print(f"{verb} {len(report.encoded)} textures (photo encoded again) and {len(report.blended)} blends "
          f"onto model {report.target}; {len(report.refinements)} refinements "
          f"{'would be ' if args.dry_run else ''}queued")
    _report_skipped(report.skipped, args.dry_run, "moved")


def _report_skipped(skipped: dict[str, str], dry_run: bool, done: str) -> None:
    """Print each texture a maintenance run left as it was, and why; exit 1 for a real run."""
    for texture_id, why in skipped.items():
        print(f"skipped {texture_id}: {why}")
    if skipped and not dry_run:
        raise CliError(f"{len(skipped)} textures were not {done} (listed above)", code=1)


def cmd_recolour(args: argparse.Namespace, settings: Settings) -> None:
    """``texspace recolour [--dry-run]``: compute stale colour tables again with today's
    recipe (:mod:`service.recolour`); codes and samplers stay."""
    from .recolour import recolour_textures

    report = recolour_textures(build_services(settings), dry_run=args.dry_run)
    verb = "would recolour" if args.dry_run else "recoloured"
    print(f"{verb} {len(report.recoloured)} textures (from their photos) and {len(report.blended)} blends "
          f"with colour calibration {report.calibration}")
    _report_skipped(report.skipped, args.dry_run, "recoloured")


def cmd_encode(args: argparse.Namespace, settings: Settings) -> None:
    source = TextureSource(settings, args.image, args.lighting)
    print(json.dumps({"code": [round(float(c), 7) for c in source.z], "model_version": source.model_version}))


def cmd_tile(args: argparse.Namespace, settings: Settings) -> None:
    from worker.images import write_image
    from worker.tiles import render_tile

    from .tiles import check_tile_work

    out, fmt = output(args, TILE_EXTENSIONS, f"tile-{args.z}-{args.x}-{args.y}")
    _at_most(args.size, settings.max_tile_size, "tile size", "TEXSPACE_MAX_TILE_SIZE")
    check_tile_work(settings, args.z, args.size)
    source = TextureSource(settings, args.texture, args.lighting, args.refine, zoom=args.z)
    rgb = render_tile(source.sampler, source.code, args.seed, args.z, args.x, args.y, args.size,
                      pixels_per_unit=source.ppu, plane=args.plane, offset=args.offset)
    out.write_bytes(write_image(rgb, fmt))
    print(out)


def cmd_volume(args: argparse.Namespace, settings: Settings) -> None:
    from worker.volumes import render_volume

    out, fmt = output(args, VOLUME_EXTENSIONS, f"volume-{args.resolution}")
    _at_most(args.resolution, settings.max_volume_resolution, "resolution", "TEXSPACE_MAX_VOLUME_RESOLUTION")
    bounds = np.asarray(args.bounds, np.float64).reshape(2, 3)
    if (np.abs(bounds) >= OFFSET_LIMIT).any() or not (bounds[1] > bounds[0]).all():
        raise CliError("--bounds: coordinates below 1e9 in magnitude, and X1 > X0, Y1 > Y0, Z1 > Z0")
    source = TextureSource(settings, args.texture, args.lighting, args.refine)
    bar, report = _progress_bar("volume")
    with bar:
        path = render_volume(source.sampler, source.code, args.seed, resolution=args.resolution,
                             bounds=bounds, fmt=fmt, out_path=out, progress=report)
    print(path)


def cmd_bake(args: argparse.Namespace, settings: Settings) -> None:
    from worker.bake import bake_mesh

    from .limits import bake_limits, check_mesh

    mesh = Path(args.mesh)
    if not mesh.is_file():
        raise CliError(f"{args.mesh}: no such mesh file")
    out, fmt = output(args, BAKE_EXTENSIONS, f"{mesh.stem}-baked")
    _at_most(args.resolution, settings.max_bake_resolution, "resolution", "TEXSPACE_MAX_BAKE_RESOLUTION")
    _at_most(mesh.stat().st_size, settings.max_mesh_bytes, f"{mesh}: size in bytes", "TEXSPACE_MAX_MESH_BYTES")
    data = mesh.read_bytes()
    check_mesh(settings, data, mesh.name)  # as the API does at submission, before any work
    source = TextureSource(settings, args.texture, args.lighting, args.refine)
    bar, report = _progress_bar("bake")
    with bar:
        result = bake_mesh(source.sampler, source.code, args.seed, mesh_bytes=data, filename=mesh.name,
                           resolution=args.resolution, scale=args.scale, fmt=fmt, out_path=out,
                           pixels_per_unit=source.ppu, limits=bake_limits(settings), progress=report,
                           projection=bake_projection(args.projection, source.structure))
    print(result.path)


def cmd_tileable(args: argparse.Namespace, settings: Settings) -> None:
    """A seamlessly tiling square image (the API's region with ``tileable: true``)."""
    from worker.regions import RegionLimits, render_region

    out, fmt = output(args, TILEABLE_EXTENSIONS, f"tileable-{args.size}")
    if args.dds_compression != "bc1" and fmt != "dds":
        raise CliError(f"--dds-compression {args.dds_compression} applies to a .dds output only")
    _at_most(args.size * args.size, settings.max_region_pixels, "pixels", "TEXSPACE_MAX_REGION_PIXELS")
    source = TextureSource(settings, args.texture, args.lighting, args.refine, zoom=NATIVE_ZOOM + args.zoom)
    bar, report = _progress_bar("tileable")
    with bar:
        path = render_region(source.tileable_sampler(), source.code, args.seed, z=NATIVE_ZOOM + args.zoom, x0=0, y0=0,
                             width=args.size, height=args.size, fmt=fmt, out_path=out, pixels_per_unit=source.ppu,
                             tileable=True, dds_compression=args.dds_compression,
                             limits=RegionLimits(max_pixels=settings.max_region_pixels),
                             progress=report)
    print(path)


def cmd_shader(args: argparse.Namespace, settings: Settings) -> None:
    """The texture as GLSL ES 3.00 or WGSL source (the API's ``shader.glsl`` / ``.wgsl``)."""
    from worker.shader import emit_shader, shader_name

    out, fmt = output(args, SHADER_EXTENSIONS, "shader")
    source = TextureSource(settings, args.texture, args.lighting, args.refine)
    sampler = getattr(source.sampler, "sampler", source.sampler)  # a model's runtime, or a fitted sampler
    ref = Path(args.texture)
    name = shader_name(ref.stem if ref.is_file() else args.texture)
    text = emit_shader(sampler.path, source.code, name, fmt,
                       header=f"texspace texture {ref.name if ref.is_file() else args.texture}, "
                              f"model {source.model_version}")
    out.write_text(text)
    print(out)


def cmd_keys(args: argparse.Namespace, settings: Settings) -> None:
    """``texspace keys create NAME [--note] | list | revoke KEY_ID`` (see :mod:`service.auth`)."""
    services = build_services(settings, immediate=True)
    if args.action == "create":
        row, key = auth.create_key(services, args.name, args.note)
        print(f"id:  {row.id}\nkey: {key}\n(store the key now: only its hash is kept)")
    elif args.action == "list":
        for row in auth.list_keys(services):
            state = f"revoked {row.revoked_at:%Y-%m-%d %H:%M}" if row.revoked_at else "active"
            print(f"{row.id}  {state:<24} {row.created_at:%Y-%m-%d %H:%M}  {row.name}")
    elif not auth.revoke_key(services, args.key_id):
        raise CliError(f"no active key with id {args.key_id!r}", code=1)
    else:
        print(f"revoked {args.key_id}")


def upload_files(paths: list[str]) -> list[Path]:
    """The image files named by ``paths``: each file as given, each folder's image files
    (by extension, ``UPLOAD_EXTENSIONS``; not its subfolders) in name order."""
    found: list[Path] = []
    for given in paths:
        path = Path(given)
        if path.is_dir():
            found += sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in UPLOAD_EXTENSIONS)
        elif path.is_file():
            found.append(path)
        else:
            raise CliError(f"{given}: no such file or folder")
    return found


def _api_client(url: str, api_key: str | None, timeout: float):  # noqa: ANN202 (service.client.Client)
    """The HTTP client ``upload`` talks to the server with (tests give it the app's transport)."""
    from .client import Client

    return Client(url, api_key=api_key, timeout=timeout)


def cmd_upload(args: argparse.Namespace, settings: Settings) -> None:
    """``texspace upload IMAGE|FOLDER ...``: upload photos to a running server one after
    another, a status line per file as each ends; exit 1 when any failed."""
    import httpx

    from .client import ApiError

    files = upload_files(args.images)
    if not files:
        raise CliError(f"no image files ({', '.join(sorted(UPLOAD_EXTENSIONS))}) in {' '.join(args.images)}")
    if args.name is not None and len(files) > 1:
        raise CliError("--name names one upload; with several files each is named after its file")
    url = args.url or os.environ.get("TEXSPACE_URL") or f"http://127.0.0.1:{settings.port}"
    failed = 0
    with _api_client(url, args.api_key or os.environ.get("TEXSPACE_API_KEY"), args.timeout) as ts:
        for number, path in enumerate(files, 1):
            where = f"[{number}/{len(files)}] {path}"
            try:
                texture = ts.upload(path, name=args.name, lighting=args.lighting)
            except ApiError as exc:
                failed += 1
                print(f"{where}: failed: {_one_line(exc)}", flush=True)
            except httpx.TransportError as exc:
                raise CliError(f"cannot reach the server at {url} ({_one_line(exc)}); {number - 1} of "
                               f"{len(files)} uploaded (TEXSPACE_URL or --url names the server)", code=1) from None
            else:
                print(f"{where}: texture {texture['id']} ({texture.get('name') or path.name})", flush=True)
    if failed:
        raise CliError(f"{failed} of {len(files)} uploads failed", code=1)


def build_parser() -> argparse.ArgumentParser:
    from worker.tiles import MAX_TILE_SIZE, MAX_ZOOM, MIN_TILE_SIZE, MIN_ZOOM, NATIVE_ZOOM

    fields = Settings.model_fields
    parser = Parser(prog="texspace", formatter_class=HelpFormatter,
                    description="processes (api, worker, serve, migrate, reencode, recolour), offline tools (encode, tile, "
                                "volume, bake, tileable, shader) that work without a server, and upload (to a server)",
                    epilog="An error is one line on stderr; exit status 2: bad input, 1: the work failed.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def proc(name: str, func, help_: str) -> argparse.ArgumentParser:  # noqa: ANN001
        p = sub.add_parser(name, help=help_, description=help_, formatter_class=HelpFormatter)
        p.add_argument("--data-dir", dest="data_dir", metavar="DIR",
                       help=f"overrides TEXSPACE_DATA_DIR (default: {fields['data_dir'].default})")
        p.set_defaults(func=func)
        return p

    for name, func, help_ in (("api", cmd_api, "run the HTTP API (uvicorn)"),
                              ("serve", cmd_serve, "run the API and one worker process (embedded default)")):
        p = proc(name, func, help_)
        p.add_argument("--host", help=f"overrides TEXSPACE_HOST (default: {fields['host'].default})")
        p.add_argument("--port", type=ranged(int, 1, 65535),
                       help=f"overrides TEXSPACE_PORT (default: {fields['port'].default})")
    p = proc("worker", cmd_worker, "consume the job queue")
    p.add_argument("--workers", type=ranged(int, 1, 1024),
                   help=f"threads, overrides TEXSPACE_WORKERS (default: {fields['workers'].default})")
    p.add_argument("--no-migrate", action="store_true", help="assume the database is migrated (default: migrate)")
    proc("migrate", cmd_migrate, "apply database migrations")
    p = proc("reencode", cmd_reencode, "move textures onto a loaded model: encode their photos again, mix "
                                       "blends again, queue refinements (after retiring a model)")
    p.add_argument("--from", dest="versions", action="append", metavar="VERSION",
                   help="textures of this model version (repeatable; default: of every model not loaded)")
    p.add_argument("--to", metavar="VERSION",
                   help="the model to move them to (default: TEXSPACE_DEFAULT_MODEL_VERSION, else the newest)")
    p.add_argument("--stale-codes", action="store_true",
                   help="instead: encode again, on their own models, the uploads whose code was chosen by an older "
                        "recipe (after an upgrade that says so); refined uploads keep their fits (default: move "
                        "textures off models not loaded)")
    p.add_argument("--dry-run", action="store_true", help="report what would move; change nothing (default: move them)")
    p = proc("recolour", cmd_recolour, "compute colour tables made by an older recipe again, from the textures' "
                                       "photos (after an upgrade that says so)")
    p.add_argument("--dry-run", action="store_true", help="report what would change; change nothing (default: recolour them)")

    def lighting_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument("--lighting", choices=LIGHTING, default="as-is",
                       help="an image file's lighting: even divides out its smooth shading (light falling off, a "
                            "vignette) before it is encoded (a stored texture keeps its own)")

    p = proc("encode", cmd_encode, "print the texture code of an image file or stored texture id")
    p.add_argument("image", help="IMAGE file or TEXTURE_ID (required)")
    lighting_arg(p)

    def refine_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument("--refine", nargs="?", type=ranged(float, 0, MAX_FIT_SECONDS, above=True), const=FIT_SECONDS,
                       metavar="SECONDS", help="an image file: fit it first, as an upload's refinement is, for "
                       f"SECONDS ({FIT_SECONDS:g} when not given), with a progress bar; needs the train extra "
                       "(PyTorch) (default: no fit, the encoder's code at once)")

    def texture_args(p: argparse.ArgumentParser, what: str, formats: dict[str, tuple[str, ...]], name: str) -> None:
        p.add_argument("--seed", type=ranged(int, 0, SEED_MAX), default=0,
                       help=f"texture instance, 0..{SEED_MAX}")
        exts = ", ".join(f"{exts[0]} = {fmt}" for fmt, exts in formats.items())
        first = next(iter(formats))
        p.add_argument("-o", "--output", metavar="FILE",
                       help=f"where to write the {what}; its extension picks the format ({exts}); the folder "
                            f"must exist (default: {name}{formats[first][0]} here)")
        p.add_argument("--format", choices=list(formats),
                       help=f"must agree with -o's extension (default: from -o's extension, else {first})")
        lighting_arg(p)
        refine_arg(p)

    p = proc("tile", cmd_tile, "render one tile of an image file or stored texture id")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID (required)")
    p.add_argument("z", type=ranged(int, MIN_ZOOM, MAX_ZOOM),
                   help=f"zoom {MIN_ZOOM}..{MAX_ZOOM}; at {NATIVE_ZOOM} a tile pixel is an exemplar pixel (required)")
    p.add_argument("x", type=ranged(int, -COORD_LIMIT, COORD_LIMIT), help="tile column, grows right (required)")
    p.add_argument("y", type=ranged(int, -COORD_LIMIT, COORD_LIMIT), help="tile row, grows down (required)")
    texture_args(p, "tile", TILE_EXTENSIONS, "tile-Z-X-Y")
    p.add_argument("--size", type=ranged(int, MIN_TILE_SIZE, MAX_TILE_SIZE), default=256,
                   help=f"tile side in pixels, {MIN_TILE_SIZE}..TEXSPACE_MAX_TILE_SIZE "
                        f"({fields['max_tile_size'].default} unless set)")
    p.add_argument("--plane", choices=PLANES, default="xy", help="which world plane the tile lies in")
    p.add_argument("--offset", type=ranged(float, -OFFSET_LIMIT, OFFSET_LIMIT), default=0.0,
                   help="plane position on the third axis, world units")

    p = proc("volume", cmd_volume, "render a solid N^3 block of an image file or stored texture id")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID (required)")
    texture_args(p, "volume", VOLUME_EXTENSIONS, "volume-N")
    p.add_argument("--resolution", type=ranged(int, MIN_VOLUME_RESOLUTION, MAX_VOLUME_RESOLUTION), default=64,
                   help=f"voxels per side N, {MIN_VOLUME_RESOLUTION}..TEXSPACE_MAX_VOLUME_RESOLUTION "
                        f"({fields['max_volume_resolution'].default} unless set)")
    p.add_argument("--bounds", type=ranged(float, -OFFSET_LIMIT, OFFSET_LIMIT), nargs=6,
                   default=[0.0, 0.0, 0.0, 1.0, 1.0, 1.0], metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="the world box, corner (X0 Y0 Z0) to corner (X1 Y1 Z1) (default: 0 0 0 1 1 1)")

    p = proc("bake", cmd_bake, "UV-unwrap a mesh and bake a texture into it")
    p.add_argument("mesh", help="OBJ, PLY, STL or GLB mesh file (by extension; required)")
    p.add_argument("--texture", required=True, help="IMAGE file or TEXTURE_ID (required)")
    texture_args(p, "bake", BAKE_EXTENSIONS, "MESH-baked")
    p.add_argument("--resolution", type=ranged(int, MIN_BAKE_RESOLUTION, MAX_BAKE_RESOLUTION), default=1024,
                   help=f"texture atlas side in pixels, {MIN_BAKE_RESOLUTION}..TEXSPACE_MAX_BAKE_RESOLUTION "
                        f"({fields['max_bake_resolution'].default} unless set)")
    p.add_argument("--scale", type=ranged(float, 0, SCALE_MAX, above=True),
                   help="world units per mesh unit (default: the mesh spans 512 exemplar pixels)")
    p.add_argument("--projection", choices=BAKE_PROJECTIONS, default="auto",
                   help="solid: the solid texture at each surface point; triplanar: its xy plane projected along "
                        "x, y and z; auto (default): triplanar for a texture fitted on a repeat lattice")

    p = proc("tileable", cmd_tileable, "render a seamlessly tiling square image of an image file or stored "
                                       "texture id (one pixel per exemplar pixel, or more with --zoom)")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID (required)")
    texture_args(p, "image", TILEABLE_EXTENSIONS, "tileable-SIZE")
    p.add_argument("--size", type=ranged(int, 64, 16384), default=1024,
                   help="side in pixels, up to TEXSPACE_MAX_REGION_PIXELS in all (dds, ktx2: 4096); the noise "
                        "octaves' frequencies are rounded to whole cells per side, so small sizes (256) change "
                        "the coarse features most")
    p.add_argument("--zoom", type=ranged(int, -2, 4), default=0,
                   help="zoom levels above the native one (0): 1 draws the same period's worth of texture in twice "
                        "the pixels per side")
    p.add_argument("--dds-compression", choices=DDS_COMPRESSIONS, default="bc1",
                   help="a .dds output's blocks: bc1 (default; BC1, the legacy header every DDS reader knows) or "
                        "bc7 (about half BC1's error; DX10 header, which Debian 12's Blender 3.4, ImageMagick 6 "
                        "and iinfo cannot read)")

    p = proc("shader", cmd_shader, "write an image file's or stored texture id's shader: GLSL ES 3.00 or WGSL "
                                   "function texspace_<id>(p, seed) -> linear RGB (docs/SHADER.md)")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID (required)")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="where to write it; .glsl or .wgsl picks the language (default: shader.glsl here)")
    p.add_argument("--format", choices=list(SHADER_EXTENSIONS),
                   help="must agree with -o's extension (default: from -o's extension, else glsl)")
    lighting_arg(p)
    refine_arg(p)

    p = proc("upload", cmd_upload, "upload photos (files, or every image in a folder) to a running server, one "
                                   "after another, a line per file; exit 1 when any failed")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files or folders of them (required)")
    p.add_argument("--url", help="the server (default: TEXSPACE_URL, else http://127.0.0.1:TEXSPACE_PORT)")
    p.add_argument("--api-key", dest="api_key", help="for a server with API keys on (default: TEXSPACE_API_KEY)")
    p.add_argument("--name", help="the texture's name, for a single file (default: its file name)")
    p.add_argument("--timeout", type=ranged(float, 0, UPLOAD_WAIT_MAX, above=True), default=300.0,
                   help="seconds per upload (an upload is encoded before it answers)")
    lighting_arg(p)

    p = proc("keys", cmd_keys, "API keys: create, list, revoke")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    create = actions.add_parser("create", help="make a key and print it once", formatter_class=HelpFormatter)
    create.add_argument("name", help="who or what the key is for (required)")
    create.add_argument("--note", help="free text kept with the key (default: none)")
    actions.add_parser("list", help="ids, states and names (never the keys)", formatter_class=HelpFormatter)
    revoke = actions.add_parser("revoke", help="revoke a key by id", formatter_class=HelpFormatter)
    revoke.add_argument("key_id", help="the id `keys list` shows (required)")
    return parser


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    prog = f"texspace {args.command}"
    try:
        settings = _settings(args)
        setup_logging(settings.log_level, settings.log_json and args.command in ("api", "worker", "serve"))
        if args.command not in ("api", "worker", "serve", "migrate"):
            logging.getLogger("alembic").setLevel(logging.WARNING)  # a lookup migrates quietly
        args.func(args, settings)
    except CliError as exc:
        sys.exit(_fail(prog, str(exc), exc.code))
    except KeyboardInterrupt:
        sys.exit(_fail(prog, "interrupted", 130))
    except Exception as exc:  # domain errors, OS errors, the unexpected: one line, never a traceback
        from worker.errors import TexspaceError

        log.debug("%s failed", prog, exc_info=True)
        if isinstance(exc, TexspaceError):
            sys.exit(_fail(prog, exc.detail, 2 if type(exc).__name__ in INPUT_ERRORS else 1))
        if isinstance(exc, OSError) and exc.strerror:
            sys.exit(_fail(prog, f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror, 1))
        sys.exit(_fail(prog, f"{type(exc).__name__}: {exc} (TEXSPACE_LOG_LEVEL=DEBUG shows where)", 1))


def _fail(prog: str, message: str, code: int) -> int:
    print(f"{prog}: error: {_one_line(message)}", file=sys.stderr)
    return code


if __name__ == "__main__":
    main()
