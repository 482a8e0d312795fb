"""The noise function: statistics, determinism, infinity (tiles far out look like tiles at 0)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from model.noise import channel_values, corner_hashes, noise_features, octave_seeds  # noqa: E402


def cell_grid(n=256, z_values=(0, 1, -7)):
    g = torch.arange(-n // 2, n // 2, dtype=torch.int64)
    x, y, z = torch.meshgrid(g, g, torch.tensor(z_values), indexing="ij")
    return torch.stack([x, y, z], dim=-1)


def values_at(cells, seed=0):
    """Channel values of individual cells (the [0,0,0] corner of each)."""
    seeds = octave_seeds(torch.tensor(seed), 1)[0]
    return channel_values(corner_hashes(cells, seeds)[..., 0, 0, 0]).numpy()


def corr(a, b):
    return abs(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_cell_values_are_uniform_with_the_right_moments():
    v = values_at(cell_grid())
    assert abs(v.mean() - 0.5) < 0.01
    assert abs(v.var() - 1 / 12) < 0.005
    assert v.min() >= 0 and v.max() <= 1
    for c in range(3):  # each channel fills [0, 1] evenly: ten equal bins hold 10% each
        counts = np.histogram(v[..., c], bins=10, range=(0, 1))[0] / v[..., c].size
        assert np.abs(counts - 0.1).max() < 0.01
    assert len(np.unique(v)) > 100_000  # continuous values, not a few levels


def _reference_cell_values(cells: np.ndarray, seed: int) -> np.ndarray:
    """The documented hash written again in numpy uint32: seed lowbias32 chain, cell
    terms, two xorshift-multiply rounds, three odd multipliers, top bits to [0, 1]."""
    u = np.uint32

    def shr(h, b):
        return h >> u(b)

    def lowbias32(h):
        h = (h ^ shr(h, 16)) * u(0x7FEB352D)
        h = (h ^ shr(h, 15)) * u(0x846CA68B)
        return h ^ shr(h, 16)

    with np.errstate(over="ignore"):
        base = lowbias32(lowbias32(u(seed)) ^ (u(0) * u(0x68E31DA5)))
        octave_seed = lowbias32(base ^ u(0x2545F491))  # octave 1 of 1
        lo = cells.astype(np.int64).astype(np.uint32)
        hi = np.floor(cells / 2.0**32).astype(np.int64).astype(np.uint32)
        mult_lo = np.array([0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D], u)
        mult_hi = np.array([0x27D4EB2F, 0x165667B1, 0x61C88647], u)
        h = octave_seed + (lo * mult_lo + hi * mult_hi).sum(axis=-1, dtype=u)
        h = (h ^ shr(h, 16)) * u(0x7FEB352D)
        h = (h ^ shr(h, 15)) * u(0x846CA68B)
        fields = h[..., None] * np.array([1, 0xA54FF53B, 0x510E527F], u)
    return fields.astype(np.float32) * np.float32(2.0**-32)


def test_hash_matches_an_independent_uint32_reference():
    # What the shader emitter (worker/shader.py) and any other port must reproduce.
    cells = cell_grid(64).reshape(-1, 3)
    cells = torch.cat([cells, cells + 2**32 - 5, cells - 10**9])
    got = values_at(cells, seed=7)
    assert np.array_equal(got, _reference_cell_values(cells.numpy(), 7))


def test_neighbour_cells_and_channels_are_uncorrelated():
    v = values_at(cell_grid())
    assert corr(v[1:], v[:-1]) < 0.02  # x neighbours
    assert corr(v[:, 1:], v[:, :-1]) < 0.02  # y neighbours
    assert corr(v[:, :, 0], v[:, :, 1]) < 0.02  # z neighbours
    assert corr(v[1:, 1:], v[:-1, :-1]) < 0.02  # diagonal
    assert corr(v[..., 0], v[..., 1]) < 0.02  # colour channels
    assert corr(v[..., 1], v[..., 2]) < 0.02
    assert corr(v[..., 0], v[..., 2]) < 0.02


def test_far_cells_have_the_same_statistics_and_no_period():
    near = values_at(cell_grid())
    for offset in (10**7, -(10**7) * 128, 2**32, 2**40):
        far = values_at(cell_grid() + offset)
        assert abs(far.mean() - 0.5) < 0.01 and abs(far.var() - 1 / 12) < 0.005
        assert corr(far, near) < 0.02  # not a copy of the origin: no 2**32 period
    shifted = values_at(cell_grid() + torch.tensor([2**32, 0, 0]))
    assert not np.allclose(shifted, near)


def test_seeds_give_different_noise():
    a, b = values_at(cell_grid(), seed=1), values_at(cell_grid(), seed=2)
    assert corr(a, b) < 0.02
    assert np.array_equal(a, values_at(cell_grid(), seed=1))


def test_interpolation_is_continuous_and_nearest_is_a_cell_value():
    x = torch.linspace(0.0, 4.0, 4001, dtype=torch.float64)
    pts = torch.stack([x, torch.full_like(x, 0.3), torch.full_like(x, 0.7)], -1)[:, None, :]  # [P,1,3]
    seeds = octave_seeds(torch.tensor(3), 1)
    nearest, interp = noise_features(pts, seeds)
    steps = interp[1:, 0] - interp[:-1, 0]
    assert steps.abs().max() < 0.01  # lattice step 1, sample step 0.001: no jumps
    # nearest is piecewise constant: it changes only at cell borders (integers)
    changes = (nearest[1:, 0] != nearest[:-1, 0]).any(-1).nonzero().flatten()
    borders = x[changes + 1]
    assert torch.allclose(borders, borders.round(), atol=1e-3)
    # at a cell centre the interpolated value equals the cell's own value
    centre = torch.tensor([[[2.5, 0.5, 0.5]]], dtype=torch.float64)
    n, i = noise_features(centre, seeds)
    assert torch.allclose(n, i, atol=1e-6)


def test_without_nearest_the_blend_is_the_same():
    # A decoder without the nearest-cell input asks noise_features to skip it: the
    # interpolated values must not change with that choice (the sampler's noise would).
    pts = torch.rand(64, 4, 3, dtype=torch.float64) * 100.0
    seeds = octave_seeds(torch.tensor(5), 4)
    nearest, interp = noise_features(pts, seeds, smooth=True)
    skipped, same = noise_features(pts, seeds, smooth=True, nearest=False)
    assert skipped is None and nearest is not None
    assert torch.equal(interp, same)


def test_interpolation_is_continuous_across_the_32_bit_carry():
    # Cell -1 -> 0 and 2**32 - 1 -> 2**32 change the high half of the cell index: the
    # upper corner's hash must carry it (else the noise jumps there).
    seeds = octave_seeds(torch.tensor(3), 1)
    for border in (0.0, 2.0**32, -(2.0**32)):
        x = border + torch.linspace(-1.0, 1.0, 2001, dtype=torch.float64)
        pts = torch.stack([x, torch.full_like(x, 0.3), torch.full_like(x, 0.7)], -1)[:, None, :]
        _, interp = noise_features(pts, seeds)
        assert (interp[1:, 0] - interp[:-1, 0]).abs().max() < 0.01, border


def test_wrapped_lattice_repeats_with_its_basis():
    from model.noise import wrap_cells

    wrap = torch.tensor([[3.0, 4.0], [-8.0, 6.0]], dtype=torch.float64)  # u = 1 (3, 4), v = 2 (-4, 3)
    i, j = torch.meshgrid(torch.arange(-20.0, 20.0, dtype=torch.float64),
                          torch.arange(-20.0, 20.0, dtype=torch.float64), indexing="ij")
    ri, rj = wrap_cells(i, j, wrap[..., None, None])
    for a, b in ((1, 0), (0, 1), (-2, 3)):
        si, sj = wrap_cells(i + a * 3 - b * 8, j + a * 4 + b * 6, wrap[..., None, None])
        assert torch.equal(si, ri) and torch.equal(sj, rj)
    # one representative per class: |det| = 50 classes
    assert len(set(zip(ri.flatten().tolist(), rj.flatten().tolist()))) == 50


def test_decoder_row_path_equals_the_batched_path():
    # The exported sampler evaluates the decoder as one GEMM per layer over rows (one
    # code, or one point per code); training batches many codes of many points.
    from model.networks import Decoder

    torch.manual_seed(0)
    decoder = Decoder(24, 0, 64, 32, 3)
    noise, code = torch.randn(3, 50, 24), torch.randn(3, 64)
    batched = decoder(noise, None, code)
    for b in range(3):
        assert torch.allclose(decoder(noise[b:b + 1], None, code[b:b + 1])[0], batched[b], atol=1e-5)
        assert torch.allclose(decoder(noise[b][:, None], None, code[b].expand(50, 64))[:, 0], batched[b], atol=1e-5)


def test_unsigned_floats_of_hashes_match_the_masked_int64_reading():
    from model.noise import _UnsignedToFloat

    h = torch.tensor([0, 1, -1, -(2**31), 2**31 - 1, 123456789, -987654321], dtype=torch.int32)
    expected = torch.bitwise_and(h.to(torch.int64), 0xFFFFFFFF).to(torch.float32)
    assert torch.equal(_UnsignedToFloat.apply(h), expected)
    assert torch.equal(_UnsignedToFloat.apply(h[::2]), expected[::2])  # a strided view too
