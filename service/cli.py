"""The ``texspace`` command: processes (api, worker, serve, migrate) and offline tools
(encode, tile, volume, bake) that work without a server."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from . import auth, db, processes
from .context import build_services
from .logs import setup_logging
from .settings import Settings
from .tables import Texture


def _settings(args: argparse.Namespace) -> Settings:
    """Settings from the environment; flags override (and reach child processes)."""
    for flag, env in (("data_dir", "TEXSPACE_DATA_DIR"), ("host", "TEXSPACE_HOST"),
                      ("port", "TEXSPACE_PORT"), ("workers", "TEXSPACE_WORKERS")):
        value = getattr(args, flag, None)
        if value is not None:
            os.environ[env] = str(value)
    return Settings()


def _registry(settings: Settings):  # noqa: ANN202
    from worker.runtime import ModelRegistry

    return ModelRegistry(settings.model_dirs, default=settings.default_model_version)


class TextureSource:
    """A texture named on the command line: an image file (encoded now) or a stored id."""

    def __init__(self, settings: Settings, ref: str) -> None:
        registry = _registry(settings)
        if Path(ref).is_file():
            from worker.colour_match import texture_vector
            from worker.images import encode_texture, read_image

            runtime = registry.get(settings.default_model_version)
            image = read_image(Path(ref).read_bytes(), max_pixels=settings.max_image_pixels)
            self.z, colour = encode_texture(runtime, image)
            self.code, self.sampler, self.ppu = texture_vector(self.z, colour), runtime, runtime.pixels_per_unit
            self.model_version = runtime.version
            return
        services = build_services(settings, immediate=True)
        services._registry = registry
        with db.session_scope(services.sessions) as session:
            texture = session.get(Texture, ref)
        if texture is None:
            raise SystemExit(f"texspace: {ref!r} is neither an image file nor a texture id in "
                             f"{settings.resolved_database_url}")
        self.z, self.code = np.asarray(texture.code, np.float32), texture.sampling_code()
        self.sampler, self.ppu = services.sampler_for(texture), services.pixels_per_unit(texture)
        self.model_version = texture.model_version


def _progress_bar(description: str):  # noqa: ANN202
    from tqdm import tqdm

    bar = tqdm(total=100, desc=description, unit="%", file=sys.stderr, disable=None)

    def report(fraction: float) -> None:
        bar.n = round(100 * fraction, 1)
        bar.refresh()

    return bar, report


def cmd_api(args: argparse.Namespace) -> None:
    processes.run_api(_settings(args))


def cmd_worker(args: argparse.Namespace) -> None:
    processes.run_worker(_settings(args), migrate=not args.no_migrate)


def cmd_serve(args: argparse.Namespace) -> None:
    processes.run_serve(_settings(args))


def cmd_migrate(args: argparse.Namespace) -> None:
    settings = _settings(args)
    settings.ensure_dirs()
    db.migrate(settings.resolved_database_url)
    print(f"database at head: {settings.resolved_database_url}")


def cmd_encode(args: argparse.Namespace) -> None:
    source = TextureSource(_settings(args), args.image)
    print(json.dumps({"code": [round(float(c), 7) for c in source.z], "model_version": source.model_version}))


def cmd_tile(args: argparse.Namespace) -> None:
    from worker.images import write_image
    from worker.tiles import render_tile

    source = TextureSource(_settings(args), args.texture)
    rgb = render_tile(source.sampler, source.code, args.seed, args.z, args.x, args.y, args.size,
                      pixels_per_unit=source.ppu, plane=args.plane, offset=args.offset)
    out = Path(args.output or f"tile-{args.z}-{args.x}-{args.y}.{args.format}")
    out.write_bytes(write_image(rgb, args.format))
    print(out)


def cmd_volume(args: argparse.Namespace) -> None:
    from worker.volume_writers import EXTENSIONS
    from worker.volumes import render_volume

    source = TextureSource(_settings(args), args.texture)
    out = Path(args.output or f"volume-{args.resolution}{EXTENSIONS[args.format]}")
    bounds = np.asarray(args.bounds, np.float64).reshape(2, 3)
    bar, report = _progress_bar("volume")
    with bar:
        path = render_volume(source.sampler, source.code, args.seed, resolution=args.resolution,
                             bounds=bounds, fmt=args.format, out_path=out, progress=report)
    print(path)


def cmd_bake(args: argparse.Namespace) -> None:
    from worker.bake import BakeLimits, bake_mesh

    source = TextureSource(_settings(args), args.texture)
    mesh = Path(args.mesh)
    out = Path(args.output or f"{mesh.stem}-baked.{'glb' if args.format == 'glb' else 'zip'}")
    bar, report = _progress_bar("bake")
    with bar:
        result = bake_mesh(source.sampler, source.code, args.seed, mesh_bytes=mesh.read_bytes(),
                           filename=mesh.name, resolution=args.resolution, scale=args.scale, fmt=args.format,
                           out_path=out, pixels_per_unit=source.ppu, limits=BakeLimits(), progress=report)
    print(result.path)


def cmd_keys(args: argparse.Namespace) -> None:
    """``texspace keys create NAME [--note] | list | revoke KEY_ID`` (see :mod:`service.auth`)."""
    services = build_services(_settings(args), immediate=True)
    if args.action == "create":
        row, key = auth.create_key(services, args.name, args.note)
        print(f"id:  {row.id}\nkey: {key}\n(store the key now: only its hash is kept)")
    elif args.action == "list":
        for row in auth.list_keys(services):
            state = f"revoked {row.revoked_at:%Y-%m-%d %H:%M}" if row.revoked_at else "active"
            print(f"{row.id}  {state:<24} {row.created_at:%Y-%m-%d %H:%M}  {row.name}")
    elif not auth.revoke_key(services, args.key_id):
        raise SystemExit(f"texspace: no active key with id {args.key_id!r}")
    else:
        print(f"revoked {args.key_id}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="texspace", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    def proc(name: str, func, help_: str) -> argparse.ArgumentParser:  # noqa: ANN001
        p = sub.add_parser(name, help=help_)
        p.add_argument("--data-dir", dest="data_dir", help="overrides TEXSPACE_DATA_DIR")
        p.set_defaults(func=func)
        return p

    for name, func, help_ in (("api", cmd_api, "run the HTTP API (uvicorn)"),
                              ("serve", cmd_serve, "run the API and one worker process (embedded default)")):
        p = proc(name, func, help_)
        p.add_argument("--host")
        p.add_argument("--port", type=int)
    p = proc("worker", cmd_worker, "consume the job queue")
    p.add_argument("--workers", type=int, help="threads (overrides TEXSPACE_WORKERS)")
    p.add_argument("--no-migrate", action="store_true", help="assume the database is migrated")
    proc("migrate", cmd_migrate, "apply database migrations")

    p = proc("encode", cmd_encode, "print the texture code of an image")
    p.add_argument("image")

    def texture_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("-o", "--output")

    p = proc("tile", cmd_tile, "render one tile of an image file or stored texture id")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID")
    for axis in ("z", "x", "y"):
        p.add_argument(axis, type=int)
    texture_args(p)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--plane", choices=("xy", "xz", "yz"), default="xy")
    p.add_argument("--offset", type=float, default=0.0)
    p.add_argument("--format", choices=("png", "webp", "exr"), default="png")

    p = proc("volume", cmd_volume, "render a solid N^3 block")
    p.add_argument("texture", help="IMAGE file or TEXTURE_ID")
    texture_args(p)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--bounds", type=float, nargs=6, default=[0, 0, 0, 1, 1, 1], metavar="X0 Y0 Z0 X1 Y1 Z1")
    p.add_argument("--format", choices=("npy", "exr", "tiff", "raw", "nrrd", "dds", "flipbook"), default="npy")

    p = proc("bake", cmd_bake, "UV-unwrap a mesh and bake a texture into it")
    p.add_argument("mesh")
    p.add_argument("--texture", required=True, help="IMAGE file or TEXTURE_ID")
    texture_args(p)
    p.add_argument("--resolution", type=int, default=1024)
    p.add_argument("--scale", type=float, default=None, help="world units per mesh unit (default: auto)")
    p.add_argument("--format", choices=("glb", "obj"), default="glb")

    p = proc("keys", cmd_keys, "API keys: create, list, revoke")
    actions = p.add_subparsers(dest="action", required=True)
    create = actions.add_parser("create", help="make a key and print it once")
    create.add_argument("name")
    create.add_argument("--note")
    actions.add_parser("list", help="ids, states and names (never the keys)")
    revoke = actions.add_parser("revoke", help="revoke a key by id")
    revoke.add_argument("key_id")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    settings = _settings(args)
    setup_logging(settings.log_level, settings.log_json and args.command in ("api", "worker", "serve"))
    args.func(args)


if __name__ == "__main__":
    main()
