"""Single-exemplar fitting writes a sampler with the shipped contract, and it learns."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
from scipy import ndimage
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

from model.export import export_model  # noqa: E402
from model.fit import fit_exemplar  # noqa: E402
from model.structure import detect_boards, detect_stripes  # noqa: E402
from worker.colour import even_lighting  # noqa: E402
from eval.synthetic_photos import boards, corrugation, running_bond  # noqa: E402
from model.evaluate import load_candidates  # noqa: E402
from model.networks import ModelConfig, TextureSpace  # noqa: E402


def space_checkpoint(tmp_path: Path) -> Path:
    """A fresh space (torch seed 0) exported under ``tmp_path``: what these fits start from."""
    torch.manual_seed(0)
    export_model(TextureSpace(ModelConfig()), tmp_path / "space")
    return tmp_path / "space" / "space.pt"


class StopFit(Exception):
    """Raised by ``stop_before_training``'s stand-in for ``model.fit.train``."""


def stop_before_training(monkeypatch, read) -> dict:  # noqa: ANN001
    """Replace ``model.fit.train`` by a stand-in that records ``read(cfg)`` under the
    exemplar's stem and raises StopFit: what a fit would train, without training it."""
    import model.fit as fit

    seen = {}

    def train(cfg, progress=None, interim=None, pause=None):  # noqa: ANN001, ANN202
        seen[Path(cfg.exemplar).stem] = read(cfg)
        raise StopFit

    monkeypatch.setattr(fit, "train", train)
    return seen


def training_that_publishes(space: Path, code: torch.Tensor, step: int, seen):  # noqa: ANN001
    """A stand-in for ``model.train.train`` that publishes the space's own model with ``code``
    from ``step`` through the fit's Interim (as ``Probe.lend_best`` does; ``seen`` gets the
    Interim), then ends at step 50 on a zero code (the probe's state)."""
    from model.networks import load_checkpoint

    def train(cfg, progress=None, interim=None, pause=None):  # noqa: ANN001, ANN202
        seen(interim)
        model, _ = load_checkpoint(space)
        interim.publish(model, code, step)
        path = Path(cfg.out) / "end.pt"
        torch.save({**torch.load(space, weights_only=False), "code": torch.zeros(1, 8), "step": 50,
                    "wall_seconds": 1.0, "probe": {"score": 1.0, "step": 50}}, path)
        return path
    return train


def saved_png(path: Path, photo: np.ndarray) -> np.ndarray:
    """Write ``photo`` (0..1) as an 8-bit PNG at ``path``; the pixels as a fit reads them back."""
    Image.fromarray((photo * 255).round().astype(np.uint8)).save(path)
    return np.asarray(Image.open(path), np.float32) / 255


def test_fit_writes_a_contract_sampler_and_its_code(tmp_path, skimage_textures, vgg):
    space = space_checkpoint(tmp_path)
    image = tmp_path / "gravel.png"
    Image.fromarray((skimage_textures["gravel"] * 255).astype(np.uint8)).save(image)
    seen = []
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=space,
                          minutes=0.05, patch=32, progress=seen.append, grain="auto")
    assert result["steps"] >= 1 and seen and 0 < seen[-1] <= 1
    assert result["grain"] is None  # gravel: detected as isotropic
    code = json.loads((tmp_path / "fit" / "code.json").read_text())["code"]
    assert len(code) == 8
    session = ort.InferenceSession(str(tmp_path / "fit" / "sampler.onnx"), providers=["CPUExecutionProvider"])
    from model.colour import identity_colour  # the fitted sampler has the colour stage too

    rgb = session.run(None, {"points": np.random.default_rng(0).random((100, 3)), "colour": identity_colour()[None].numpy(),
                             "z": np.asarray([code], np.float32), "seed": np.asarray(1, np.int64)})[0]
    assert rgb.shape == (100, 3) and np.isfinite(rgb).all()
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert manifest["kind"] == "fitted" and manifest["code"] == code and manifest["rate"] == "falling"
    # the slim checkpoint beside it is what model.evaluate compares with the space's code
    (fit,) = load_candidates([tmp_path / "fit" / "fit.pt"])
    assert fit.label == "ours-fit" and fit.fitted_to == "gravel" and fit.code.reshape(-1).tolist() == code


