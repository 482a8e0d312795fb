"""Training: a few steps lower the loss for every variant; the CLI checkpoints and resumes."""
from __future__ import annotations

import dataclasses
import inspect
import json

import numpy as np
import pytest
from PIL import Image

torch = pytest.importorskip("torch")

from model.config import VARIANTS  # noqa: E402
from model.networks import ModelConfig, TextureSpace, load_checkpoint  # noqa: E402
from model.slices import random_planes, render_slices  # noqa: E402
from model.vgg import shared_vgg  # noqa: E402
from model.losses import gram_loss, gram_matrices  # noqa: E402
from model.objective import LATTICE_CONTRAST_WEIGHT, Objective, crop_starts  # noqa: E402
from model.slices import lattice_partners  # noqa: E402
from model.train import main as train_main, train  # noqa: E402
from model.train_config import TrainConfig, parse_args  # noqa: E402


@pytest.fixture(scope="module")
def brick(skimage_textures):
    return skimage_textures["brick"][::4, ::4].copy()  # 128 x 128


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_a_few_steps_lower_the_loss(variant, brick, vgg):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = TextureSpace(ModelConfig(variant=variant))
    objective = Objective([brick], ("relu1_1", "relu2_1", "relu3_1"), "gram")
    crops = torch.from_numpy(brick[:64, :64].transpose(2, 0, 1).copy())[None].repeat(2, 1, 1, 1)
    origins, axes = random_planes(2, rng, extent=4.0)
    seeds = torch.tensor([1, 2])
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss():
        z = model.encode(crops * 2 - 1)
        return objective(render_slices(model.field, z, seeds, origins, axes, 32), np.array([0, 0]))

    first = loss().item()
    for _ in range(20):
        optimizer.zero_grad()
        value = loss()
        value.backward()
        optimizer.step()
    assert loss().item() < 0.97 * first  # fixed batch: any drop is real, 3% is a margin


def test_cli_trains_checkpoints_and_resumes(tmp_path, brick, vgg):
    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    out = tmp_path / "run"
    common = ["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32",
              "--batch", "1", "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1,relu2_1"]
    train_main(common + ["--steps", "3"])
    model, ckpt = load_checkpoint(out / "checkpoint.pt")
    assert ckpt["step"] == 3 and ckpt["code"].shape == (1, 8)
    # checkpoints written before the optimiser groups carried their base rate still resume
    for group in ckpt["optimizer"]["param_groups"]:
        del group["base_lr"]
    torch.save(ckpt, out / "checkpoint.pt")
    train_main(common + ["--steps", "5"])
    _, ckpt = load_checkpoint(out / "checkpoint.pt")
    assert ckpt["step"] == 5  # resumed from 3, not restarted
    lines = (out / "log.jsonl").read_text().splitlines()
    assert len(lines) == 5


def test_probe_keeps_the_best_scoring_state(tmp_path, brick, vgg):
    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    out = tmp_path / "run"
    # a learning rate high enough to make some steps worse, so the choice matters
    train_main(["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32", "--batch", "1",
                "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1,relu2_1", "--steps", "4",
                "--lr", "0.05", "--warmup", "1", "--probe-every", "1"])
    scores = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines() if "probe" in line]
    assert [s["step"] for s in scores] == [0, 1, 2, 3, 4]
    model, ckpt = load_checkpoint(out / "checkpoint.pt")
    best = min(scores, key=lambda s: s["probe"])
    assert ckpt["probe"]["step"] == best["step"] and ckpt["step"] == 4
    assert abs(ckpt["probe"]["score"] - best["probe"]) < 1e-4


def test_lattice_partners_share_the_phases_not_the_place():
    lattice = (0.25, 0.0, 0.125, 0.3)
    field = TextureSpace(ModelConfig(lattice=lattice)).field
    origins = torch.from_numpy(np.random.default_rng(1).uniform(-50, 50, (64, 3)))
    partners = lattice_partners(origins, lattice, np.random.default_rng(2))
    steps = (partners - origins)[:, :2].numpy() @ np.linalg.inv(np.array(lattice).reshape(2, 2))
    assert np.allclose(steps, np.round(steps), atol=1e-9) and np.all(np.abs(np.round(steps)).sum(axis=1) > 0)
    assert torch.equal(partners[:, 2], origins[:, 2])  # same depth: the same slice plane, moved
    phases = field.lattice_phases(torch.stack([origins, partners])[:, :, None, :].reshape(2, -1, 3))
    assert torch.allclose(phases[0], phases[1], atol=1e-4)


