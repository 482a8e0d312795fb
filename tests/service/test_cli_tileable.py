"""``texspace tileable``: the API's tileable region from the command line, same bytes,
same limits, one-line refusals that create nothing."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.cli import main
from service.settings import Settings
from tests.helpers import brick_png
from tests.service.test_cli_errors import refused, tree
from tests.worker.gpu_readers import read_bc7_dds


def test_cli_tileable_of_stored_texture_matches_api(cli_env: Path, capsys) -> None:
    from fastapi.testclient import TestClient

    from service.context import build_services
    from service.main import create_app

    services = build_services(Settings(), immediate=True)
    body = {"z": 6, "x0": 0, "y0": 0, "width": 128, "height": 128, "seed": 3, "tileable": True}
    with TestClient(create_app(services=services)) as client:
        texture = client.post("/v1/textures", files={"image": ("b.png", brick_png())}).json()
        job = client.get(client.post(texture["links"]["regions"], json=body).json()["links"]["self"]).json()
        api_png = client.get(job["links"]["result"]).content
    services.engine.dispose()
    main(["tileable", texture["id"], "--size", "128", "--seed", "3", "-o", "stored.png"])
    assert (cli_env / "stored.png").read_bytes() == api_png


def test_cli_tileable_of_an_image_file(cli_env: Path) -> None:
    main(["tileable", "brick.png", "--size", "128", "-o", "t.png"])
    image = np.asarray(Image.open(cli_env / "t.png"), dtype=np.float32)
    assert image.shape == (128, 128, 3)
    interior = np.abs(np.diff(image, axis=1)).mean()
    assert np.abs(image[:, 0] - image[:, -1]).mean() < 2 * interior   # no seam at the wrap
    main(["tileable", "brick.png", "--size", "64", "-o", "t.exr"])
    assert (cli_env / "t.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"
    main(["tileable", "brick.png", "--size", "64", "--dds-compression", "bc7", "-o", "t.dds"])
    header, levels = read_bc7_dds((cli_env / "t.dds").read_bytes())
    assert (header["dxgi_format"], header["width"], len(levels)) == (99, 64, 7)


@pytest.mark.parametrize(("argv", "words"), [
    (["tileable", "brick.png", "--size", "32"], "argument --size: must be in [64, 16384]"),
    (["tileable", "brick.png", "--size", "4097", "-o", "t.dds"], "exceed 16777216 pixels"),
    (["tileable", "brick.png", "-o", "t.jpg"], "cannot tell the format"),
    (["tileable", "brik.png"], "neither an image file nor a texture id"),
    (["tileable", "brick.png", "--dds-compression", "bc7", "-o", "t.png"], "applies to a .dds output only"),
])
def test_cli_tileable_refusals(cli_env: Path, capsys, argv, words) -> None:
    before = tree(cli_env)
    code, line = refused(argv, capsys)
    assert code == 2 and words in line, line
    assert not tree(cli_env) - before


def test_cli_tileable_follows_the_region_limit(cli_env: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("TEXSPACE_MAX_REGION_PIXELS", str(256 * 256))
    code, line = refused(["tileable", "brick.png", "--size", "257"], capsys)
    assert code == 2 and "TEXSPACE_MAX_REGION_PIXELS" in line
