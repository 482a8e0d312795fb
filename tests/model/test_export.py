"""Export -> ONNX Runtime: the sampler contract (docs/ARCHITECTURE.md, Contract 1) and torch parity."""
from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest

torch = pytest.importorskip("torch")

from model.colour import apply_colour, colour_size, identity_colour  # noqa: E402
from model.export import MAX_IR_VERSION, export_model  # noqa: E402
from model.networks import ModelConfig, TextureSpace  # noqa: E402


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(3)
    model = TextureSpace(ModelConfig(variant="ours"))
    out = tmp_path_factory.mktemp("export")
    manifest = export_model(model, out, {"mode": "untrained"})
    session = ort.InferenceSession(str(out / "sampler.onnx"), providers=["CPUExecutionProvider"])
    return model, session, manifest, out


def run(session, points, z, seed, colour=None):
    """The sampler with the identity colour table unless one is given (rows as z)."""
    if colour is None:
        colour = np.repeat(identity_colour()[None].numpy(), len(z), axis=0)
    feed = {"points": points, "z": z, "seed": np.asarray(seed, dtype=np.int64), "colour": colour}
    return session.run(None, feed)[0]


def random_colour_tables(rng, rows: int, knots: int = 64) -> np.ndarray:
    """Valid colour tables (model/colour.py layout): random maps, increasing curves."""
    start = rng.uniform(0.2, 0.6, (rows, 3))  # compressed colour lies in ~0.25..1
    step = rng.uniform(0.3, 0.9, (rows, 3)) / knots
    values = np.sort(rng.uniform(0.2, 1.1, (rows, 3, knots)), axis=-1).reshape(rows, -1)
    parts = [rng.normal(0, 1, (rows, 9)), start, step, values, rng.normal(0, 0.7, (rows, 9))]
    return np.concatenate(parts, axis=1).astype(np.float32)