def test_a_striped_photo_is_fitted_on_its_stripes(tmp_path, vgg):
    """fit_exemplar with lattice="auto" falls back to the stripes when there is no 2D lattice
    and reports them as its lattice, in world units."""
    space = space_checkpoint(tmp_path)
    image = tmp_path / "corrugated.png"
    photo = saved_png(image, corrugation())
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=space,
                          minutes=0.02, patch=32, lattice="auto", grain="auto")
    stripes = np.array(detect_stripes(even_lighting(photo))) / ModelConfig().pixels_per_unit  # as detection reads it
    assert result["grain"] is None and result["lattice"] == pytest.approx(stripes.tolist())
    unfitted = fit_exemplar(image, tmp_path / "plain", init_checkpoint=space,
                            minutes=0.02, patch=32, lattice=None, grain="auto")
    assert unfitted["lattice"] is None


def test_a_boards_photo_keeps_its_grain_and_reads_its_boards(tmp_path, vgg):
    """With grain and lattice "auto", boards get both: noise stretched along the grain and
    phases across it. The sampler, its tileable twin and its shader take the pair."""
    from model.export import TILEABLE_SAMPLER
    from worker.colour_match import identity_colour
    from worker.runtime import PeriodicSampler, SamplerSession
    from worker.shader import emit_shader

    space = space_checkpoint(tmp_path)
    image = tmp_path / "planks.png"
    photo = saved_png(image, boards())
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=space,
                          minutes=0.02, patch=32, lattice="auto", grain="auto")
    found = np.array(detect_boards(even_lighting(photo), "y")) / ModelConfig().pixels_per_unit  # as detection reads it
    assert result["grain"] == "y" and result["lattice"] == pytest.approx(found.tolist())
    vector = np.concatenate([np.asarray(result["code"], np.float32), identity_colour(216)])
    tileable = PeriodicSampler(SamplerSession(tmp_path / "fit" / TILEABLE_SAMPLER, threads=1), period=0.9)
    near = np.random.default_rng(3).uniform(0, 1, (200, 3))
    base = tileable.sample(near, vector, 4)
    for shift in ((0.9, 0.0, 0.0), (0.0, -1.8, 0.0)):
        assert np.abs(tileable.sample(near + shift, vector, 4) - base).max() < 1e-4
    for language in ("glsl", "wgsl"):
        text = emit_shader(tmp_path / "fit" / "sampler.onnx", vector, "planks", language)
        assert "repeat lattice" in text and text.count("{") == text.count("}")
    # a fit asked for no lattice keeps the grain alone
    plain = fit_exemplar(image, tmp_path / "plain", init_checkpoint=space,
                         minutes=0.02, patch=32, lattice=None, grain="auto")
    assert plain["grain"] == "y" and plain["lattice"] is None


def test_a_leaning_grain_is_fitted_straightened(tmp_path, monkeypatch):
    """A grain 8 degrees off the photo's y axis: the fit learns from the photo turned
    upright (read as it is, not resized back up), and says by how much; an upright grain
    and a lean under GRAIN_TILT_MIN are fitted as they are; one 35 degrees off (which the
    axis test misses) is found on the turned photo and turned too."""
    from model.structure.grain import GRAIN_TILT_MIN, grain_tilt
    from model.train import load_exemplars
    from eval.synthetic_photos import streaks

    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch, lambda cfg: (cfg.grain, load_exemplars(cfg)[1][0]))
    for name, lean in (("leaning", 8.0), ("upright", 0.0), ("slight", GRAIN_TILT_MIN / 2), ("diagonal", 35.0)):
        saved_png(tmp_path / f"{name}.png", streaks(angle_degrees=lean))
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / f"{name}.png", tmp_path / name, init_checkpoint=space, grain="auto")
    grain, photo = seen["leaning"]
    assert grain == "y" and grain_tilt(photo, "y") == pytest.approx(0.0, abs=0.3)
    side = 256 / (np.cos(np.radians(8)) + np.sin(np.radians(8)))  # 226.7 px: read at the working pixel size
    assert photo.shape[0] == photo.shape[1] and abs(photo.shape[0] - side) <= 1
    for name in ("upright", "slight"):
        assert seen[name][0] == "y" and seen[name][1].shape[:2] == (256, 256)
    grain, photo = seen["diagonal"]  # past the axis test: found on the turned photo, and turned
    assert grain == "y" and grain_tilt(photo, "y") == pytest.approx(0.0, abs=0.3)
    assert abs(photo.shape[0] - 256 / (np.cos(np.radians(35)) + np.sin(np.radians(35)))) <= 1
    # the whole fit: its result and manifest say the turn
    monkeypatch.undo()
    result = fit_exemplar(tmp_path / "leaning.png", tmp_path / "fit", init_checkpoint=space, minutes=0.02, patch=32,
                          grain="auto")
    assert result["straightened"] == pytest.approx(8.0, abs=0.3) and result["grain"] == "y"
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert manifest["straightened"] == result["straightened"]