def test_pair_contrast_charges_identical_repeats_and_frees_varied_ones(vgg):
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.3, 0.7, (64, 64, 3)).astype(np.float32)
    objective = Objective([photo], ("relu1_1",), "gram", lattice_px=(16.0, 0.0, 0.0, 16.0))
    patch = torch.rand(1, 3, 32, 32)
    indices = np.zeros(2, np.int64)
    stamped = objective.pair_contrast(torch.cat([patch, patch]), indices)
    assert float(stamped) == pytest.approx(LATTICE_CONTRAST_WEIGHT)
    varied = objective.pair_contrast(torch.cat([patch, torch.rand(1, 3, 32, 32)]), indices)
    assert float(varied) == 0.0  # as different as the photo's repeats: no charge
    assert float(objective(torch.cat([patch, patch]), indices, pairs=True)) > float(
        objective(torch.cat([patch, patch]), indices))
    assert objective.pairs  # (random pixels: its 16-px "repeats" differ as much as any two pixels)
    # a photo whose repeats are the same (the grill's holes) gives pairs nothing to charge
    repeated = np.tile(photo[:16, :16], (4, 4, 1))
    assert not Objective([repeated], ("relu1_1",), "gram", lattice_px=(16.0, 0.0, 0.0, 16.0)).pairs
    assert not Objective([photo], ("relu1_1",), "gram").pairs


def test_objective_adds_the_spectrum_weighed_by_the_photos_gram_magnitude(vgg, brick):
    from model.losses import gram_energy, spectrum_loss, spectrum_target, target_grams

    photo = np.ascontiguousarray(brick if brick.ndim == 3 else np.repeat(brick[..., None], 3, axis=2))
    layers = ("relu1_1",)
    plain = Objective([photo], layers, "gram")
    weighted = Objective([photo], layers, "gram", spectrum_weight=2.0)
    torch.manual_seed(0)
    patch, indices = torch.rand(1, 3, 32, 32) * 0.5, np.zeros(1, np.int64)
    extra = float(weighted(patch, indices)) - float(plain(patch, indices))
    energy = gram_energy(target_grams(torch.from_numpy(photo.transpose(2, 0, 1).copy())[None], shared_vgg(layers)))
    expect = 2.0 * energy * float(spectrum_loss(patch, spectrum_target(photo, 32))[0])
    assert extra == pytest.approx(expect, rel=1e-4)  # weighed by the photo's Gram magnitude


def test_a_fit_with_the_spectrum_charges_it_in_steps_and_probes(tmp_path, brick, vgg):
    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)

    def run(name: str, spectrum: str) -> list[dict]:
        train_main(["--mode", "single", "--exemplar", str(image), "--out", str(tmp_path / name), "--patch", "32",
                    "--batch", "2", "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1,relu2_1",
                    "--steps", "1", "--colour-normalise", "--spectrum", spectrum, "--probe-every", "1"])
        return [json.loads(line) for line in (tmp_path / name / "log.jsonl").read_text().splitlines()]

    plain, charged = run("plain", "0"), run("charged", "1")
    # the same seed draws the same patches: the first step and the first probe cost more with it
    assert charged[0]["probe"] > plain[0]["probe"] and charged[1]["loss"] > plain[1]["loss"]


