"""Hashed lattice value noise: the one noise function of texspace.

Training (torch autograd) and inference (the exported ``sampler.onnx``) run this same
code, so the two agree by construction. Every operation here is chosen to export to
plain ONNX and to mean the same thing in torch, numpy and ONNX Runtime:

* Integer hashing keeps every value a non-negative 32-bit number held in int64.
  ``& 0xFFFFFFFF`` masks, every multiplier is below 2**31 so no product overflows
  int64, and right shifts export as Cast(uint64) -> BitShift -> Cast(int64) (ONNX
  ``BitShift`` rejects int64; see ``_shr``).
* Lattice coordinates are float64 until the cell index is taken, so a point at 1e7
  world units still lands in exactly the right cell at the finest octave.
* The lattice is infinite: the cell index is hashed in two 32-bit halves, so there
  is no period.

Layout of the result (``n_octaves`` octaves, 3 colour channels):

    noise_features(...) -> (nearest, interpolated), each float32 [..., n_octaves, 3]

``nearest`` is the value of the cell holding the point, ``interpolated`` the
(multi)linear blend of the 2**D cell centres around it (cell-centred lattice: the value
of cell k sits at k + 0.5). Both are uniform in [0, 1) per cell.
"""

from __future__ import annotations

import torch

MASK32 = 0xFFFFFFFF
# Multipliers of the 32-bit mixer (below 2**31; from the "lowbias32" family of
# xorshift-multiply mixers, retuned to fit int64 without overflow).
_MIX_A = 0x7FEB352D
_MIX_B = 0x2C1B3C6D
# Odd constants that spread the lattice coordinates before mixing.
_COORD_LO = (0x5BD1E995, 0x27D4EB2F, 0x165667B1)
_COORD_HI = (0x3C6EF373, 0x1B873593, 0x61C88647)
_SEED_MULT = 0x68E31DA5
_OCTAVE_MULT = 0x2545F491
# Three colour channels share one 32-bit hash: 10 bits each.
_CHANNEL_BITS = 10
_CHANNEL_LEVELS = 1 << _CHANNEL_BITS
_CHANNEL_MASKS = torch.tensor([(_CHANNEL_LEVELS - 1) << (_CHANNEL_BITS * c) for c in range(3)], dtype=torch.int64)
_CHANNEL_SCALES = torch.tensor([2.0 ** -(_CHANNEL_BITS * (c + 1)) for c in range(3)], dtype=torch.float32)
_HALF_BIN = 0.5 / _CHANNEL_LEVELS  # bin centres: added after interpolation (weights sum to 1)


def _shr(h: torch.Tensor, bits: int) -> torch.Tensor:
    """Right shift of a non-negative int64.

    ONNX ``BitShift`` rejects int64, so ``model/export.py`` exports this op as
    Cast(uint64) -> BitShift -> Cast(int64): the same number for every non-negative
    value, and 2.7x cheaper in onnxruntime than the integer Div it replaced (bench/).
    """
    return torch.bitwise_right_shift(h, bits)


def mix32(h: torch.Tensor) -> torch.Tensor:
    """Avalanche a 32-bit value held in int64 (values stay in [0, 2**32))."""
    h = torch.bitwise_xor(h, _shr(h, 16))
    h = torch.bitwise_and(h * _MIX_A, MASK32)
    h = torch.bitwise_xor(h, _shr(h, 15))
    h = torch.bitwise_and(h * _MIX_B, MASK32)
    h = torch.bitwise_xor(h, _shr(h, 16))
    return h