def test_boards_found_upright_are_not_turned_by_the_grains_mean_lean(monkeypatch):
    """A grain's mean lean (the structure tensor's) turned photos whose boards run along the
    axis and lost them (0ad's gold brick courses, 5 degrees; wavy ripples, 11): a photo whose
    boards are found as it is keeps its axis; one without boards is still straightened."""
    import model.fit
    from model.fit import detect_structure
    from eval.synthetic_photos import streaks

    monkeypatch.setattr(model.fit, "grain_turn", lambda photo, grain: 11.0 if grain else 0.0)
    cfg = ModelConfig()
    found = detect_structure(boards(), cfg, grain="auto", lattice="auto", even="auto", lean="auto")
    assert found.turned == 0.0 and found.grain == "y" and found.lattice is not None
    assert abs(found.lattice[0] * cfg.pixels_per_unit - 25.6) < 0.1
    plain = detect_structure(streaks(), cfg, grain="auto", lattice="auto", even="auto", lean="auto")
    assert plain.turned == 11.0 and plain.lattice is None


def test_ripples_found_on_the_turned_photo_lean_as_in_the_photo():
    """Ripples leaning 25 degrees smear the upright profile: they are found on the photo
    turned by its grain's lean, as stripes that replace the grain detection gave (as on a
    photo found upright), and, with no grain left to run along an axis, fitted as the photo
    leans: the stripes turned back, the photo not turned (hazard stripes at 45 degrees came
    back upright, with the grain kept). A grain asked for stays, and the photo is turned."""
    from model.fit import detect_structure
    from eval.synthetic_photos import ripples

    cfg = ModelConfig()
    for lean in (-25.0, 25.0):
        photo = ripples(48.0, lean=lean)
        found = detect_structure(photo, cfg, grain="auto", lattice="auto", even="auto", lean="auto")
        assert found.turned == 0.0 and found.grain is None and found.photo is photo, (lean, found.grain)
        ax, ay, bx, by = (v * cfg.pixels_per_unit for v in found.lattice)
        assert abs(np.degrees(np.arctan2(-ax, ay)) - lean) < 2.0 and abs(np.hypot(ax, ay) - 48.0) < 0.1 * 48.0
        assert (bx, by) == pytest.approx((-ay, ax))
    asked = detect_structure(ripples(48.0, lean=-25.0), cfg, grain="x", lattice="auto", even="auto", lean="auto")
    assert asked.grain == "x" and asked.lattice is not None and asked.turned != 0.0


def test_every_fit_takes_the_large_patch_and_falling_rates_by_default(tmp_path, monkeypatch):
    """Stripe and 2D lattice fits train on PATCH, as a fit without structure does (the
    validation cardboard: 0.054 -> 0.0048; floor tiles 0.28 -> 0.031 with falling rates),
    and their rates fall over their time unless ``rate="constant"``; a lattice fit still
    trains one patch a step (and its partner)."""
    import model.fit as fit

    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch,
                                lambda cfg: (cfg.patch, cfg.lattice is not None, cfg.decay_by_time, cfg.batch))
    for name, image in (("corrugated", corrugation()), ("bricks", running_bond())):
        Image.fromarray((image * 255).round().astype(np.uint8)).save(tmp_path / f"{name}.png")
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / f"{name}.png", tmp_path / name, init_checkpoint=space,
                         lattice="auto", grain="auto")
    assert seen == {"corrugated": (fit.PATCH, True, True, 1), "bricks": (fit.PATCH, True, True, 1)}
    for rate, falling in (("falling", True), ("constant", False)):
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / "bricks.png", tmp_path / "bricks", init_checkpoint=space,
                         lattice="auto", rate=rate)
        assert seen["bricks"][2] is falling
    with pytest.raises(ValueError, match="rate"):
        fit_exemplar(tmp_path / "bricks.png", tmp_path / "bricks", init_checkpoint=space,
                     rate="auto")


