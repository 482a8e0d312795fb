"""Tileable regions: the image repeats exactly, so tiled 2 x 2 it has no seam.

Seam statistic: the mean |difference| between neighbouring columns (rows), for each of the
N - 1 interior lines of the image and for the wrap (last column against the first, which is
the line a 2 x 2 tiling adds). Without a seam the wrap is one more sample of the interior
distribution; the infinite (non-tileable) texture's wrap is far outside it, which shows the
statistic would see a seam.
"""
import io

import numpy as np
import pytest
from PIL import Image

from worker.colour import srgb_to_linear
from worker.errors import FeatureUnavailable, InvalidParameter
from worker.colour_match import texture_vector
from worker.encode import encode_texture
from worker.regions import render_region
from worker.runtime import ModelRuntime, PeriodicSampler, periodic_sampler
from worker.tiles import NATIVE_ZOOM

N = NATIVE_ZOOM


@pytest.fixture(scope="module")
def vector(runtime, brick):
    """The brick's code followed by its colour table, as a texture row samples it."""
    return texture_vector(*encode_texture(runtime, brick))


def render(runtime, vector, tmp_path, size, *, tileable, seed=0, x0=0, y0=0, name="r.png", z=N):
    path = render_region(runtime, vector, seed, z=z, x0=x0, y0=y0, width=size, height=size, fmt="png",
                         out_path=tmp_path / name, tileable=tileable)
    return path.read_bytes()


def linear(png: bytes) -> np.ndarray:
    return srgb_to_linear(np.asarray(Image.open(io.BytesIO(png)), dtype=np.float32) / 255.0)


def seam_scores(image: np.ndarray) -> tuple[float, float]:
    """(columns, rows): the wrap's mean |difference| in standard deviations of the interior lines'."""
    scores = []
    for axis in (1, 0):
        other = tuple(a for a in (0, 1, 2) if a != axis)
        interior = np.abs(np.diff(image, axis=axis)).mean(axis=other)
        first, last = np.take(image, 0, axis=axis), np.take(image, -1, axis=axis)
        wrap = np.abs(first - last).mean()
        scores.append(float((wrap - interior.mean()) / interior.std()))
    return scores[0], scores[1]


def check_seamless(runtime, vector, tmp_path, size, seeds, z=N) -> dict:
    """Seam scores of the tileable and the plain render for each seed (asserted), and the
    colour statistics of both (the last seed's)."""
    tiled, plain = [], []
    for s in seeds:
        image = linear(render(runtime, vector, tmp_path, size, tileable=True, seed=s, z=z))
        reference = linear(render(runtime, vector, tmp_path, size, tileable=False, seed=s, z=z))
        tiled.append(seam_scores(image))
        plain.append(seam_scores(reference))
    tiled, plain = np.array(tiled), np.array(plain)
    # no seam: each wrap within 4 sigma of the interior lines, and no bias over seeds
    assert np.abs(tiled).max() < 4.0, tiled
    assert abs(tiled.mean()) < 2.0, tiled
    # the statistic sees a seam where there is one: every wrap of the infinite texture lies
    # beyond the bound a tileable one must keep, and on average far beyond it (the size of
    # that wrap's jump is itself random: 4.8-10 sigma over these seeds and axes)
    assert plain.min() > 4.0, plain
    assert plain.mean() > 6.0, plain
    stats = {name: (im.reshape(-1, 3).mean(0), im.reshape(-1, 3).std(0))
             for name, im in (("tileable", image), ("plain", reference))}
    return {"tileable": tiled, "plain": plain, "stats": stats}


def check_statistics(stats: dict) -> None:
    """Same texture: the rounded frequencies change the pattern, not its colour statistics."""
    (mean_t, std_t), (mean_p, std_p) = stats["tileable"], stats["plain"]
    assert np.abs(mean_t - mean_p).max() < 0.03, stats
    assert np.all(np.abs(np.log(std_t / std_p)) < np.log(1.25)), stats


def test_tileable_256_has_no_seam(runtime, vector, tmp_path):
    check_seamless(runtime, vector, tmp_path, 256, seeds=range(3))


