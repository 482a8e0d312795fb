"""Hashed lattice value noise: the one noise function of texspace.

Training (torch autograd) and inference (the exported ``sampler.onnx``) run this same
code, so the two agree by construction. Every operation here is chosen to export to
plain ONNX and to mean the same thing in torch, numpy, ONNX Runtime and a GPU shader:

* Hashing is 32-bit integer arithmetic held in int32: additions and multiplications
  wrap modulo 2**32 (two's complement, as in torch, ONNX Runtime and GLSL ``uint``),
  and every right shift is logical (``_shr``; the exported graph runs the hash in
  uint32, model/export.py, where it is one ``BitShift``).
* Few bitwise operations: ONNX Runtime's bitwise kernels (Xor, And, BitShift) cost about
  3x its Add or Mul per element. A cell's hash is two xorshift-multiply rounds, and its
  three colour values are the top bits of the hash times three odd constants, read by
  a cast to float, not masked fields.
* Lattice coordinates are float64 until the cell index is taken, so a point at 1e7
  world units still lands in exactly the right cell at the finest octave.
* The lattice is infinite: a cell index is hashed as its low 32 bits plus a term for
  the bits above, so there is no period.

Layout of the result (``n_octaves`` octaves, 3 colour channels):

    noise_features(...) -> (nearest, interpolated), each float32 [..., n_octaves, 3]

``nearest`` is the value of the cell holding the point, ``interpolated`` the
(multi)linear blend of the 2**D cell centres around it (cell-centred lattice: the value
of cell k sits at k + 0.5). Cell values are uniform in [0, 1] (multiples of 2**-32
rounded to float32).
"""

from __future__ import annotations

import torch

def _int32(value: int) -> int:
    """A 32-bit pattern as the signed int32 number with the same bits."""
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value >= 1 << 31 else value


# The "lowbias32" xorshift-multiply mixer (Chris Wellons' hash prospector): two
# multiplies, three logical shifts; bias 0.17 on its avalanche measure.
_MIX_A = _int32(0x7FEB352D)
_MIX_B = _int32(0x846CA68B)
# Odd constants that spread a cell's coordinates (low 32 bits, and the bits above)
# before mixing.
_COORD_LO = tuple(_int32(c) for c in (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D))
_COORD_HI = tuple(_int32(c) for c in (0x27D4EB2F, 0x165667B1, 0x61C88647))
_SEED_MULT = _int32(0x68E31DA5)
_OCTAVE_MULT = _int32(0x2545F491)
# A cell's three colour values: the hash times each of these odd constants (mod 2**32),
# read as an unsigned number and scaled by 2**-32. The top bits of a product depend on
# every bit of the hash, so no final xorshift is needed before them.
_CHANNEL_MULTS = torch.tensor([1, _int32(0xA54FF53B), _int32(0x510E527F)], dtype=torch.int32)
_FIELD_SCALE = 2.0 ** -32
_TWO32 = 2.0 ** 32


class _LogicalShiftRight(torch.autograd.Function):
    """``h >> bits`` with zeros shifted in, on int32 (torch shifts signed ints arithmetically).

    The exporter writes one placeholder node, lowered by ``model/export.py`` to
    Cast(uint32) -> BitShift -> Cast(int32); in torch the sign-extended bits are masked.
    """

    @staticmethod
    def forward(ctx, h: torch.Tensor, bits: int) -> torch.Tensor:
        return torch.bitwise_and(torch.bitwise_right_shift(h, bits), (1 << (32 - bits)) - 1)

    @staticmethod
    def symbolic(g, h, bits: int):
        return g.op("texspace::ShiftRight", h, bits_i=bits).setType(h.type())


class _UnsignedToFloat(torch.autograd.Function):
    """An int32's bits read as an unsigned number, to float32 (rounded to nearest).

    Exported as a plain Cast to float: the graph holds the hash as uint32
    (``model/export.py``), so the cast reads it unsigned there, as here."""

    @staticmethod
    def forward(ctx, h: torch.Tensor) -> torch.Tensor:
        # The same bits viewed as uint32, then one conversion: 16x faster on the CPU than
        # widening to int64 and masking (6.3M values, one thread: 148 -> 9 ms), bit for bit
        # the same floats; it was 7% of a fit's step.
        if torch.jit.is_tracing():  # (the exporter writes the symbolic Cast below; its tracer cannot view dtypes)
            return torch.bitwise_and(h.to(torch.int64), 0xFFFFFFFF).to(torch.float32)
        return h.contiguous().view(torch.uint32).to(torch.float32)

    @staticmethod
    def symbolic(g, h):
        from torch.onnx import TensorProtoDataType

        return g.op("Cast", h, to_i=int(TensorProtoDataType.FLOAT))