def test_scoring_without_gradients_goes_plane_by_plane_to_the_same_numbers(vgg):
    # The probe renders and scores one plane / image at a time (faster on one thread); the
    # numbers must be those of the batch: each plane keeps its own code, seed and place.
    torch.manual_seed(0)
    field = TextureSpace(ModelConfig()).field
    origins, axes = random_planes(3, np.random.default_rng(0), extent=2.0)  # near the origin: float32 exact
    codes, seeds = torch.randn(3, 8), torch.tensor([4, 5, 6])
    with torch.no_grad():
        one_by_one = render_slices(field, codes, seeds, origins, axes, 24)
    batched = render_slices(field, codes, seeds, origins, axes, 24).detach()  # with gradients: one call
    assert one_by_one.shape == (3, 3, 24, 24)
    assert torch.allclose(one_by_one, batched, atol=1e-4)
    assert not torch.allclose(one_by_one[0], one_by_one[1], atol=1e-2)  # not one plane three times
    photo = np.random.default_rng(1).uniform(0.2, 0.8, (48, 48, 3)).astype(np.float32)
    objective = Objective([photo, photo[::-1].copy()], ("relu1_1", "relu2_1"), "gram")
    indices = np.array([0, 1, 0])
    with torch.no_grad():
        scored = float(objective(batched, indices))
    assert scored == pytest.approx(float(objective(batched, indices)), rel=1e-5)


@pytest.mark.parametrize("grain, axis, role", [("x", 0, 0), ("y", 1, 1)])
def test_grain_planes_keep_the_grain_axis_in_the_exemplars_role(grain, axis, role):
    # A y-grain exemplar (stripes running up-down) must show its stripes up-down on the xy
    # tile plane too: every plane's v axis (patch rows) is world y; for x-grain, u is world x.
    origins, axes = random_planes(64, np.random.default_rng(0), grain=grain)
    along = np.eye(3)[axis]
    assert np.allclose(axes[:, role].numpy(), along)
    assert np.allclose((axes[:, 1 - role].numpy() @ along), 0.0)             # the other axis is across it
    assert np.allclose(np.linalg.norm(axes.numpy(), axis=-1), 1.0)
    assert len({tuple(np.round(a, 6)) for a in axes[:, 1 - role].numpy()}) > 4  # turned about the grain
    with pytest.raises(ValueError):
        random_planes(2, np.random.default_rng(0), grain="z")


def test_anchor_changes_the_transform_gradient_not_the_colours():
    # Far from the origin the "shift the noise" part of a transform's gradient is ~|x| times
    # larger and useless (the noise is stationary); anchoring at the plane removes it.
    torch.manual_seed(0)
    field = TextureSpace(ModelConfig(smooth=True, nearest_input=False)).field
    with torch.no_grad():
        field.translator.to_transform.bias.normal_(0, 0.1)
    points = torch.rand(2, 300, 3, dtype=torch.float64) * 2 + 700
    z, seeds = torch.randn(2, 8), torch.tensor([3, 4])
    grads = []
    for anchor in (None, points[:, 0]):
        field.zero_grad()
        rgb = field(points, z, seeds, anchor=anchor)
        rgb.square().mean().backward()
        grads.append((rgb.detach(), field.translator.to_transform.bias.grad.norm().item()))
    assert torch.equal(grads[0][0], grads[1][0])
    assert grads[1][1] * 100 < grads[0][1]


def test_colour_normalised_run_warm_starts_codes_and_decays(tmp_path, brick, vgg):
    # A space run, then a --colour-normalise run from it: the code table starts from the
    # space's learned codes (not random ones), the encoder becomes colour-blind, and the
    # learning rate falls linearly to 10% between --decay-start and --decay-end.
    from model.train import learning_rate

    data = tmp_path / "data"
    data.mkdir()
    for k, tint in enumerate([(1.0, 0.6, 0.3), (0.4, 0.5, 1.0)]):
        grey = brick if brick.ndim == 3 else brick[..., None]
        Image.fromarray((grey * np.array(tint) * 255).astype(np.uint8)).save(data / f"t{k}.png")
    common = ["--data", str(data), "--patch", "32", "--batch", "2", "--short-side", "128", "--crop", "64",
              "--quiet", "--layers", "relu1_1,relu2_1", "--exclude", ""]
    train_main(common + ["--out", str(tmp_path / "space"), "--steps", "2"])
    _, space = load_checkpoint(tmp_path / "space" / "checkpoint.pt")
    train_main(common + ["--out", str(tmp_path / "cn"), "--steps", "1", "--code-lr", "1e-6",
                         "--init", str(tmp_path / "space" / "checkpoint.pt"), "--colour-normalise"])
    model, ckpt = load_checkpoint(tmp_path / "cn" / "checkpoint.pt")
    assert model.cfg.colour_blind_encoder and not space["config"]["colour_blind_encoder"]
    assert torch.allclose(ckpt["codes"], space["codes"], atol=1e-4)
    assert learning_rate(50, 1.0, 10, (100, 200)) == 1.0
    assert learning_rate(150, 1.0, 10, (100, 200)) == pytest.approx(0.55)
    assert learning_rate(500, 1.0, 10, (100, 200)) == pytest.approx(0.1)
    # --decay-by-time: the same fall over a timed run's wall time, whatever its step
    assert learning_rate(500, 1.0, 10, time_done=0.0) == 1.0
    assert learning_rate(500, 1.0, 10, time_done=0.5) == pytest.approx(0.55)
    assert learning_rate(5, 1.0, 10, time_done=1.0) == pytest.approx(0.06)  # still warming up, and at the floor