def test_lattice_fit_reads_phases_has_a_shader_and_a_tileable_sampler(tmp_path, vgg):
    from model.export import TILEABLE_SAMPLER
    from worker.colour_match import identity_colour
    from worker.runtime import PeriodicSampler, SamplerSession
    from model.networks import load_checkpoint
    from worker.shader import emit_shader, texture_constants

    space = space_checkpoint(tmp_path)
    image = tmp_path / "bricks.png"
    Image.fromarray((running_bond() * 255).astype(np.uint8)).save(image)
    result = fit_exemplar(image, tmp_path / "fit", init_checkpoint=space,
                          minutes=0.05, patch=32, lattice="auto", grain="auto", shade="on")
    ppu = ModelConfig().pixels_per_unit
    assert result["grain"] is None and result["lattice"] is not None
    ax, ay, bx, by = np.array(result["lattice"]) * ppu  # world units: one exemplar pixel = 1 / ppu
    assert abs(ax * by - ay * bx) == pytest.approx(32 * 11, rel=0.01)
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert manifest["lattice"] == result["lattice"] and manifest["tileable_sampler"] == TILEABLE_SAMPLER
    (fitted,) = [load_checkpoint(tmp_path / "fit" / "fit.pt")[0]]
    field = fitted.field
    # the phases repeat exactly on the lattice, far from the origin too; each cell has its own
    # shade (3 inputs after the 16 phases), the same for one seed within a period
    assert fitted.cfg.lattice_shade
    seed = torch.tensor([9], dtype=torch.int32)
    features_at = lambda at, period=None: field.lattice_phases(at, period, seed)  # noqa: E731
    periodic = lambda features: torch.cat([features[..., :16], features[..., 19:]], dim=-1)  # noqa: E731
    a, b = np.array(result["lattice"][:2]), np.array(result["lattice"][2:])
    points = torch.from_numpy(np.random.default_rng(1).uniform(-1e4, 1e4, (1, 50, 3)))
    moved = points.clone()
    moved[..., :2] += torch.from_numpy(3 * a - 7 * b)
    assert torch.allclose(periodic(features_at(points)), periodic(features_at(moved)), atol=1e-4)
    assert not torch.allclose(features_at(points)[..., 16:19], features_at(moved)[..., 16:19], atol=1e-2)
    # the tileable sampler repeats every period in x and y, lattice phases included
    tileable = PeriodicSampler(SamplerSession(tmp_path / "fit" / TILEABLE_SAMPLER, threads=1), period=0.9)
    vector = np.concatenate([np.asarray(result["code"], np.float32), identity_colour(216)])
    near = np.random.default_rng(3).uniform(0, 1, (200, 3))
    base = tileable.sample(near, vector, 4)
    for shift in ((0.9, 0.0, 0.0), (0.0, -1.8, 0.0)):
        assert np.abs(tileable.sample(near + shift, vector, 4) - base).max() < 1e-4
    # ... because the phases do (the fit has barely moved their weights from zero): the
    # lattice is nudged to whole cells per period, and without the period it does not wrap
    period = torch.tensor(0.9, dtype=torch.float64)
    at = torch.from_numpy(near)[None]
    for shift in ((0.9, 0.0, 0.0), (0.0, 2.7, 0.0)):
        moved = at + torch.tensor(shift, dtype=torch.float64)
        assert torch.allclose(features_at(moved, period), features_at(at, period), atol=1e-4)
        assert not torch.allclose(features_at(moved), features_at(at), atol=1e-2)
    # the shader reads the lattice out of the sampler: its phase features are the field's
    code = np.asarray(result["code"], np.float32)
    vector = np.concatenate([code, np.zeros(216, np.float32)])
    constants = texture_constants(tmp_path / "fit" / "sampler.onnx", vector)
    repeat = constants.repeat                                   # u = R p + r
    basis = np.array(result["lattice"]).reshape(2, 2).T         # columns a, b
    assert np.allclose(repeat[:, :2] @ basis, np.eye(2), atol=1e-9) and np.allclose(repeat[:, 2:], 0, atol=1e-12)
    near = np.random.default_rng(2).uniform(-3, 3, (40, 3))
    u = near @ repeat[:, :3].T + repeat[:, 3]
    angle = 2 * np.pi * (u - np.floor(u))[:, :, None] * np.arange(1, 5)          # [P, axis, k]
    phases = np.concatenate([np.sin(angle).reshape(40, -1), np.cos(angle).reshape(40, -1)], axis=1)
    want = features_at(torch.from_numpy(near)[None]).numpy()[0]
    assert np.allclose(phases, want[:, :16], atol=1e-5)  # (then the mean cell's colour: 3 more)
    # the fit measured the photo's mean repeat cell, and the shader carries it
    assert fitted.cfg.lattice_cell == tuple(field.lattice_mean_cell.shape[:2])
    assert float(field.lattice_mean_cell.std()) == pytest.approx(1.0, rel=0.01)  # standardised
    for language in ("glsl", "wgsl"):
        text = emit_shader(tmp_path / "fit" / "sampler.onnx", vector, "bricks", language)
        assert "repeat lattice" in text and text.count("{") == text.count("}")
        assert "mean repeat cell" in text and f"{field.lattice_mean_cell.shape[0]}.0" in text