def _shr(h: torch.Tensor, bits: int) -> torch.Tensor:
    return _LogicalShiftRight.apply(h, bits)


def _xorshift_multiply(h: torch.Tensor) -> torch.Tensor:
    """lowbias32's two xorshift-multiply rounds."""
    h = torch.bitwise_xor(h, _shr(h, 16)) * _MIX_A
    return torch.bitwise_xor(h, _shr(h, 15)) * _MIX_B


def mix32(h: torch.Tensor) -> torch.Tensor:
    """Avalanche a 32-bit value (lowbias32): int32 [...] -> int32 [...] (a bijection).

    For the per-request seeds; cell corners use the cheaper ``cell_mix``."""
    h = _xorshift_multiply(h)
    return torch.bitwise_xor(h, _shr(h, 16))


def cell_mix(h: torch.Tensor) -> torch.Tensor:
    """lowbias32 without its last xorshift: int32 [...] -> int32 [...].

    That last step folds the high bits into the low ones; ``channel_fields`` reads only
    the top bits of products of the result, so a cell's hash skips it (two of the
    eight bitwise ops a corner cost)."""
    return _xorshift_multiply(h)


def _split32(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer-valued float64 -> (low 32 bits, the bits above), both int32.

    Both halves are taken in float64 (exact for |c| < 2**53: c is an integer and the
    scale a power of two) and cast only once in [-2**31, 2**32). ONNX Runtime (1.31)
    runs the exported Cast(float64 -> int64) -> Cast(int64 -> uint32) as one direct
    conversion, wrong outside that range: a plain c.to(int64).to(int32) gave every cell
    past 2**32 the wrong low half in the graph, though not in torch.
    """
    high = torch.floor(c * (1.0 / _TWO32))
    lo = (c - high * _TWO32).to(torch.int64).to(torch.int32)  # in [0, 2**32)
    hi = high.to(torch.int64).to(torch.int32)  # |hi| < 2**31 for |c| < 2**63
    return lo, hi


def octave_seeds(seed: torch.Tensor, n_octaves: int) -> torch.Tensor:
    """One 32-bit seed per octave from the request seed.

    seed : int64 [] or [B]  ->  int32 [..., n_octaves]
    """
    seed = seed.to(torch.int64)
    lo = seed.to(torch.int32)
    hi = torch.div(seed, 1 << 32, rounding_mode="floor").to(torch.int32)  # a scalar: Div is fine
    base = mix32(torch.bitwise_xor(mix32(lo), hi * _SEED_MULT))
    # A constant (not arange) so the exported graph holds no Range op.
    octave = torch.tensor([_int32(k * _OCTAVE_MULT) for k in range(1, n_octaves + 1)],
                          dtype=torch.int32, device=seed.device)
    return mix32(torch.bitwise_xor(base.unsqueeze(-1), octave))


def _axis_terms(cells: torch.Tensor, first_axis: int = 0) -> torch.Tensor:
    """Each axis' share of the cell hash, for a cell and its upper neighbour.

    cells : float64 [D, ...] lower corner cell per axis (axis-major, integer-valued), of
            lattice axes ``first_axis`` .. ``first_axis + D - 1``
    returns int32 [D, 2, ...]: index [d, i] is the term of cell ``cells[d] + i``

    The hash of a cell is cell_mix of (seed + sum over axes of these terms), all mod 2**32,
    so a cell's 2**D corners need only 2 terms per axis, summed by broadcasting. The
    upper neighbour's term is the lower one + the axis constant, plus the high-half
    constant where the low half wraps (lo = -1, once every 2**32 cells).
    """
    dims = cells.shape[0]
    rest = [1] * (cells.dim() - 1)
    lo, hi = _split32(cells)
    axes = slice(first_axis, first_axis + dims)
    lo_mult = torch.tensor(_COORD_LO[axes], dtype=torch.int32, device=cells.device).reshape([dims] + rest)
    hi_mult = torch.tensor(_COORD_HI[axes], dtype=torch.int32, device=cells.device).reshape([dims] + rest)
    term = lo * lo_mult + hi * hi_mult  # [D, ...]
    wraps = lo == torch.tensor(-1, dtype=torch.int32, device=cells.device)  # (an int32 constant: no cast)
    upper = term + torch.where(wraps, lo_mult + hi_mult, lo_mult)
    return torch.stack([term, upper], dim=1)


def _cell_term(cells: torch.Tensor, axis: int) -> torch.Tensor:
    """One axis' share of the cell hash for cells anywhere: float64 (integer-valued) -> int32."""
    lo, hi = _split32(cells)
    return lo * _COORD_LO[axis] + hi * _COORD_HI[axis]


def wrap_cells(i: torch.Tensor, j: torch.Tensor, wrap: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cells (i, j) reduced to one representative per class of a periodic lattice.

    i, j : float64 (integer-valued), broadcastable
    wrap : float64 [2, 2, ...] integer basis vectors u = wrap[0], v = wrap[1] (x, y
           components) of the sublattice of cells that repeat, broadcastable to i
    Cells that differ by a u, v combination get the same (i, j) back, so their hashes,
    and the noise, repeat with those periods. Exact: every number here is an integer
    below 2**53 but the two divisions, which floor the same for an exact quotient.
    """
    (ux, uy), (vx, vy) = wrap[0], wrap[1]
    det = ux * vy - uy * vx
    alpha = torch.floor((vy * i - vx * j) / det)
    beta = torch.floor((ux * j - uy * i) / det)
    return i - alpha * ux - beta * vx, j - alpha * uy - beta * vy


def cell_shade(i: torch.Tensor, j: torch.Tensor, seed: torch.Tensor, wrap: torch.Tensor | None = None) -> torch.Tensor:
    """Three uniform values in [0, 1] for each cell (i, j) of a 2D lattice, the same at every
    point of the cell: float64 (integer-valued) i, j [...], int32 seed broadcastable to them
    -> float32 [..., 3]. The hash is the one a noise octave gives its cell (i, j, 0), so a
    shader reproduces it with the noise's own functions. ``wrap`` (``wrap_cells``): the cells
    repeat with those integer periods (tileable synthesis)."""
    if wrap is not None:
        i, j = wrap_cells(i, j, wrap)
    return channel_values(cell_mix(seed + _cell_term(i, 0) + _cell_term(j, 1)))


def _corner_hashes_major(cells: torch.Tensor, seeds: torch.Tensor, wrap: torch.Tensor | None = None) -> torch.Tensor:
    """Corner-major form of ``corner_hashes``: float64 [D, ...] -> int32 [2, 2(, 2), ...].

    Corner axes lead and the points' axes trail, so every broadcast in the sum below
    (and in the blends of ``noise_features``) repeats long contiguous rows: the fast
    path of ONNX Runtime's elementwise kernels (a trailing size-2 or size-3 axis made
    the same ops 2-4x slower). With ``wrap`` (see ``wrap_cells``) the lattice repeats in
    its first two axes; each of the 4 corners in that plane is then wrapped on its own.
    """
    dims = cells.shape[0]
    if wrap is not None:
        rest = [1] * (cells.dim() - 1)
        step = torch.tensor([0.0, 1.0], dtype=cells.dtype, device=cells.device)
        i = cells[0] + step.reshape([2, 1] + rest)  # [2, 1, ...]
        j = cells[1] + step.reshape([1, 2] + rest)  # [1, 2, ...]
        i, j = wrap_cells(i, j, wrap)
        h = seeds + _cell_term(i, 0) + _cell_term(j, 1)  # [2, 2, ...]
        if dims == 3:
            h = h.unsqueeze(2) + _axis_terms(cells[2:], first_axis=2)[0]  # + [2, ...]: third corner axis
        return cell_mix(h)
    terms = _axis_terms(cells)  # [D, 2, ...]
    h = seeds
    for d in range(dims):
        t = terms[d]  # [2, ...] along corner axis d
        for _ in range(dims - 1 - d):
            t = t.unsqueeze(1)
        for _ in range(d):
            t = t.unsqueeze(0)
        h = h + t
    return cell_mix(h)


def corner_hashes(base: torch.Tensor, seeds: torch.Tensor) -> torch.Tensor:
    """32-bit hashes of the 2**D cells around each lattice point.

    base  : integer-valued [..., D]  the lower corner cell (any integer or float dtype)
    seeds : int32 broadcastable to base[..., 0]
    returns int32 [..., 2, 2(, 2)]: index [..., i, j(, k)] is cell base + (i, j(, k))
    """
    dims = base.shape[-1]
    h = _corner_hashes_major(base.to(torch.float64).movedim(base.dim() - 1, 0), seeds)
    for _ in range(dims):
        h = h.movedim(0, h.dim() - 1)
    return h


def channel_fields(h: torch.Tensor, axis: int = -1) -> torch.Tensor:
    """A cell hash's three colour values, unscaled: int32 [...] -> float32 in [0, 2**32]
    with a new channel axis of size 3 at ``axis`` (last by default).

    Channel c is the hash times ``_CHANNEL_MULTS[c]`` (mod 2**32) read unsigned. One
    Mul and one Cast per element in the graph, where masking 10-bit fields out of the
    hash took a BitwiseAnd (three times the cost). The blends below are linear, so they
    run on these unscaled values and one multiply by ``_FIELD_SCALE`` follows.
    """
    h = h.unsqueeze(axis)
    shape = [1] * h.dim()
    shape[axis] = 3
    return _UnsignedToFloat.apply(h * _CHANNEL_MULTS.to(h.device).reshape(shape))


def channel_values(h: torch.Tensor) -> torch.Tensor:
    """Three uniform values in [0, 1] from one cell hash: int32 [...] -> float32 [..., 3]."""
    return channel_fields(h) * _FIELD_SCALE


def _blend(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Multilinear blend, corner axes leading.

    values  : [2, 2(, 2), C, ...]  corner values
    weights : [D, ...]             interpolation parameter per axis in [0, 1]
    returns [C, ...]
    """
    for d in range(weights.shape[0]):
        v0, v1 = values.unbind(0)  # one Split in the graph, not two Gathers
        values = v0 + weights[d] * (v1 - v0)
    return values


def _pick(values: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """The corner each axis' flag picks: values [2, 2(, 2), C, ...], upper bool [D, ...] -> [C, ...]."""
    for d in range(upper.shape[0]):
        v0, v1 = values.unbind(0)
        values = torch.where(upper[d], v1, v0)
    return values


def noise_features(
    lattice_points: torch.Tensor,
    seeds: torch.Tensor,
    smooth: bool = False,
    wrap: torch.Tensor | None = None,
    nearest: bool = True,
) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Value noise at points already mapped into each octave's lattice.

    lattice_points : float64 [..., K, D]  position of each point in octave k's lattice
                     (transform and frequency already applied), K octaves
    seeds          : int32 broadcastable to [..., K] (from ``octave_seeds``)
    smooth         : apply smoothstep to the interpolation weights (C1 continuous)
    wrap           : float64 [2, 2, ..., K] or None: make the lattice periodic in its first
                     two axes with these integer basis vectors per octave (``wrap_cells``)
    nearest        : False: skip the nearest cell's value (None in its place); a decoder
                     without the nearest-cell input would discard it, and picking it costs
                     as much as hashing the corners (3D, 32k points x 8 octaves: 15 vs 14 ms)
    returns (nearest, interpolated), float32 [..., K, 3] each
    """
    # Axis-major inside (see _corner_hashes_major); one transpose in, one per output out.
    # Cell-centred lattice: value k sits at k + 0.5, so interpolate from q = p - 0.5.
    q = lattice_points.movedim(lattice_points.dim() - 1, 0) - 0.5  # [D, ..., K] (ONNX: no negative perm)
    base = torch.floor(q)
    frac = (q - base).to(torch.float32)  # keeps the gradient w.r.t. transforms
    # Unscaled fields: both blends below are linear with weights summing to 1, so the
    # scale is applied once after them.
    dims = q.shape[0]
    fields = channel_fields(_corner_hashes_major(base, seeds, wrap), axis=dims)  # [2,2(,2), 3, ..., K]

    weights = frac * frac * (3.0 - 2.0 * frac) if smooth else frac
    interpolated = _blend(fields, weights) * _FIELD_SCALE  # [3, ..., K]
    last = interpolated.dim() - 1
    if not nearest:
        return None, interpolated.movedim(0, last)
    # The nearest cell centre is the corner each rounded fraction picks.
    picked = _pick(fields, frac >= 0.5) * _FIELD_SCALE
    return picked.movedim(0, last), interpolated.movedim(0, last)
