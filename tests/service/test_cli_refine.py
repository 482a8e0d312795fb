"""``texspace tile|volume|bake|tileable|shader IMAGE --refine [SECONDS]``: the photo is fitted
first, as an upload's refinement is, and drawn with the fitted sampler, its code and a colour
table made for it. The fit is the stand-in of tests/service/helpers.py (no torch)."""
from __future__ import annotations

from pathlib import Path

from service.cli import main
from service.settings import FIT_SECONDS
from worker.contract import DETAIL_SECONDS
from tests.service.test_cli_errors import refused, tree


def test_refine_fits_the_photo_before_it_draws(cli_env: Path, fit_calls) -> None:
    main(["tile", "brick.png", "6", "0", "0", "--size", "64", "-o", "plain.png"])
    assert not fit_calls
    main(["tile", "brick.png", "6", "0", "0", "--size", "64", "-o", "refined.png", "--refine", "30"])
    (call,) = fit_calls
    assert call["minutes"] == 0.5 and call["image_path"].name == "brick.png"
    assert call["detail_seconds"] == 0  # a tile at the native zoom shows no finer detail: no stage
    assert call["interim"] is None and call["pause"] is None  # nothing to serve part way
    # the structure an upload's fit looks for: without it a brick photo was refined without its bricks
    assert {key: call[key] for key in ("grain", "lattice", "even", "lean")} == dict.fromkeys(
        ("grain", "lattice", "even", "lean"), "auto")
    # the stand-in fits code zeros: another code through the sampler, other pixels
    assert (cli_env / "refined.png").read_bytes() != (cli_env / "plain.png").read_bytes()
    # above the native zoom the fit's detail stage runs too (drawn where model.fit made a sampler for it)
    main(["tile", "brick.png", "8", "0", "0", "--size", "64", "-o", "deep.png", "--refine", "30"])
    assert fit_calls[-1]["detail_seconds"] == DETAIL_SECONDS > 0
    for zoom, stage in (("0", 0), ("2", DETAIL_SECONDS)):  # a tileable image: --zoom counts from the native zoom
        main(["tileable", "brick.png", "--size", "64", "--zoom", zoom, "-o", f"t{zoom}.png", "--refine", "30"])
        assert fit_calls[-1]["detail_seconds"] == stage
    main(["shader", "brick.png", "-o", "s.glsl", "--refine"])  # SECONDS defaults to an upload's budget
    assert fit_calls[-1]["minutes"] == FIT_SECONDS / 60


def test_refine_of_a_stored_texture_is_refused(cli_env: Path, capsys, fit_calls) -> None:
    before = tree(cli_env)
    code, line = refused(["tile", "0123456789abcdef", "6", "0", "0", "--refine"], capsys)
    assert code == 2 and "--refine applies to an image file" in line, line
    assert not fit_calls and not tree(cli_env) - before
