"""The CLI is as careful as the API: each bad input is one line on stderr and a non-zero
exit (2: bad input, 1: the work failed), never a traceback, and nothing is created (no
output file, no ./data/texspace.db); the output's format follows the -o extension; every
argument's help says its default."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cli import build_parser, main
from tests.helpers import brick_png

MESHES = Path(__file__).resolve().parents[1] / "data" / "meshes"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def cli_env(tmp_path: Path, monkeypatch) -> Path:
    """A working folder with brick.png, a broken image and a broken mesh; the environment
    has no TEXSPACE_* variable, so the data dir is the default ./data (must stay absent)."""
    for key in list(os.environ):
        if key.startswith("TEXSPACE_"):
            monkeypatch.delenv(key)
    monkeypatch.setenv("TEXSPACE_AUTO_FIT", "false")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "brick.png").write_bytes(brick_png())
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 2 3\n")
    return tmp_path


def tree(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*")}


def refused(argv: list[str], capsys) -> tuple[int, str]:  # noqa: ANN001
    """(exit code, the one stderr line) of a CLI run that must fail."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"{argv}: not one line:\n{err}"
    assert "Traceback" not in err
    return exit_info.value.code, lines[0]


# (argv, exit code, words the message must hold)
BAD_INPUTS = [
    (["tile", "bad.png", "6", "0", "0"], 2, "image"),
    (["encode", "bad.png"], 2, "image"),
    (["tile", "brik.png", "6", "0", "0"], 2, "neither an image file nor a texture id"),  # mistyped path
    (["volume", "data/brick.png"], 2, "neither an image file nor a texture id"),
    (["bake", "no-such.obj", "--texture", "brick.png"], 2, "no such mesh file"),
    (["bake", "bad.obj", "--texture", "brick.png", "-o", "b.glb"], 2, "mesh"),
    (["tile", "brick.png", "13", "0", "0"], 2, "argument z: must be in [2, 12], got 13"),
    (["tile", "brick.png", "1", "0", "0"], 2, "argument z: must be in [2, 12]"),
    (["tile", "brick.png", "six", "0", "0"], 2, "an integer is needed"),
    (["tile", "brick.png", "6", "0", "0", "--size", "-5"], 2, "argument --size: must be in [64, 1024], got -5"),
    (["tile", "brick.png", "6", "0", "0", "--size", "2048"], 2, "--size"),
    (["tile", "brick.png", "2", "0", "0", "--size", "1024"], 2, "samples"),  # TEXSPACE_MAX_TILE_SAMPLES
    (["tile", "brick.png", "6", "0", "0", "--seed", "-1"], 2, "--seed"),
    (["tile", "brick.png", "6", "0", "0", "--offset", "nan"], 2, "--offset"),
    (["volume", "brick.png", "--resolution", "300"], 2, "resolution 300 exceeds the limit of 256"),
    (["volume", "brick.png", "--resolution", "1"], 2, "--resolution"),
    (["volume", "brick.png", "--bounds", "0", "0", "0", "1", "1", "-1"], 2, "--bounds"),
    (["volume", "brick.png", "--bounds", "0", "0", "0", "1", "1"], 2, "--bounds"),
    (["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "--resolution", "8192"], 2,
     "resolution 8192 exceeds the limit of 4096"),
    (["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "--scale", "0"], 2, "--scale"),
    (["tile", "brick.png", "6", "0", "0", "-o", "no-folder/t.png"], 2, "the folder no-folder does not exist"),
    (["volume", "brick.png", "-o", "no-folder/v.npy"], 2, "does not exist"),
    (["tile", "brick.png", "6", "0", "0", "-o", "t.exr", "--format", "png"], 2, "a png file ends in .png"),
    (["tile", "brick.png", "6", "0", "0", "-o", "t.jpg"], 2, "cannot tell the format"),
    (["tile", "brick.png", "6", "0", "0", "-o", "t"], 2, "cannot tell the format"),
    (["volume", "brick.png", "-o", "v.exr", "--format", "npy"], 2, "a npy file ends in .npy"),
    (["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "-o", "c.obj"], 2, "cannot tell the format"),
    (["tile", "brick.png", "6", "0", "0", "-o", "."], 2, "is a folder"),
    (["keys", "--data-dir", "kd", "revoke", "nope"], 1, "no active key"),
]


@pytest.mark.parametrize(("argv", "code", "words"), BAD_INPUTS, ids=[" ".join(a[0]) for a in BAD_INPUTS])
def test_bad_input_is_one_line_and_creates_nothing(cli_env: Path, capsys, argv, code, words) -> None:
    before = tree(cli_env)
    status, line = refused(argv, capsys)
    assert status == code, line
    assert line.startswith("texspace"), line
    assert words in line, line
    created = tree(cli_env) - before
    if argv[0] == "keys":  # keys work on a database: the one named with --data-dir
        created = {p for p in created if not p.startswith("kd")}
    assert not created, f"{argv} created {sorted(created)}"


def test_limits_follow_the_settings_as_the_apis_do(cli_env: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("TEXSPACE_MAX_VOLUME_RESOLUTION", "16")
    monkeypatch.setenv("TEXSPACE_MAX_TILE_SIZE", "128")
    monkeypatch.setenv("TEXSPACE_MAX_BAKE_RESOLUTION", "64")
    assert "exceeds the limit of 16" in refused(["volume", "brick.png", "--resolution", "17"], capsys)[1]
    assert "exceeds the limit of 128" in refused(["tile", "brick.png", "6", "0", "0", "--size", "256"], capsys)[1]
    assert "exceeds the limit of 64" in refused(["bake", str(MESHES / "cube.obj"), "--texture", "brick.png",
                                                "--resolution", "128"], capsys)[1]
    monkeypatch.setenv("TEXSPACE_MAX_MESH_FACES", "4")  # the cube has 12
    code, line = refused(["bake", str(MESHES / "cube.obj"), "--texture", "brick.png", "--resolution", "64"], capsys)
    assert code == 2 and "limit is 4" in line
    monkeypatch.setenv("TEXSPACE_MAX_VOLUME_RESOLUTION", "many")
    code, line = refused(["volume", "brick.png"], capsys)
    assert code == 2 and "TEXSPACE_MAX_VOLUME_RESOLUTION" in line
    assert not (cli_env / "data").exists()


def test_the_format_follows_the_extension(cli_env: Path) -> None:
    main(["tile", "brick.png", "6", "0", "0", "--size", "64", "-o", "t.exr"])
    assert (cli_env / "t.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic, not PNG
    main(["tile", "brick.png", "6", "0", "0", "--size", "64", "-o", "t.webp"])
    head = (cli_env / "t.webp").read_bytes()[:12]
    assert head[:4] == b"RIFF" and head[8:] == b"WEBP"
    main(["tile", "brick.png", "6", "0", "0", "--size", "64", "--format", "webp"])  # no -o: the format's name
    assert (cli_env / "tile-6-0-0.webp").is_file()
    main(["volume", "brick.png", "--resolution", "4", "-o", "v.exr"])
    assert (cli_env / "v.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"
    main(["volume", "brick.png", "--resolution", "4", "-o", "v.tiff"])
    assert (cli_env / "v.tiff").read_bytes()[:2] in (b"II", b"MM")
    main(["volume", "brick.png", "--resolution", "4", "-o", "V.NPY"])
    assert np.load(cli_env / "V.NPY").shape == (4, 4, 4, 3)
    assert not (cli_env / "data").exists(), "image files need no database"


def test_every_argument_has_help_with_its_default() -> None:
    """Positional arguments say what they take; options also say their default."""
    parser = build_parser()
    problems = []

    def walk(p: argparse.ArgumentParser, name: str) -> None:
        formatter = p._get_formatter()
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    walk(sub, f"{name} {sub_name}")
            elif isinstance(action, argparse._HelpAction):
                continue
            elif not action.help:
                problems.append(f"{name} {action.dest}: no help")
            elif action.option_strings and not action.required \
                    and "default" not in formatter._get_help_string(action):
                problems.append(f"{name} {action.dest}: no default in {action.help!r}")

    walk(parser, "texspace")
    assert not problems, problems
    volume = " ".join(parser._subparsers._group_actions[0].choices["volume"].format_help().split())
    assert volume.count("X0 Y0 Z0 X1 Y1 Z1") == 2  # the usage line and the option, once each
    assert "Z1 X0" not in volume
    assert "(default: 0 0 0 1 1 1)" in volume


def test_the_real_command_prints_no_traceback(cli_env: Path) -> None:
    """The installed entry point (a fresh interpreter): a bad image is one line, exit 2."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TEXSPACE_")}
    done = subprocess.run([sys.executable, "-m", "service.cli", "tile", "bad.png", "6", "0", "0"],
                          cwd=cli_env, env={**env, "PYTHONPATH": str(REPO)}, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr, done.stderr
    assert not (cli_env / "data").exists() and not (cli_env / "tile-6-0-0.png").exists()


def test_ranges_are_the_apis(client) -> None:
    """Each range the CLI checks is the one the API's schema declares, at both ends."""
    spec = client.app.openapi()
    schemas = spec["components"]["schemas"]
    tile_op = spec["paths"]["/v1/textures/{texture_id}/tiles/{z}/{x}/{y}.{fmt}"]["get"]
    tile = {p["name"]: p["schema"] for p in tile_op["parameters"]}
    bake_body = spec["paths"]["/v1/textures/{texture_id}/bakes"]["post"]["requestBody"]["content"]
    bake_ref = bake_body["multipart/form-data"]["schema"]["$ref"].rsplit("/", 1)[1]
    bake = schemas[bake_ref]["properties"]
    volume = schemas["VolumeIn"]["properties"]
    parser = build_parser()

    def accepts(argv: list[str]) -> bool:
        try:
            parser.parse_args(argv)
        except SystemExit:
            return False
        return True

    def ends(schema: dict) -> tuple[float, float]:
        schema = next((s for s in schema.get("anyOf", []) if s.get("type") != "null"), schema)
        kind = int if schema.get("type") == "integer" else float
        return kind(schema.get("minimum", schema.get("exclusiveMinimum"))), kind(schema["maximum"])

    cases = [  # (argv with {} for the value, the API's schema of that value)
        (["tile", "t", "{}", "0", "0"], tile["z"]),
        (["tile", "t", "6", "{}", "0"], tile["x"]),
        (["tile", "t", "6", "0", "0", "--size", "{}"], tile["size"]),
        (["tile", "t", "6", "0", "0", "--seed", "{}"], tile["seed"]),
        (["tile", "t", "6", "0", "0", "--offset", "{}"], tile["offset"]),
        (["volume", "t", "--resolution", "{}"], volume["resolution"]),
        (["bake", "m.obj", "--texture", "t", "--resolution", "{}"], bake["resolution"]),
    ]
    for argv, schema in cases:
        low, high = ends(schema)
        fill = lambda v: [str(v) if a == "{}" else a for a in argv]  # noqa: E731
        assert accepts(fill(low)) and accepts(fill(high)), (argv, low, high)
        step = 1 if isinstance(high, int) else high * 1e-6
        assert not accepts(fill(low - step)) and not accepts(fill(high + step)), (argv, low, high)
    scale_low, scale_high = ends(bake["scale"])
    assert "exclusiveMinimum" in str(bake["scale"]) and scale_low == 0
    assert not accepts(["bake", "m.obj", "--texture", "t", "--scale", "0"])
    assert accepts(["bake", "m.obj", "--texture", "t", "--scale", str(scale_high)])