def test_a_space_on_new_photos_starts_its_codes_at_the_encoders(tmp_path, brick, vgg):
    # --init from a space of two photos onto a corpus of three: the table cannot be copied,
    # so each row starts at the init encoder's code of its photo (the code an upload of it
    # gets), not at random rows the decoder has never rendered.
    from model.data import TextureDataset
    from model.train import initial_code

    def write(folder, tints):
        folder.mkdir()
        for k, tint in enumerate(tints):
            image = np.roll(brick, 17 * k, axis=1) * np.array(tint)
            Image.fromarray((image * 255).astype(np.uint8)).save(folder / f"t{k}.png")

    write(tmp_path / "two", [(1.0, 0.6, 0.3), (0.4, 0.5, 1.0)])
    write(tmp_path / "three", [(1.0, 1.0, 1.0), (0.2, 0.9, 0.4), (0.9, 0.9, 0.2)])
    common = ["--patch", "32", "--batch", "2", "--short-side", "128", "--crop", "64", "--quiet",
              "--layers", "relu1_1", "--exclude", "", "--colour-normalise"]
    train_main(common + ["--data", str(tmp_path / "two"), "--out", str(tmp_path / "space"), "--steps", "2"])
    init, _ = load_checkpoint(tmp_path / "space" / "checkpoint.pt")
    train_main(common + ["--data", str(tmp_path / "three"), "--out", str(tmp_path / "big"), "--steps", "1",
                         "--code-lr", "1e-9", "--init", str(tmp_path / "space" / "checkpoint.pt")])
    _, ckpt = load_checkpoint(tmp_path / "big" / "checkpoint.pt")
    images = TextureDataset(str(tmp_path / "three"), short_side=128).images
    expected = torch.cat([initial_code(init, image, 64) for image in images])
    assert ckpt["codes"].shape == (3, init.cfg.code_size)
    assert torch.allclose(ckpt["codes"], expected, atol=1e-4)
    assert not torch.allclose(expected[0], expected[1], atol=1e-3)  # the photos' own codes


def test_a_timed_run_decaying_by_time_ends_near_its_floor(tmp_path, brick, vgg):
    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    train_main(["--mode", "single", "--exemplar", str(image), "--out", str(tmp_path / "fit"), "--minutes", "0.04",
                "--patch", "32", "--batch", "1", "--short-side", "64", "--layers", "relu1_1", "--warmup", "1",
                "--lr", "1e-3", "--decay-by-time", "--quiet"])
    rates = [json.loads(line)["lr"] for line in (tmp_path / "fit" / "log.jsonl").read_text().splitlines()]
    assert len(rates) >= 3 and rates == sorted(rates, reverse=True)
    assert rates[0] > 0.8e-3 and rates[-1] < 0.5e-3  # the last step ran in the run's second half


def test_parse_args_gives_the_train_config_of_the_flags(capsys):
    cfg = parse_args(["--out", "r", "--mode", "single", "--exemplar", "a.png", "--short-side", "128", "--minutes", "2",
                      "--transform-lr", "5e-3", "--grain", "y", "--no-nearest", "--decay-start", "0", "--exclude", ""])
    assert isinstance(cfg, TrainConfig)
    assert cfg == TrainConfig(out="r", mode="single", exemplar="a.png", short_side=128, minutes=2.0, transform_lr=5e-3,
                              grain="y", no_nearest=True, decay_start=0, exclude="")
    assert parse_args(["--out", "r"]) == TrainConfig(out="r")  # a flag not given keeps the config's default
    with pytest.raises(SystemExit):
        parse_args(["--help"])
    usage = capsys.readouterr().out
    assert all(f"--{f.name.replace('_', '-')}" in usage for f in dataclasses.fields(TrainConfig))  # a flag per field
    with pytest.raises(SystemExit, match="device"):
        TrainConfig(out="r", device="gpu")  # the CLI's choices hold for configs built in code