def test_mean_cell_holds_the_grout_where_the_photo_has_it_and_reads_back_between_samples():
    from model.lattice import lattice_mean_cell

    rng = np.random.default_rng(0)
    photo = 0.8 + 0.05 * rng.standard_normal((128, 160, 3)).astype(np.float32)  # marbling: averages away
    photo[3::16] = photo[:, 5::20] = 0.1  # grout: rows 3, 19, ...; columns 5, 25, ...
    cell = lattice_mean_cell(photo, (20.0, 0.0, 0.0, 16.0))  # [n_a (x), n_b (y), 3]
    assert cell.shape == (20, 16, 3)
    dark = cell.mean(axis=2) < -1.0
    # pixel centres at 5.5 and 3.5 px fall in bins 5 and 3 of their axes: those lines and nothing else
    assert dark[5].all() and dark[:, 3].all() and dark.sum() == 16 + 20 - 1
    # the field reads it bilinearly at cell-centred samples, wrapping across the cell's edge
    field = TextureSpace(ModelConfig(lattice=(20 / 256, 0.0, 0.0, 16 / 256), lattice_cell=(20, 16))).field
    field.lattice_mean_cell.copy_(torch.from_numpy(cell))
    centres = (torch.stack(torch.meshgrid(torch.arange(20), torch.arange(16), indexing="ij"), -1) + 0.5)
    phase = centres.to(torch.float64) / torch.tensor([20.0, 16.0], dtype=torch.float64)
    assert torch.allclose(field.mean_cell_colour(phase), torch.from_numpy(cell), atol=1e-6)
    edge = field.mean_cell_colour(torch.tensor([[0.0, 0.5 / 16]], dtype=torch.float64))
    assert torch.allclose(edge[0], torch.from_numpy((cell[0, 0] + cell[-1, 0]) / 2), atol=1e-6)


def test_a_lattice_field_starts_as_the_field_without_it() -> None:
    torch.manual_seed(0)
    plain = TextureSpace(ModelConfig()).field
    lattice = TextureSpace(ModelConfig(lattice=(0.125, 0.0, 0.0625, 0.043))).field
    missing, unexpected = lattice.load_state_dict(plain.state_dict(), strict=False)
    assert missing == ["decoder.from_phase.weight"] and unexpected == []
    cell = TextureSpace(ModelConfig(lattice=(0.125, 0.0, 0.0625, 0.043), lattice_cell=(32, 11))).field
    missing, _ = cell.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["decoder.from_phase.weight", "lattice_mean_cell"]
    cell.lattice_mean_cell.normal_()
    points = torch.from_numpy(np.random.default_rng(2).uniform(-5, 5, (1, 200, 3)))
    z = torch.randn(1, 8)
    with torch.no_grad():  # zero phase weights: the same texture until a fit moves them
        assert torch.equal(plain(points, z, torch.tensor(4)), lattice(points, z, torch.tensor(4)))
        assert torch.equal(plain(points, z, torch.tensor(4)), cell(points, z, torch.tensor(4)))