def _split32(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed int64 -> (low 32 bits, high 32 bits), both as non-negative int64."""
    lo = torch.bitwise_and(c, MASK32)
    # torch shifts a negative int64 arithmetically, the export (uint64 BitShift)
    # logically: the two differ only in the top 32 bits of the result, which the mask
    # drops. Same value as the (c - lo) / 2**32 it replaces, without an integer Div.
    hi = torch.bitwise_and(torch.bitwise_right_shift(c, 32), MASK32)
    return lo, hi


def octave_seeds(seed: torch.Tensor, n_octaves: int) -> torch.Tensor:
    """One 32-bit seed per octave from the request seed.

    seed : int64 [] or [B]  ->  int64 [..., n_octaves]
    """
    lo, hi = _split32(seed.to(torch.int64))
    base = mix32(torch.bitwise_xor(mix32(lo), torch.bitwise_and(hi * _SEED_MULT, MASK32)))
    # A constant (not arange) so the exported graph holds no Range op.
    octave = torch.tensor(list(range(1, n_octaves + 1)), dtype=torch.int64, device=seed.device)
    return mix32(torch.bitwise_xor(base.unsqueeze(-1), torch.bitwise_and(octave * _OCTAVE_MULT, MASK32)))


def _axis_terms(cells: torch.Tensor, dims: int) -> torch.Tensor:
    """Each axis' share of the cell hash, for a cell and its upper neighbour.

    cells : int64 [D, ...] lower corner cell per axis (axis-major)
    returns int64 [D, 2, ...]: index [d, i] is the term of cell ``cells[d] + i``

    The hash of a cell is mix32 of (seed + sum over axes of these terms) mod 2**32, so a
    cell's 2**D corners need only 2 terms per axis, summed by broadcasting.
    """
    rest = [1] * (cells.dim() - 1)
    pair = torch.tensor([0, 1], dtype=torch.int64, device=cells.device).reshape([1, 2] + rest)
    lo, hi = _split32(cells.unsqueeze(1) + pair)
    lo_mult = torch.tensor(_COORD_LO[:dims], dtype=torch.int64, device=cells.device).reshape([dims, 1] + rest)
    hi_mult = torch.tensor(_COORD_HI[:dims], dtype=torch.int64, device=cells.device).reshape([dims, 1] + rest)
    return torch.bitwise_and(lo * lo_mult, MASK32) + torch.bitwise_and(hi * hi_mult, MASK32)


def _corner_hashes_major(cells: torch.Tensor, seeds: torch.Tensor) -> torch.Tensor:
    """Corner-major form of ``corner_hashes``: int64 [D, ...] -> int64 [2, 2(, 2), ...].

    Corner axes lead and the points' axes trail, so every broadcast in the sum below
    (and in the blends of ``noise_features``) repeats long contiguous rows: the fast
    path of ONNX Runtime's elementwise kernels (a trailing size-2 or size-3 axis made
    the same ops 2-4x slower).
    """
    dims = cells.shape[0]
    terms = _axis_terms(cells, dims)  # [D, 2, ...]
    h = seeds
    for d in range(dims):
        t = terms[d]  # [2, ...] along corner axis d
        for _ in range(dims - 1 - d):
            t = t.unsqueeze(1)
        for _ in range(d):
            t = t.unsqueeze(0)
        h = h + t
    # One mixing round suffices: neighbour-cell correlation measured below 0.002.
    return mix32(torch.bitwise_and(h, MASK32))


def corner_hashes(base: torch.Tensor, seeds: torch.Tensor) -> torch.Tensor:
    """32-bit hashes of the 2**D cells around each lattice point.

    base  : int64 [..., D]  the lower corner cell
    seeds : int64 broadcastable to base[..., 0]
    returns int64 [..., 2, 2(, 2)]: index [..., i, j(, k)] is cell base + (i, j(, k))
    """
    dims = base.shape[-1]
    h = _corner_hashes_major(base.movedim(base.dim() - 1, 0), seeds)
    for _ in range(dims):
        h = h.movedim(0, h.dim() - 1)
    return h


def channel_levels(h: torch.Tensor, axis: int = -1) -> torch.Tensor:
    """The three 10-bit fields of a 32-bit hash as level / 1024: int64 [...] -> float32,
    with a new channel axis of size 3 inserted at ``axis`` (last by default).

    Masked in place and scaled by a power of two instead of shifted down: a field
    ``level << 10c`` has at most 10 significant bits, so the float32 cast and the scaling
    are exact, and the graph needs no integer division.
    """
    h = h.unsqueeze(axis)
    shape = [1] * h.dim()
    shape[axis] = 3
    fields = torch.bitwise_and(h, _CHANNEL_MASKS.to(h.device).reshape(shape))
    return fields.to(torch.float32) * _CHANNEL_SCALES.to(h.device).reshape(shape)


def channel_values(h: torch.Tensor) -> torch.Tensor:
    """Three uniform values in (0, 1) from one 32-bit hash: int64 [...] -> float32 [..., 3].

    10 bits per channel; values are the centres of 1024 equal bins, so the mean is
    exactly 0.5 and the variance (1 - 1024**-2) / 12.
    """
    return channel_levels(h) + _HALF_BIN


def _blend(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Multilinear blend, corner axes leading.

    values  : [2, 2(, 2), C, ...]  corner values
    weights : [D, ...]             interpolation parameter per axis in [0, 1]
    returns [C, ...]
    """
    for d in range(weights.shape[0]):
        v0, v1 = values[0], values[1]
        values = v0 + weights[d] * (v1 - v0)
    return values


def _pick(values: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """The corner each axis' flag picks: values [2, 2(, 2), C, ...], upper bool [D, ...] -> [C, ...]."""
    for d in range(upper.shape[0]):
        values = torch.where(upper[d], values[1], values[0])
    return values


def noise_features(
    lattice_points: torch.Tensor,
    seeds: torch.Tensor,
    smooth: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Value noise at points already mapped into each octave's lattice.

    lattice_points : float64 [..., K, D]  position of each point in octave k's lattice
                     (transform and frequency already applied), K octaves
    seeds          : int64 broadcastable to [..., K] (from ``octave_seeds``)
    smooth         : apply smoothstep to the interpolation weights (C1 continuous)
    returns (nearest, interpolated), float32 [..., K, 3] each
    """
    # Axis-major inside (see _corner_hashes_major); one transpose in, one per output out.
    # Cell-centred lattice: value k sits at k + 0.5, so interpolate from q = p - 0.5.
    q = lattice_points.movedim(lattice_points.dim() - 1, 0) - 0.5  # [D, ..., K] (ONNX: no negative perm)
    base = torch.floor(q)
    frac = (q - base).to(torch.float32)  # keeps the gradient w.r.t. transforms
    # Levels without the half-bin offset: both blends below have weights summing to 1,
    # so the offset is added once per octave instead of once per corner.
    dims = q.shape[0]
    levels = channel_levels(_corner_hashes_major(base.to(torch.int64), seeds), axis=dims)  # [2,2(,2), 3, ..., K]

    weights = frac * frac * (3.0 - 2.0 * frac) if smooth else frac
    interpolated = _blend(levels, weights) + _HALF_BIN  # [3, ..., K]
    # The nearest cell centre is the corner each rounded fraction picks.
    nearest = _pick(levels, frac >= 0.5) + _HALF_BIN
    last = interpolated.dim() - 1
    return nearest.movedim(0, last), interpolated.movedim(0, last)