def test_tileable_above_the_native_zoom_has_no_seam_and_twice_the_pixels(runtime, vector, tmp_path):
    """A 512 px export at z 7 is the 256 px export's period in twice the pixels: seamless,
    repeating every 512 pixels, and like the z 6 export downsampled 2 x 2."""
    check_seamless(runtime, vector, tmp_path, 512, seeds=[0], z=N + 1)
    base = render(runtime, vector, tmp_path, 512, tileable=True, z=N + 1, name="a.png")
    assert render(runtime, vector, tmp_path, 512, tileable=True, z=N + 1, x0=512, y0=-1024, name="b.png") == base
    fine = linear(base)
    coarse = linear(render(runtime, vector, tmp_path, 256, tileable=True, name="c.png"))
    halved = fine.reshape(256, 2, 256, 2, 3).mean(axis=(1, 3))
    assert np.abs(halved - coarse).mean() < 0.25 * np.abs(coarse - coarse.mean((0, 1))).mean()


@pytest.mark.slow
def test_tileable_2048_has_no_seam(runtime, vector, tmp_path):
    """The product promise: a tileable 2048^2 export tiled 2 x 2 has no detectable seam."""
    scores = check_seamless(runtime, vector, tmp_path, 2048, seeds=[0])
    print("seam z-scores (columns, rows):", scores["tileable"], "plain:", scores["plain"])
    print("linear mean / std, tileable vs plain:", scores["stats"])
    check_statistics(scores["stats"])


def test_tileable_repeats_exactly(runtime, vector, tmp_path):
    """Shifting the region by one period (its size) gives the same bytes: 2 x 2 copies are
    one continuous render."""
    base = render(runtime, vector, tmp_path, 128, tileable=True, seed=4, x0=-40, y0=7, name="a.png")
    for dx, dy in ((128, 0), (0, -128), (256, 384)):
        assert render(runtime, vector, tmp_path, 128, tileable=True, seed=4, x0=-40 + dx, y0=7 + dy,
                      name="b.png") == base


def test_tileable_keeps_the_texture_statistics(runtime, vector, tmp_path):
    tiled = linear(render(runtime, vector, tmp_path, 512, tileable=True, name="t.png")).reshape(-1, 3)
    plain = linear(render(runtime, vector, tmp_path, 512, tileable=False, name="p.png")).reshape(-1, 3)
    print("512^2 linear mean / std, tileable vs plain:", tiled.mean(0), plain.mean(0), tiled.std(0), plain.std(0))
    check_statistics({"tileable": (tiled.mean(0), tiled.std(0)), "plain": (plain.mean(0), plain.std(0))})


def test_tileable_arguments_are_checked(runtime, vector, tmp_path):
    common = dict(x0=0, y0=0, out_path=tmp_path / "x.png", tileable=True)
    for bad in (dict(z=N, width=64, height=32), dict(z=N, width=64, height=64, plane="xz"),
                dict(z=N, width=64, height=64, fmt="pyramid")):
        with pytest.raises(InvalidParameter):
            render_region(runtime, vector, 0, **common, **bad)
    assert not (tmp_path / "x.png").exists()


def test_periodic_sampler_contract(runtime, vector):
    session = runtime.tileable_sampler()
    assert session.periodic and not runtime.sampler.periodic
    assert runtime.tileable_sampler() is session          # opened once
    points = np.random.default_rng(0).uniform(-3, 3, (300, 3))
    shifted = points + np.array([2.0, -4.0, 0.0])         # whole periods of 1 unit
    sampler = periodic_sampler(runtime, 1.0)
    assert isinstance(sampler, PeriodicSampler)
    assert np.array_equal(sampler.sample(points, vector, 3), sampler.sample(shifted, vector, 3))
    with pytest.raises(InvalidParameter):
        session.sample(points, vector, 3)                 # a tileable sampler needs its period
    with pytest.raises(InvalidParameter):
        runtime.sampler.sample(points, vector, 3, period=1.0)
    with pytest.raises(InvalidParameter):
        PeriodicSampler(runtime.sampler, 1.0)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InvalidParameter):
            PeriodicSampler(session, bad)


def test_export_without_tileable_sampler(model_dir, tmp_path):
    """A model exported before tileable textures: everything works but tileable, which says
    to re-export."""
    import json

    for name in ("encoder.onnx", "sampler.onnx"):
        (tmp_path / name).symlink_to(model_dir / name)
    manifest = json.loads((model_dir / "manifest.json").read_text())
    manifest.pop("tileable_sampler", None)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    old = ModelRuntime(tmp_path)
    assert old.tileable_path is None
    with pytest.raises(FeatureUnavailable, match="re-export"):
        old.tileable_sampler()