def test_train_reads_as_one_short_story():
    # setup, resume, steps, probe and save are named pieces; train() only tells the run
    assert len(inspect.getsource(train).splitlines()) < 60


def test_muted_octaves_stay_silent_through_training_and_the_start_stays_on_offer(tmp_path, brick, vgg):
    """--mute-octaves N zeroes the N coarsest octaves' decoder columns and Adam never moves
    them (the others do move); the probe scored the unmuted start first, so a run whose
    muted states all score worse can still end on it."""
    from model.networks import ModelConfig

    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    out = tmp_path / "run"
    train_main(["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32", "--batch", "1",
                "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1,relu2_1", "--steps", "3",
                "--mute-octaves", "3", "--probe-every", "1", "--no-nearest", "--warmup", "1"])
    per_octave = 3  # --no-nearest: the interpolated RGB of each octave
    _, ckpt = load_checkpoint(out / "checkpoint.pt")
    steps = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    weight = ckpt["model"]["field.decoder.from_noise.weight"]
    assert weight.shape[1] == ModelConfig().n_octaves * per_octave
    if ckpt["probe"]["step"] > 0:  # a muted state won: the coarse columns are exactly zero
        assert not weight[:, : 3 * per_octave].any() and weight[:, 3 * per_octave:].abs().sum() > 0
    assert [s["step"] for s in steps if "probe" in s][0] == 0  # the start was scored before muting

    torch.manual_seed(0)
    model = TextureSpace(ModelConfig(nearest_input=False))
    from model.train import mute_coarse_octaves

    mute_coarse_octaves(model, 3)
    weight = model.field.decoder.from_noise.weight
    before = weight.detach().clone()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(3):
        points = torch.rand(1, 64, 3, dtype=torch.float64)
        model.sample(points, torch.randn(1, 8), 1).sum().backward()
        optimiser.step()
        optimiser.zero_grad()
    assert not weight[:, :9].any() and not torch.equal(weight[:, 9:], before[:, 9:])


def test_lend_best_hands_the_best_state_and_puts_the_training_state_back():
    """Probe.lend_best: ``use`` sees the best weights and code; afterwards the run is where it
    was (weights, code, train mode), and the optimiser still holds the same parameters."""
    from types import SimpleNamespace

    from model.probe import Probe

    model = torch.nn.Linear(2, 2)
    codes = torch.nn.Parameter(torch.zeros(1, 8))
    probe = object.__new__(Probe)  # its state only: no planes, no objective
    probe.run = SimpleNamespace(model=model, codes=codes, step=3)
    probe.best = probe.snapshot()
    with torch.no_grad():  # training moved on after the best state
        model.weight.add_(1.0)
        codes.add_(2.0)
    current_weight, parameter = model.weight.detach().clone(), model.weight
    seen = []
    probe.lend_best(lambda m, code, step: seen.append((m.weight.detach().clone(), code, step, m.eval())))
    ((weight, code, step, _),) = seen
    assert torch.equal(weight, probe.best["model"]["weight"]) and torch.equal(code, torch.zeros(1, 8)) and step == 3
    assert torch.equal(model.weight, current_weight) and torch.equal(codes, torch.full((1, 8), 2.0))
    assert model.training and model.weight is parameter