def test_a_lattice_fit_starts_drawing_the_mean_cell_dark_where_it_is_dark() -> None:
    """start_on_mean_cell: from zero cell weights, the field's colour follows the mean cell's
    colour at each point's phase (same sign, about ``share`` of the texture's spread), and
    the rest of the texture makes room for it (the total spread stays about the same)."""
    from model.lattice import mean_cell_share
    from model.train import start_on_mean_cell

    torch.manual_seed(0)
    lattice = (0.25, 0.0, 0.0, 0.25)
    space = TextureSpace(ModelConfig(lattice=lattice, lattice_cell=(16, 16)))
    grid = np.full((16, 16, 3), 0.8, np.float32)
    grid[:2] = grid[:, :2] = (0.2, 0.25, 0.3)  # grout two cells wide
    space.field.lattice_mean_cell.copy_(torch.from_numpy((grid - grid.mean((0, 1))) / grid.std()))
    points = torch.from_numpy(np.random.default_rng(2).uniform(-5, 5, (1, 4000, 3)))
    code, seed = torch.randn(1, 8), torch.tensor(4)
    with torch.no_grad():
        before = space.field(points, code, seed).reshape(-1, 3).numpy()
    start_on_mean_cell(space, code, 0.6, np.random.default_rng(0))
    with torch.no_grad():
        after = space.field(points, code, seed).reshape(-1, 3).numpy()
        cell = space.field.lattice_phases(points)[..., -3:].reshape(-1, 3).numpy()  # the cell's colour there
    assert np.corrcoef(before[:, 0], cell[:, 0])[0, 1] ** 2 < 0.01  # (nothing of the cell before)
    spread = before.std(axis=0).mean()
    for channel in range(3):  # (the share is of the mean spread: a channel with more of its own follows less)
        assert np.corrcoef(after[:, channel], cell[:, channel])[0, 1] > 0.25
    slope = ((after - after.mean(0)) * cell).sum() / np.square(cell).sum()
    assert 0.5 * 0.6 * spread < slope < 2 * 0.6 * spread
    assert 0.7 < after.std(axis=0).mean() / spread < 1.4
    # the share: a grid without marbling is all mean cell; noise on no lattice, almost none
    tiled = np.tile(grid, (8, 8, 1))
    assert mean_cell_share(tiled, (16.0, 0.0, 0.0, 16.0)) > 0.99
    noise = np.random.default_rng(3).random((128, 128, 3))
    assert mean_cell_share(noise, (16.0, 0.0, 0.0, 16.0)) < 0.3


def test_patch_side_defaults_to_128_with_or_without_a_lattice(tmp_path, monkeypatch):
    """The measured default (model/fit.py: PATCH); an explicit patch wins."""
    import model.fit as fit

    seen = []

    def fake_train(cfg, progress=None, interim=None, pause=None):
        seen.append(cfg.patch)
        raise StopFit

    monkeypatch.setattr(fit, "train", fake_train)
    space = space_checkpoint(tmp_path)
    bricks, plain = tmp_path / "bricks.png", tmp_path / "plain.png"
    Image.fromarray((running_bond() * 255).astype(np.uint8)).save(bricks)
    noise = ndimage.gaussian_filter(np.random.default_rng(2).random((256, 256)), 3)
    Image.fromarray((np.repeat(noise[..., None], 3, axis=2) * 255).astype(np.uint8)).save(plain)
    for image, patch in ((plain, None), (bricks, None), (plain, 48)):
        with pytest.raises(StopFit):
            fit_exemplar(image, tmp_path / "fit", init_checkpoint=space, patch=patch,
                         lattice="auto", grain="auto")
    assert seen == [fit.PATCH, fit.PATCH, 48] and fit.PATCH == 128


def test_a_fit_starts_from_the_code_an_upload_gets(tmp_path, skimage_textures):
    """The fit's first code is the served one (same crops, the torch encoder against the
    exported ONNX one), so a fit that keeps its start serves what the upload served."""
    from model.networks import load_checkpoint
    from model.train import initial_code
    from worker.encode import encode_image
    from worker.photo import resize_short_side
    from worker.runtime import ModelRuntime

    model, _ = load_checkpoint(space_checkpoint(tmp_path))
    photo = resize_short_side(skimage_textures["gravel"], model.cfg.exemplar_short_side)
    served = encode_image(ModelRuntime(tmp_path / "space"), photo)
    start = initial_code(model, photo, 128)[0].numpy()
    assert np.abs(served).max() > 0.01  # a code, not zeros
    np.testing.assert_allclose(start, served, atol=1e-4)