def test_sampler_io_names_shapes_dtypes(exported):
    _, session, manifest, out = exported
    inputs = {i.name: i for i in session.get_inputs()}
    assert list(inputs) == ["points", "z", "seed", "colour"]
    assert inputs["colour"].type == "tensor(float)" and inputs["colour"].shape[1] == colour_size()
    assert manifest["colour_size"] == colour_size()
    assert inputs["points"].type == "tensor(double)" and inputs["points"].shape[1] == 3
    assert inputs["z"].type == "tensor(float)" and inputs["z"].shape[1] == 8
    assert inputs["seed"].type == "tensor(int64)"
    (output,) = session.get_outputs()
    assert output.name == "rgb" and output.type == "tensor(float)"
    rgb = run(session, np.zeros((5, 3)), np.zeros((1, 8), np.float32), 0)
    assert rgb.shape == (5, 3) and rgb.dtype == np.float32
    assert ((rgb >= 0) & (rgb <= 1)).all()
    assert run(session, np.zeros((5, 3)), np.zeros((1, 8), np.float32), [0]).shape == (5, 3)  # seed [1]
    import onnx

    for name in ("encoder.onnx", "sampler.onnx"):
        assert onnx.load(str(out / name)).ir_version <= MAX_IR_VERSION
    enc = ort.InferenceSession(str(out / "encoder.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in enc.get_inputs()] == ["image"] and enc.get_outputs()[0].name == "z"
    z = enc.run(None, {"image": np.zeros((3, 3, 128, 128), np.float32)})[0]
    assert z.shape == (3, 8) and z.dtype == np.float32
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == manifest
    for key in ("version", "variant", "code_size", "pixels_per_unit", "encoder_input_range",
                "exemplar_short_side", "output_colour", "training"):
        assert key in manifest
    assert len(manifest["version"]) == 16


@pytest.mark.parametrize("scale", [10.0, 1e3, 1e6])
def test_onnx_matches_torch(exported, scale):
    model, session, _, _ = exported
    rng = np.random.default_rng(int(scale))
    points = (rng.random((4000, 3)) - 0.5) * 2 * scale
    z = rng.standard_normal((1, 8)).astype(np.float32)
    with torch.no_grad():
        ref = model.sample(torch.from_numpy(points)[None], torch.from_numpy(z), 11)[0].numpy()
    assert np.abs(run(session, points, z, 11) - ref).max() < 1e-4
    per_point = rng.standard_normal((4000, 8)).astype(np.float32)
    with torch.no_grad():
        ref = model.sample(torch.from_numpy(points)[:, None], torch.from_numpy(per_point), 11)[:, 0].numpy()
    assert np.abs(run(session, points, per_point, 11) - ref).max() < 1e-4


def test_colour_stage_matches_torch_shared_and_per_point(exported):
    # The graph's colour stage is model/colour.py's apply_colour, for one table shared by
    # all points and for one table per point (blends); the identity table changes nothing.
    model, session, _, _ = exported
    rng = np.random.default_rng(7)
    points = rng.random((3000, 3)) * 20
    z = rng.standard_normal((1, 8)).astype(np.float32)
    with torch.no_grad():
        raw = model.sample(torch.from_numpy(points)[None], torch.from_numpy(z), 3)
    assert np.abs(run(session, points, z, 3) - raw[0].numpy()).max() < 1e-5
    table = random_colour_tables(rng, 1)
    coloured = run(session, points, z, 3, table)
    ref = apply_colour(raw, torch.from_numpy(table))[0].numpy()
    assert np.abs(coloured - ref).max() < 1e-4  # steep random curves: summation order shows
    assert np.abs(coloured - raw[0].numpy()).mean() > 0.01  # the table did something
    tables = random_colour_tables(rng, len(points))
    per_point = run(session, points, np.repeat(z, len(points), axis=0), 3, tables)
    ref = apply_colour(raw[0][:, None], torch.from_numpy(tables))[:, 0].numpy()
    assert np.abs(per_point - ref).max() < 1e-4


@pytest.mark.parametrize("name", ["sampler.onnx", "sampler_tileable.onnx"])
def test_z_and_colour_rows_pair_freely(exported, name):
    # Contract 1: z [1|P] and colour [1|P] in any pairing give [P,3] and the shared form's
    # pixels (a fit exports its samplers with this code, so each fitted texture keeps it).
    _, _, _, out = exported
    session = ort.InferenceSession(str(out / name), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(9)
    n = 500
    feed = {"points": rng.random((n, 3)) * 6, "seed": np.asarray(2, np.int64)}
    if name != "sampler.onnx":
        feed["period"] = np.asarray(3.0)
    z, table = rng.standard_normal((1, 8)).astype(np.float32), random_colour_tables(rng, 1)
    shared = session.run(None, feed | {"z": z, "colour": table})[0]
    for z_rows, colour_rows in [(1, n), (n, 1), (n, n)]:
        rgb = session.run(None, feed | {"z": np.repeat(z, z_rows, axis=0),
                                        "colour": np.repeat(table, colour_rows, axis=0)})[0]
        assert rgb.shape == (n, 3) and np.array_equal(rgb, shared), (z_rows, colour_rows)


def test_bit_identical_across_runs_and_batch_splits(exported):
    _, session, _, _ = exported
    rng = np.random.default_rng(0)
    points = rng.standard_normal((3000, 3)) * 50
    z = rng.standard_normal((1, 8)).astype(np.float32)
    whole = run(session, points, z, 5)
    assert np.array_equal(whole, run(session, points, z, 5))
    parts = np.concatenate([run(session, points[a:b], z, 5) for a, b in [(0, 1), (1, 1000), (1000, 3000)]])
    assert np.array_equal(whole, parts)


def test_other_seed_gives_other_texture(exported):
    _, session, _, _ = exported
    rng = np.random.default_rng(1)
    points = rng.random((5000, 3)) * 4
    z = rng.standard_normal((1, 8)).astype(np.float32)
    a, b = run(session, points, z, 1), run(session, points, z, 2)
    assert np.abs(a - b).mean() > 0.2 * a.std()
    assert abs(a.mean() - b.mean()) < 0.5 * a.std() + 1e-3  # same texture statistics


def test_far_from_origin_has_the_same_statistics(exported):
    _, session, _, _ = exported
    rng = np.random.default_rng(2)
    local = rng.random((20000, 3)) * 8
    z = rng.standard_normal((1, 8)).astype(np.float32)
    near = run(session, local, z, 4)
    far = run(session, local + 1e7, z, 4)
    assert np.abs(near.mean(0) - far.mean(0)).max() < 0.1 * near.std() + 2e-3
    assert np.abs(near.std(0) / far.std(0) - 1).max() < 0.1
    assert not np.allclose(near, far)  # a different place, not a copy


def test_exported_sampler_matches_torch_far_from_the_origin(tmp_path):
    # The per-octave transforms scale lattice coordinates of millions of cells far out; in
    # float32 one rounding step between torch's and ONNX Runtime's GEMMs moved the finest
    # octaves by whole cells (the shipped space: 0.045 apart at 5,000 units, 0.4 at 1e6).
    # Computed in float64 from the code (Translator.forward), they agree everywhere.
    from model.export import export_sampler

    torch.manual_seed(7)
    model = TextureSpace(ModelConfig(variant="ours", nearest_input=False, smooth=True, isotropic_transforms=True))
    torch.nn.init.normal_(model.field.translator.to_transform.weight, std=0.3)  # scales far from 1
    export_sampler(model.field, tmp_path / "sampler.onnx")
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(8)
    z = rng.standard_normal((1, 8)).astype(np.float32)
    for offset in (0.0, 5e3, 1e6, -3e7):
        points = rng.random((3000, 3)) * 4 + offset
        with torch.no_grad():
            ref = model.field(torch.from_numpy(points)[None], torch.from_numpy(z), torch.tensor(4))[0].numpy()
        assert np.abs(run(session, points, z, 4) - ref).max() < 1e-5, offset


def test_exported_noise_matches_torch_past_2_32_cells(tmp_path):
    # ONNX Runtime 1.31 runs Cast(float64 -> int64) -> Cast(int64 -> uint32) as one direct
    # conversion that is wrong past 2**32: the graph's noise once differed from torch there
    # (tiles a few million world units out). Cells on both sides of the carry, both signs.
    from model.export import _export
    from model.noise import noise_features, octave_seeds

    class Noise(torch.nn.Module):
        def forward(self, lattice, seed):
            return noise_features(lattice, octave_seeds(seed.reshape([]), 4), smooth=True)[1]

    rng = np.random.default_rng(5)
    offsets = np.array([0.0, 2.0**32 - 50, 5e9, -5e9, 3e12, -(2.0**40)])[:, None, None, None]
    lattice = torch.from_numpy((rng.uniform(0, 100, (6, 400, 4, 3)) + offsets).reshape(1, -1, 4, 3))
    path = tmp_path / "noise.onnx"
    _export(Noise(), (lattice, torch.tensor(3)), path, ["lattice", "seed"], ["noise"], {"lattice": {1: "P"}})
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"lattice": lattice.numpy(), "seed": np.array(3, np.int64)})[0]
    with torch.no_grad():
        want = Noise()(lattice, torch.tensor(3)).numpy()
    assert np.abs(got - want).max() < 1e-5


@pytest.mark.parametrize("stretch", [8.0, 16.0])
def test_grain_model_is_fibres_along_its_axis_and_exports(tmp_path, stretch):
    # A y-grain solid changes slowly along world y and quickly across it, and the stretch
    # survives export (torch and ONNX Runtime agree).
    from model.export import export_sampler

    torch.manual_seed(5)
    model = TextureSpace(ModelConfig(variant="ours", grain="y", grain_stretch=stretch))
    export_sampler(model.field, tmp_path / "sampler.onnx")
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    steps = np.arange(512) / 256.0
    along = np.stack([np.full(512, 0.3), steps, np.full(512, 0.7)], axis=1)
    across = np.stack([steps, np.full(512, 0.3), np.full(512, 0.7)], axis=1)
    z = np.random.default_rng(2).standard_normal((1, 8)).astype(np.float32)
    rgb_along, rgb_across = run(session, along, z, 4), run(session, across, z, 4)
    variation = lambda rgb: np.abs(np.diff(rgb, axis=0)).mean()
    assert variation(rgb_along) * 3 < variation(rgb_across)
    with torch.no_grad():
        ref = model.sample(torch.from_numpy(along)[None], torch.from_numpy(z), 4)[0].numpy()
    assert np.abs(rgb_along - ref).max() < 1e-4


def test_isotropic_transforms_keep_the_volume_and_export(tmp_path):
    # With isotropic_transforms, each octave's learned transform becomes |det T|^(1/3) I:
    # no stretch direction (the cause of the diagonal lean of 2D tiles), same cell volume.
    from model.export import export_sampler

    torch.manual_seed(6)
    shipped = {"nearest_input": False, "smooth": True}  # (nearest-cell inputs jump at 1-ulp border shifts)
    free = TextureSpace(ModelConfig(variant="ours", **shipped))
    torch.nn.init.normal_(free.field.translator.to_transform.weight, std=0.3)  # a stretched, sheared T
    iso = TextureSpace(ModelConfig(variant="ours", isotropic_transforms=True, **shipped))
    iso.load_state_dict(free.state_dict())
    z = torch.randn(2, 8)
    with torch.no_grad():
        _, t_free, _ = free.field.translator(z)
        _, t_iso, _ = iso.field.translator(z)
    eye = torch.eye(3)
    scale = t_iso[..., 0, 0]
    assert torch.allclose(t_iso, scale[..., None, None] * eye)
    assert torch.allclose(scale ** 3, torch.linalg.det(t_free.double()).abs(), rtol=1e-4)
    assert not torch.allclose(t_free, t_free[..., :1, :1] * eye, atol=1e-2)  # the free one was anisotropic
    export_sampler(iso.field, tmp_path / "sampler.onnx")
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    points = np.random.default_rng(3).random((2000, 3)) * 8
    zz = z[:1].numpy()
    with torch.no_grad():
        ref = iso.sample(torch.from_numpy(points)[None], z[:1], 4)[0].numpy()
    # scales of 3-5 make the finest octave ~5x finer than an untrained model's: rounding
    # differences grow with it (2e-4 seen, 0.05 of an 8-bit level)
    assert np.abs(run(session, points, zz, 4) - ref).max() < 1e-3


def test_a_warped_field_leans_exports_and_tiles(tmp_path):
    # A fit's warp (ModelConfig.warp) stretches every feature along its lean: an untrained
    # field warped 4x along 30 degrees changes slowly along that direction and fast across
    # it; the sampler, its tileable sampler (rounded per octave to whole steps a period) and
    # torch agree, and the tileable one repeats exactly.
    from model.export import TILEABLE_SAMPLER, export_sampler, export_tileable_sampler
    from model.train import lean_warp

    torch.manual_seed(4)
    model = TextureSpace(ModelConfig(variant="ours", nearest_input=False, smooth=True, isotropic_transforms=True,
                                     warp=True))
    with torch.no_grad():
        model.field.warp.copy_(lean_warp(30.0, 4.0) - torch.eye(2, dtype=torch.float64))
    export_sampler(model.field, tmp_path / "sampler.onnx")
    export_tileable_sampler(model.field, tmp_path / TILEABLE_SAMPLER)
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    z = np.random.default_rng(2).standard_normal((1, 8)).astype(np.float32)
    steps = np.arange(2048)[:, None] / 1024.0
    line = lambda degrees: np.array([np.cos(np.radians(degrees)), np.sin(np.radians(degrees)), 0.0]) * steps + 0.3
    variation = lambda rgb: np.abs(np.diff(rgb, axis=0)).mean()
    along, across = run(session, line(30.0), z, 4), run(session, line(120.0), z, 4)
    assert variation(along) * 2.5 < variation(across)
    with torch.no_grad():
        ref = model.sample(torch.from_numpy(line(30.0))[None], torch.from_numpy(z), 4)[0].numpy()
    assert np.abs(along - ref).max() < 1e-4
    tileable = ort.InferenceSession(str(tmp_path / TILEABLE_SAMPLER), providers=["CPUExecutionProvider"])
    points = np.random.default_rng(3).random((3000, 3)) * 2
    feed = {"points": points, "z": z, "seed": np.asarray(4), "colour": identity_colour()[None].numpy(),
            "period": np.asarray(2.0)}
    rgb = tileable.run(None, feed)[0]
    for shift in ([2.0, 0, 0], [0, -6.0, 0], [4.0, 2.0, 0]):
        assert np.array_equal(tileable.run(None, feed | {"points": points + shift})[0], rgb), shift
    tiled_along = tileable.run(None, feed | {"points": line(30.0)})[0]
    tiled_across = tileable.run(None, feed | {"points": line(120.0)})[0]
    assert variation(tiled_along) * 2.5 < variation(tiled_across)  # the rounded warp still leans


def test_a_warp_scales_depth_by_its_mean_scale_in_the_photo_plane(tmp_path):
    # A warp maps the photo's plane (x, y); depth takes its mean scale (sqrt |det|), so a fit of
    # a photo that is the texture scaled by s is that solid scaled by s in every direction: the
    # warped field at p is the plain field at s p, along z too, in torch and in the sampler.
    # With z as it was, a fit's cuts through depth met features of another size
    # (docs/DECISIONS.md, "A lean's depth").
    from model.export import export_sampler

    cfg = dict(variant="ours", nearest_input=False, smooth=True, isotropic_transforms=True)
    torch.manual_seed(5)
    warped = TextureSpace(ModelConfig(**cfg, warp=True))
    plain = TextureSpace(ModelConfig(**cfg))
    plain.load_state_dict({k: v for k, v in warped.state_dict().items() if k != "field.warp"})
    scale = 0.6
    with torch.no_grad():
        warped.field.warp.copy_((scale - 1.0) * torch.eye(2, dtype=torch.float64))
    points = torch.from_numpy(np.random.default_rng(6).uniform(-3, 3, (1, 2000, 3)))
    z = torch.from_numpy(np.random.default_rng(7).standard_normal((1, 8)).astype(np.float32))
    with torch.no_grad():
        ours, reference = warped.sample(points, z, 4)[0].numpy(), plain.sample(points * scale, z, 4)[0].numpy()
    assert np.abs(ours - reference).max() < 1e-5
    export_sampler(warped.field, tmp_path / "sampler.onnx")
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    assert np.abs(run(session, points[0].numpy(), z.numpy(), 4) - reference).max() < 1e-4


def test_cell_shades_are_one_per_cell_export_and_tile(tmp_path):
    # ModelConfig.lattice_shade: every repeat cell (a brick, a tile) its own three hashed
    # values, the same over the whole cell, other ones in the next cell and for another seed;
    # the sampler and torch agree, and the tileable sampler still repeats exactly (the cells a
    # period apart are one cell) while neighbouring cells differ.
    from model.export import TILEABLE_SAMPLER, TileableSamplerGraph, export_sampler, export_tileable_sampler

    torch.manual_seed(5)
    cfg = ModelConfig(variant="ours", nearest_input=False, smooth=True, lattice=(0.125, 0.0, -0.054, 0.0417),
                      lattice_cell=(8, 4), lattice_shade=True)
    field = TextureSpace(cfg).field.eval()
    with torch.no_grad():
        field.decoder.from_phase.weight.normal_(std=0.5)
    rng = np.random.default_rng(6)
    points = torch.from_numpy(rng.random((1, 4000, 3)) * 2)
    harmonics = 4 * cfg.lattice_harmonics
    shades = field.lattice_phases(points, None, torch.tensor([11], dtype=torch.int32))[0, :, harmonics:harmonics + 3]
    cells = torch.floor(points[0, :, :2] @ field.lattice_inverse.t())
    _, index = torch.unique(cells, dim=0, return_inverse=True)
    per_cell = torch.zeros(int(index.max()) + 1, 3, dtype=shades.dtype).index_reduce_(0, index, shades, "amax",
                                                                                      include_self=False)
    assert torch.equal(per_cell[index], shades)  # one value per cell
    assert per_cell.shape[0] > 100 and per_cell.std(0).min() > 0.4  # uniform in [-1, 1]: std 0.58
    other = field.lattice_phases(points, None, torch.tensor([12], dtype=torch.int32))[0, :, harmonics:harmonics + 3]
    assert (other - shades).abs().mean() > 0.3

    export_sampler(field, tmp_path / "sampler.onnx")
    export_tileable_sampler(field, tmp_path / TILEABLE_SAMPLER)
    session = ort.InferenceSession(str(tmp_path / "sampler.onnx"), providers=["CPUExecutionProvider"])
    z = rng.standard_normal((1, 8)).astype(np.float32)
    with torch.no_grad():
        ref = field(points, torch.from_numpy(z), torch.tensor(4))[0].numpy()
    assert np.abs(run(session, points[0].numpy(), z, 4) - ref).max() < 1e-4
    tileable = ort.InferenceSession(str(tmp_path / TILEABLE_SAMPLER), providers=["CPUExecutionProvider"])
    colour = identity_colour()[None].numpy()
    feed = {"points": points[0].numpy(), "z": z, "seed": np.asarray(4), "colour": colour, "period": np.asarray(1.0)}
    rgb = tileable.run(None, feed)[0]
    for shift in ([1.0, 0, 0], [0, -3.0, 0], [5.0, 2.0, 0]):
        assert np.array_equal(tileable.run(None, feed | {"points": points[0].numpy() + shift})[0], rgb), shift
    with torch.no_grad():
        ref = TileableSamplerGraph(field)(*(torch.from_numpy(np.asarray(feed[k])) for k in
                                           ("points", "z", "seed", "colour", "period"))).numpy()
    assert np.abs(rgb - ref).max() < 1e-4
    # a whole cell along the first lattice axis away (not a period): another shade, another colour
    step = np.array([0.125, 0.0, 0.0])
    assert np.abs(tileable.run(None, feed | {"points": points[0].numpy() + step})[0] - rgb).mean() > 1e-3


def test_noise_hash_runs_in_uint32_without_casts(exported):
    # The 32-bit hash is the sampler's hottest part: its shifts must be plain uint32
    # BitShifts (no Cast pairs around them) and no tensor of the graph may stay int32.
    import onnx
    from onnx import TensorProto, shape_inference

    _, _, _, out = exported
    graph = shape_inference.infer_shapes(onnx.load(str(out / "sampler.onnx"))).graph
    types = {v.name: v.type.tensor_type.elem_type for v in list(graph.value_info) + list(graph.input)}
    types |= {t.name: t.data_type for t in graph.initializer}
    shifts = [n for n in graph.node if n.op_type == "BitShift"]
    assert len(shifts) >= 6  # three per seed mix32, two per corner hash
    assert all(types[n.input[0]] == TensorProto.UINT32 for n in shifts)
    consumers = {i: n for n in graph.node for i in n.input}
    assert {consumers[n.output[0]].op_type for n in shifts} == {"BitwiseXor"}  # no Cast back
    assert TensorProto.INT32 not in types.values()
    # Channel values are multiplied out of the hash, not masked: no BitwiseAnd (3x a Mul).
    assert not [n for n in graph.node if n.op_type == "BitwiseAnd"]


def test_tileable_sampler_repeats_exactly_and_matches_torch(exported):
    from model.export import TILEABLE_SAMPLER, TileableSamplerGraph

    model, _, manifest, out = exported
    assert manifest["tileable_sampler"] == TILEABLE_SAMPLER
    session = ort.InferenceSession(str(out / TILEABLE_SAMPLER), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["points", "z", "seed", "colour", "period"]
    rng = np.random.default_rng(5)
    z = rng.standard_normal((1, 8)).astype(np.float32)
    colour = identity_colour()[None].numpy()
    for period in (1.0, 4.0):
        points = np.concatenate([rng.random((3000, 2)) * period, rng.random((3000, 1))], axis=1)
        feed = {"points": points, "z": z, "seed": np.asarray(4), "colour": colour, "period": np.asarray(period)}
        rgb = session.run(None, feed)[0]
        for shift in ([period, 0, 0], [0, -3 * period, 0], [7 * period, 2 * period, 0]):
            moved = session.run(None, feed | {"points": points + shift})[0]
            assert np.array_equal(moved, rgb), shift
        not_a_period = session.run(None, feed | {"points": points + [period / 2, 0, 0]})[0]
        assert np.abs(not_a_period - rgb).mean() > 1e-3
        with torch.no_grad():
            ref = TileableSamplerGraph(model.field)(*(torch.from_numpy(np.asarray(feed[k])) for k in
                                                     ("points", "z", "seed", "colour", "period"))).numpy()
        assert np.abs(rgb - ref).max() < 1e-4


def test_tileable_image_has_no_seam(exported):
    # A 256^2 image of one period, tiled: the step across the wrap is like any other step.
    _, _, _, out = exported
    session = ort.InferenceSession(str(out / "sampler_tileable.onnx"), providers=["CPUExecutionProvider"])
    n, ppu = 256, 256.0
    g = (np.arange(n) + 0.5) / ppu
    y, x = np.meshgrid(g, g, indexing="ij")
    points = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
    z = np.random.default_rng(2).standard_normal((1, 8)).astype(np.float32)
    feed = {"points": points, "z": z, "seed": np.asarray(1), "colour": identity_colour()[None].numpy(),
            "period": np.asarray(n / ppu)}
    image = session.run(None, feed)[0].reshape(n, n, 3)
    columns = np.abs(np.diff(image, axis=1)).mean(axis=(0, 2))  # each interior vertical line
    rows = np.abs(np.diff(image, axis=0)).mean(axis=(1, 2))
    wrap_x = np.abs(image[:, 0] - image[:, -1]).mean()
    wrap_y = np.abs(image[0] - image[-1]).mean()
    assert columns.min() <= wrap_x <= columns.max() and rows.min() <= wrap_y <= rows.max()
    assert abs(wrap_x - columns.mean()) < 3 * columns.std() and abs(wrap_y - rows.mean()) < 3 * rows.std()


def test_a_grain_fields_tileable_image_keeps_its_stretch_and_repeats_exactly():
    """A 16x grain along x: the tileable 256-px image is as much longer along the grain as the
    infinite plane (quarter-turn octaves, none of a coarse octave's steps along the grain),
    and repeats exactly with its period."""
    from model.networks import ModelConfig, TextureSpace

    torch.manual_seed(0)
    field = TextureSpace(ModelConfig(grain="x", grain_stretch=16.0, isotropic_transforms=True, smooth=True,
                                     nearest_input=False)).field.eval()
    g = (np.arange(256) + 0.5) / 256.0
    y, x = np.meshgrid(g, g, indexing="ij")
    points = torch.from_numpy(np.stack([x, y, np.zeros_like(x)], -1).reshape(1, -1, 3))
    z, seed, period = torch.randn(1, 8), torch.tensor(3), torch.tensor(1.0, dtype=torch.float64)

    def stretch(image):  # gradients across the grain over those along it
        return np.abs(np.diff(image, axis=0)).mean() / np.abs(np.diff(image, axis=1)).mean()

    with torch.no_grad():
        plane = field(points, z, seed).reshape(256, 256, 3).numpy()
        tiled = field(points, z, seed, period=period).reshape(256, 256, 3).numpy()
        moved = field(points + torch.tensor([1.0, -2.0, 0.0], dtype=torch.float64), z, seed, period=period)
    assert stretch(plane) > 8 and 0.6 < stretch(tiled) / stretch(plane) < 1.6  # (with turns of c up to 17: 0.3)
    assert np.array_equal(moved.reshape(256, 256, 3).numpy(), tiled)


def test_a_manifest_names_training_paths_as_the_repository_sees_them() -> None:
    from model.export import REPO_ROOT, training_summary

    ckpt = {"mode": "space", "step": 3, "args": {"data": str(REPO_ROOT / "gpu" / "data"), "init": "/elsewhere/x.pt",
                                                "exemplar": None, "batch": 16}}
    args = training_summary(ckpt)["args"]
    assert args == {"data": "gpu/data", "init": "x.pt", "exemplar": None, "batch": 16}
    shipped = json.loads((REPO_ROOT / "model" / "weights" / "manifest.json").read_text())
    assert not any(str(v).startswith("/") for v in shipped["training"]["args"].values())


def test_style_vectors_are_apart_by_the_gram_loss(exported):
    """style.onnx: the squared distance of two images' style vectors is model.losses.gram_loss
    between them over STYLE_LAYERS (at any image size), weights stored in float16."""
    from model.export import STYLE_LAYERS
    from model.losses import gram_loss, gram_matrices
    from model.vgg import shared_vgg

    _, _, manifest, out = exported
    assert manifest["style_features"] == "style.onnx"
    assert (out / "style.onnx").stat().st_size < 6.5e6  # 2.9 M float16 weights; float32 would be 11.7 MB
    session = ort.InferenceSession(str(out / "style.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(1)
    for shape in ((2, 3, 128, 128), (2, 3, 96, 160)):
        images = rng.random(shape, dtype=np.float32)
        images[1] = images[1] ** 3  # darker, sparser: another style
        vectors = session.run(None, {"image": images})[0]
        features = shared_vgg(STYLE_LAYERS)(torch.from_numpy(images))
        with torch.no_grad():
            expected = gram_loss({k: v[:1] for k, v in features.items()},
                                 {k: g[1:] for k, g in gram_matrices(features).items()}, reduction="none")
        assert np.square(vectors[0] - vectors[1]).sum() == pytest.approx(float(expected[0]), rel=2e-3)