def test_a_probe_renders_in_the_runs_precision_and_scores_outside_autocast(monkeypatch):
    """Probe.score: the planes render under the run's autocast (bf16 here), the objective is
    called outside it, as in training, so its colour moments and Grams stay float32. Inside it,
    a bf16 colour covariance came out not positive-definite and its Cholesky ended a fit."""
    from types import SimpleNamespace

    import model.probe as probe_module
    from model.colour import transfer_colour_moments
    from model.probe import Probe

    seen = {}

    def render(*args):  # noqa: ANN002, ANN202
        seen["render"] = torch.is_autocast_enabled("cpu")
        return torch.rand(4, 3, 16, 16).to(torch.bfloat16)

    def objective(patches, indices, pairs):  # noqa: ANN001, ANN202
        seen["objective"] = torch.is_autocast_enabled("cpu")
        seen["dtype"] = patches.dtype
        flat = torch.full((4, 3, 16, 16), 0.5)  # a flat patch: only the ridge keeps it invertible
        flat[:, 0, 0, 0] = 0.5001
        return transfer_colour_moments(flat, torch.full((4, 3), 0.5), torch.eye(3).repeat(4, 1, 1) * 1e-3).mean()

    monkeypatch.setattr(probe_module, "render_slices", render)
    probe = object.__new__(Probe)
    probe.run = SimpleNamespace(model=SimpleNamespace(field=None), codes=torch.zeros(1, 8), device=torch.device("cpu"),
                                precision=torch.bfloat16, cfg=SimpleNamespace(patch=8), objective=objective)
    probe.seeds = probe.origins = probe.axes = None
    probe.pairs = False
    assert np.isfinite(probe.score())
    assert seen == {"render": True, "objective": False, "dtype": torch.float32}


def test_an_interim_is_published_once_at_the_first_probe_that_beats_the_start(tmp_path, brick, vgg):
    """train(interim=Interim(0, ...)) in a fit: one call, at the first probe whose best state
    is past step 0, with that state; training goes on to its last step afterwards."""
    from model.probe import Interim

    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    out = tmp_path / "run"
    cfg = parse_args(["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32", "--batch", "1",
                      "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1,relu2_1", "--steps", "6",
                      "--lr", "0.01", "--warmup", "1", "--probe-every", "1"])
    published = []
    train(cfg, interim=Interim(0.0, lambda model, code, step: published.append((step, code.clone()))))
    scores = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines() if "probe" in line]
    better = [s["step"] for s in scores if s["probe"] < scores[0]["probe"]]
    _, ckpt = load_checkpoint(out / "checkpoint.pt")
    assert ckpt["step"] == 6 and better  # (at this seed and rate the second step already beats the start)
    ((step, code),) = published
    assert step == better[0]
    assert code.shape == (1, 8)


def test_an_interim_waits_for_its_seconds():
    from types import SimpleNamespace

    from model.probe import Interim

    calls = []
    interim = Interim(60.0, None)
    probe = SimpleNamespace(best={"step": 25}, lend_best=lambda use: calls.append(use))
    interim.offer(probe, 59.0)
    assert calls == [] and not interim.done
    interim.offer(SimpleNamespace(best={"step": 0}, lend_best=calls.append), 61.0)  # the start still best
    assert calls == [] and not interim.done
    interim.offer(probe, 61.0)
    interim.offer(probe, 90.0)  # once
    assert len(calls) == 1 and interim.done


def test_an_interim_of_a_fit_with_structure_may_be_its_start():
    """``start_counts``: a start still best at the interim's second is published then."""
    from types import SimpleNamespace

    from model.probe import Interim

    calls = []
    interim = Interim(10.0, None, start_counts=True)
    start = SimpleNamespace(best={"step": 0}, lend_best=calls.append)
    interim.offer(start, 9.0)
    assert calls == []
    interim.offer(start, 11.0)
    interim.offer(SimpleNamespace(best={"step": 25}, lend_best=calls.append), 20.0)  # once
    assert calls == [None] and interim.done


def test_precision_auto_follows_the_hardware_and_named_precisions_are_kept(monkeypatch):
    from model import device as device_module

    cpu = torch.device("cpu")
    assert device_module.resolve_precision("fp32", cpu) is None
    assert device_module.resolve_precision("bf16", cpu) is torch.bfloat16
    monkeypatch.setattr(device_module, "cpu_has_native_bf16", lambda: False)  # emulated bf16: no faster
    assert device_module.resolve_precision("auto", cpu) is None
    monkeypatch.setattr(device_module, "cpu_has_native_bf16", lambda: True)
    assert device_module.resolve_precision("auto", cpu) is torch.bfloat16
    with pytest.raises(SystemExit):
        TrainConfig(out="x", precision="fp16")