def test_an_even_photo_is_fitted_with_its_coarse_octaves_muted(tmp_path, monkeypatch, skimage_textures):
    """Gravel (even at large scales, no structure) mutes the octaves with cells of 32 px or
    more: 4 of 8 at 256 px a unit; a lattice photo, or even=None, mutes none."""
    import model.fit as fit

    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch, lambda cfg: cfg.mute_octaves)
    saved_png(tmp_path / "gravel.png", skimage_textures["gravel"])
    saved_png(tmp_path / "bricks.png", running_bond())
    for name, even in (("gravel", "auto"), ("bricks", "auto")):
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / f"{name}.png", tmp_path / name, init_checkpoint=space, even=even)
    assert seen == {"gravel": 4, "bricks": 0}
    with pytest.raises(StopFit):
        fit_exemplar(tmp_path / "gravel.png", tmp_path / "gravel", init_checkpoint=space, even=None)
    assert seen["gravel"] == 0
    assert fit.coarse_octaves(256.0, 8) == 4 and fit.coarse_octaves(128.0, 8) == 3


def test_the_library_detects_structure_by_default_as_the_cli_and_service_do(tmp_path, monkeypatch):
    """``fit_exemplar`` called with no grain or lattice argument looks for both, as
    ``python -m model.fit`` and an upload's refinement do: a running bond gets its lattice."""
    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch, lambda cfg: cfg.lattice)
    saved_png(tmp_path / "bricks.png", running_bond())
    with pytest.raises(StopFit):
        fit_exemplar(tmp_path / "bricks.png", tmp_path / "bricks", init_checkpoint=space)
    assert seen["bricks"] is not None


def test_a_photo_without_grain_or_lattice_is_fitted_from_its_lean(tmp_path, monkeypatch, skimage_textures):
    """An isotropic fit trains a warp that starts at the photo's lean (photo_lean); a lattice
    photo, or lean=None, trains none."""
    from model.structure import photo_lean

    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch, lambda cfg: (cfg.warp, cfg.warp_start))
    gravel = saved_png(tmp_path / "gravel.png", skimage_textures["gravel"])
    saved_png(tmp_path / "bricks.png", running_bond())
    for name in ("gravel", "bricks"):
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / f"{name}.png", tmp_path / name, init_checkpoint=space, grain="auto",
                         lattice="auto")
    assert seen["gravel"][0] and seen["gravel"][1] == pytest.approx(photo_lean(gravel), rel=0.02)
    assert seen["bricks"] == (False, None)
    with pytest.raises(StopFit):
        fit_exemplar(tmp_path / "gravel.png", tmp_path / "gravel", init_checkpoint=space, lean=None)
    assert seen["gravel"] == (False, None)


def test_a_strong_grain_is_fitted_with_longer_noise_cells(tmp_path, monkeypatch):
    """model.structure.grain_stretch picks the stretch the fit trains and exports: 16 for long
    fibres, 8 for a weak grain; the result and manifest say which (null without grain)."""
    from model.networks import load_checkpoint
    from eval.synthetic_photos import fibres

    space = space_checkpoint(tmp_path)
    seen = stop_before_training(monkeypatch, lambda cfg: (cfg.grain, cfg.grain_stretch))
    for name, photo in (("strong", fibres(40, 4)), ("weak", fibres(12, 4))):
        saved_png(tmp_path / f"{name}.png", photo)
        with pytest.raises(StopFit):
            fit_exemplar(tmp_path / f"{name}.png", tmp_path / name, init_checkpoint=space, grain="auto")
    assert seen == {"strong": ("y", 16.0), "weak": ("y", 8.0)}
    monkeypatch.undo()
    result = fit_exemplar(tmp_path / "strong.png", tmp_path / "fit", init_checkpoint=space, minutes=0.02, patch=32,
                          grain="auto")
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert result["grain_stretch"] == manifest["grain_stretch"] == 16.0
    fitted, _ = load_checkpoint(tmp_path / "fit" / "fit.pt")
    assert fitted.cfg.grain_stretch == 16.0 and fitted.field.world_scale[1].item() == pytest.approx(1 / 16)
    plain = fit_exemplar(tmp_path / "strong.png", tmp_path / "plain", init_checkpoint=space, minutes=0.02, patch=32,
                         grain=None)
    assert plain["grain"] is None and plain["grain_stretch"] is None