def test_patches_are_scored_against_the_mean_gram_of_the_photos_crops_of_their_size(vgg, brick):
    """A patch's target is the mean Gram of the photo's crops of the patch's size (padding reaches
    more of a small image's deep features); the photo's own crops score far lower against it than
    against the whole photo's Gram, and a patch as large as the photo keeps the whole Gram."""
    layers = ("relu1_1", "relu3_1", "relu5_1")
    objective = Objective([brick], layers, "gram")  # 128 x 128
    starts = crop_starts(128, 64)
    assert starts == [0, 32, 64] and crop_starts(1024, 128) == [0, 299, 597, 896] and crop_starts(1024, 256) == [0, 768]
    crops = np.stack([brick[y:y + 64, x:x + 64] for y in starts for x in starts]).transpose(0, 3, 1, 2)
    crops = torch.from_numpy(np.ascontiguousarray(crops))
    with torch.no_grad():
        mean = {name: g.mean(0, keepdim=True) for name, g in gram_matrices(objective.vgg(crops)).items()}
        target = objective.gram_target(0, 64)
        for name in layers:
            torch.testing.assert_close(target[name], mean[name], rtol=1e-4, atol=1e-6)
        assert objective.gram_target(0, 128) is objective.targets[0]
        own = float(objective(crops, np.zeros(len(crops), dtype=np.int64)))
        against_whole = float(gram_loss(objective.features(crops), objective.targets[0]))
    assert own < 0.5 * against_whole


def test_bf16_features_are_float32_and_their_gram_loss_stays_within_a_percent(vgg, brick):
    layers = ("relu1_1", "relu2_1", "relu3_1", "relu4_1", "relu5_1")
    exact = Objective([brick], layers, "gram")
    mixed = Objective([brick], layers, "gram", precision=torch.bfloat16)
    images = torch.from_numpy(np.stack([brick[:64, :64], brick[64:, 64:]]).transpose(0, 3, 1, 2).copy())
    feats = mixed.features(images)
    assert all(value.dtype == torch.float32 for value in feats.values())
    assert mixed.features(images)["relu3_1"].shape == exact.features(images)["relu3_1"].shape
    noisy = (images + 0.1 * torch.rand_like(images)).clamp(0, 1)
    reference, reduced = float(exact(noisy, np.array([0, 0]))), float(mixed(noisy, np.array([0, 0])))
    assert reference > 0 and abs(reduced - reference) < 0.01 * reference


def test_a_fit_paused_after_its_interim_resumes_to_the_uninterrupted_result(tmp_path, brick, vgg):
    """train(pause=...) stops right after the interim with a resumable checkpoint; training the
    same --out again ends where one uninterrupted run ends (same steps, code and best state)."""
    from model.probe import Interim

    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)

    def config(out):
        return parse_args(["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32",
                           "--batch", "1", "--short-side", "128", "--crop", "64", "--quiet", "--layers",
                           "relu1_1,relu2_1", "--steps", "6", "--lr", "0.01", "--warmup", "1", "--probe-every", "1",
                           "--precision", "fp32"])
    train(config(tmp_path / "whole"))
    published, asked = [], []
    paused = train(config(tmp_path / "paused"), interim=Interim(0.0, lambda model, code, step: published.append(step)),
                   pause=lambda: asked.append(True) or True)
    _, ckpt = load_checkpoint(paused)
    assert asked == [True] and ckpt["paused"] and ckpt["step"] == published[0] < 6
    assert ckpt["probe_best"]["step"] == published[0] and ckpt["budget_seconds"] >= 0
    train(config(tmp_path / "paused"))  # the continuation: no interim, no pause
    _, whole = load_checkpoint(tmp_path / "whole" / "checkpoint.pt")
    _, resumed = load_checkpoint(tmp_path / "paused" / "checkpoint.pt")
    assert resumed["step"] == whole["step"] == 6 and not resumed.get("paused")
    assert resumed["probe"]["step"] == whole["probe"]["step"]
    assert torch.allclose(resumed["code"], whole["code"], atol=1e-5)


def test_an_interim_asks_for_one_probe_at_its_second():
    from model.probe import Interim

    interim = Interim(10.0, None)
    assert not interim.due(9.9)
    assert interim.due(10.2) and not interim.due(10.4)  # once, then the schedule's probes