@pytest.mark.parametrize("kept_step, reported", [(0, 0), (25, 4)])
def test_a_fit_that_keeps_its_unmuted_start_reports_no_muted_octaves(tmp_path, monkeypatch, skimage_textures,
                                                                       kept_step, reported):
    """The probe's first score is of the unmuted start: when the fit ends on it (step 0),
    the served sampler mutes nothing, and the result and manifest say so."""
    import model.fit as fit

    space = space_checkpoint(tmp_path)

    def train(cfg, progress=None, interim=None, pause=None):  # noqa: ANN001, ANN202 - the space itself, kept at kept_step
        ckpt = torch.load(space, weights_only=False)
        path = Path(cfg.out) / "kept.pt"
        torch.save({**ckpt, "code": torch.zeros(1, 8), "step": kept_step, "wall_seconds": 1.0,
                    "probe": {"score": 1.0, "step": kept_step}}, path)
        assert cfg.mute_octaves == 4  # gravel: the fit trains muted
        return path

    monkeypatch.setattr(fit, "train", train)
    saved_png(tmp_path / "gravel.png", skimage_textures["gravel"])
    result = fit_exemplar(tmp_path / "gravel.png", tmp_path / "fit", init_checkpoint=space)
    manifest = json.loads((tmp_path / "fit" / "manifest.json").read_text())
    assert result["muted_octaves"] == manifest["muted_octaves"] == reported


def test_a_fit_publishes_its_interim_as_a_contract_sampler_with_its_structure(tmp_path, monkeypatch,
                                                                               skimage_textures):
    """``interim``: what train's Interim hands over (a model, its code, the step) is written as
    the sampler pair under OUTDIR/interim and passed on with the code and the result's
    structure; the fit then ends as usual."""
    import model.fit as fit

    space = space_checkpoint(tmp_path)
    interims = []
    monkeypatch.setattr(fit, "train", training_that_publishes(space, torch.full((1, 8), 0.25), 25, interims.append))
    saved_png(tmp_path / "gravel.png", skimage_textures["gravel"])
    published = []
    result = fit_exemplar(tmp_path / "gravel.png", tmp_path / "fit", init_checkpoint=space,
                          interim=lambda *args: published.append(args), interim_seconds=12.0)
    ((folder, code, step, structure),) = published
    assert interims[0].seconds == 12.0
    assert folder == tmp_path / "fit" / "interim" and step == 25 and code == [0.25] * 8
    assert structure == {k: result[k] for k in structure}  # gravel: even, leaning; as the result says
    assert structure["muted_octaves"] == 4 and structure["lean"] is not None and structure["lattice"] is None
    from model.colour import identity_colour

    for name in ("sampler.onnx", "sampler_tileable.onnx"):  # both load; the interim draws its own code
        session = ort.InferenceSession(str(folder / name), providers=["CPUExecutionProvider"])
        feeds = {"points": np.random.default_rng(0).random((64, 3)), "colour": identity_colour()[None].numpy(),
                 "z": np.asarray([code], np.float32), "seed": np.asarray(1, np.int64)}
        if name == "sampler_tileable.onnx":
            feeds["period"] = np.asarray(4.0)
        assert np.isfinite(session.run(None, feeds)[0]).all()
    assert json.loads((tmp_path / "fit" / "code.json").read_text())["code"] == [0.0] * 8  # the end's, not the interim's



@pytest.mark.parametrize("lean, start_counts", [("auto", True), (None, False)])
def test_an_interim_may_be_the_start_only_when_the_fit_builds_structure_in(tmp_path, monkeypatch, skimage_textures,
                                                                           lean, start_counts):
    """The leaning gravel's fit starts on a sampler the encoder's tiles lack (its lean), so its
    start may be the interim, served unmuted as the probe scored it; without lean, grain or
    lattice the start is the upload's own sampler and is never published as refined."""
    import model.fit as fit

    space = space_checkpoint(tmp_path)
    interims = []  # the start still best: Probe.lend_best hands step 0
    monkeypatch.setattr(fit, "train", training_that_publishes(space, torch.zeros(1, 8), 0, interims.append))
    saved_png(tmp_path / "gravel.png", skimage_textures["gravel"])
    published = []
    result = fit_exemplar(tmp_path / "gravel.png", tmp_path / "fit", init_checkpoint=space, lean=lean,
                          interim=lambda *args: published.append(args))
    ((_, _, step, structure),) = published
    assert interims[0].start_counts is start_counts
    assert step == 0 and structure["muted_octaves"] == 0  # the probe's start is unmuted
    assert result["muted_octaves"] == 4  # the end (step 50) trained muted