def test_an_interim_published_by_a_probe_that_straddles_its_second_is_still_due_once():
    """A scheduled probe that starts at 9.x s publishes after 10 s; the next step is still the
    interim's second for the pause, or that fit never paused (seen: a 90-s fit held the lane
    for all 90 s when its 25th step came just before the tenth second)."""
    from types import SimpleNamespace

    from model.probe import Interim

    interim = Interim(10.0, lambda *state: None)
    assert not interim.due(9.6)
    interim.offer(SimpleNamespace(best={"step": 25}, lend_best=lambda use: None), 12.1)
    assert interim.done
    assert interim.due(12.6) and not interim.due(13.1)


def test_a_flat_photo_leans_nowhere_and_its_warp_is_the_identity():
    """A solid grey upload (no gradient anywhere) crashed its refinement three times with a
    division by zero in lean_warp: its lean's stretch came out 0."""
    from model.structure import photo_lean
    from model.train import lean_warp

    degrees, stretch = photo_lean(np.full((64, 64, 3), 0.5, np.float32))
    assert stretch == 1.0
    assert torch.equal(lean_warp(degrees, stretch), torch.eye(2, dtype=torch.float64))


def test_a_fit_pauses_at_its_interims_second_even_when_its_start_stays_best(tmp_path, brick, vgg):
    """A start that stays best (rates 0 here; the validation grass in practice) publishes no
    interim; the fit still pauses at the interim's second, or it held the uploads behind it
    for its whole budget."""
    from model.probe import Interim

    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    cfg = parse_args(["--mode", "single", "--exemplar", str(image), "--out", str(tmp_path / "run"), "--patch", "32",
                      "--batch", "1", "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1",
                      "--steps", "6", "--lr", "0", "--code-lr", "0", "--warmup", "1", "--probe-every", "1"])
    published, asked = [], []
    path = train(cfg, interim=Interim(0.0, lambda *state: published.append(state)),
                 pause=lambda: asked.append(True) or True)
    _, ckpt = load_checkpoint(path)
    assert published == [] and asked == [True] and ckpt["paused"] and ckpt["step"] == 1


def test_a_fit_canceled_from_its_progress_hook_stops_without_a_last_score(tmp_path, brick, vgg):
    """A cancel (the service's progress hook raises) ends the fit at once: no last probe and
    no best state restored for a result nobody takes (they held a canceled fit 3-5 s more)."""
    image = tmp_path / "brick.png"
    Image.fromarray((brick * 255).astype(np.uint8)).save(image)
    out = tmp_path / "run"
    cfg = parse_args(["--mode", "single", "--exemplar", str(image), "--out", str(out), "--patch", "32", "--batch", "1",
                      "--short-side", "128", "--crop", "64", "--quiet", "--layers", "relu1_1", "--steps", "20",
                      "--warmup", "1", "--probe-every", "10"])
    steps = []

    def progress(fraction):  # noqa: ANN001, ANN202
        steps.append(fraction)
        if len(steps) == 3:
            raise KeyboardInterrupt("canceled")
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=progress)
    scores = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines() if "probe" in line]
    assert scores == [0]  # the start's score only
    _, ckpt = load_checkpoint(out / "checkpoint.pt")
    assert ckpt["step"] == 3 and ckpt.get("probe") is None


def test_a_fit_starts_from_the_code_it_is_given():
    """--start-code (an upload's stored code) is the single-mode code's start; a code of
    another length than the space's is refused."""
    from model.train import learned_codes

    model = TextureSpace(ModelConfig())
    image = np.zeros((64, 64, 3), np.float32)
    start = [0.1 * i for i in range(model.cfg.code_size)]
    cfg = TrainConfig(mode="single", out="unused", init="space.pt", start_code=start)
    code = learned_codes(cfg, model, [image], 64, None)
    assert code.shape == (1, model.cfg.code_size)
    np.testing.assert_allclose(code.detach().numpy()[0], start, atol=1e-7)
    assert parse_args(["--out", "o", "--mode", "single", "--start-code", "0.5", "-1"]).start_code == [0.5, -1.0]
    with pytest.raises(SystemExit, match="start-code has 3 numbers"):
        learned_codes(dataclasses.replace(cfg, start_code=[0.0, 1.0, 2.0]), model, [image], 64, None)
