"""Per-texture colouring: the last stage of the sampler (docs/ARCHITECTURE.md, Contract 1, ``colour``).

The decoder's raw output carries the texture's *structure*; its colours come from the
texture's own colour table, computed from the photo when it is encoded
(``worker/colour_match.py``) and applied here, inside ``sampler.onnx``:

    raw rgb --(.)^1/4--> c [3] --A (3x3)--> u [3] --curve per channel--> d [3] --B (3x3)--> (.)^4 --> rgb

* The statistics live in compressed colour, ``(rgb + FLOOR) ** (1/4)``, a stand-in for
  log colour: a photo's colour is albedo times shading, and in a log-like space the two
  separate, so chroma does not grow in the shadows. (Matched in linear RGB, the chroma
  spread of gravel and granite tiles came out 1.5-1.9x the photo's in CIELAB; in log or
  fourth-root colour 0.96-1.07x.) The fourth root is two square roots: unlike Log and
  Exp, whose vectorised kernels round differently from their scalar tails, square roots
  and products are exact IEEE operations, so a point's colour does not depend on how
  the points were split into batches.
* ``B`` holds the photo's principal axes in that space (orthonormal columns), ``d`` is
  a colour in that decorrelated basis.
* ``A`` projects the raw output on the same axes and whitens it there.
* Each channel's curve maps the distribution of ``u`` (over many points and seeds of this
  texture's own raw synthesis) onto the photo's distribution of ``d``: the photo's
  quantile function after the raw cumulative distribution, sampled at ``knots`` evenly
  spaced values of ``u`` from ``start`` in steps of ``step``, constant beyond.

So every channel of ``d`` has the photo's histogram by construction (histogram-preserving
synthesis, after Heitz and Neyret 2018), whatever colours the encoder got wrong. The curves
are increasing, so dark stays dark and structure is untouched. The table is a flat vector
of ``colour_size(knots)`` float32 numbers: ``A`` (9, row-major), ``start`` (3), ``step``
(3), the curves' values (3 x knots, channel-major), ``B`` (9, row-major). A linear blend
of two tables is a valid table (each knot moves linearly, curves stay increasing), so
interpolation fields blend colour per point too.
"""

from __future__ import annotations

import torch

# The compressed colour's FLOOR, and the moment transfer's ridge (a share RIDGE of each
# covariance's mean variance, at least RIDGE_FLOOR), are the serving colour table's own: the
# transfer training applies is exactly the table the service stores (tests/model/test_colour.py).
from worker.colour_match import FLOOR, RIDGE, RIDGE_FLOOR

KNOTS = 64  # samples of each channel's curve
_MIN_STEP = 1e-12  # a grid step used as a divisor (zero only in hand-made tables)


def colour_size(knots: int = KNOTS) -> int:
    """Length of a colour table: A (9) + start (3) + step (3) + values (3 x knots) + B (9)."""
    return 24 + 3 * knots


def identity_colour(knots: int = KNOTS) -> torch.Tensor:
    """The table that leaves colours in [0, 1] unchanged: float32 [colour_size(knots)]."""
    eye = torch.eye(3).flatten()
    low, high = FLOOR**0.25, (1.0 + FLOOR) ** 0.25
    ramp = torch.linspace(low, high, knots).repeat(3)
    grid = torch.tensor([low] * 3 + [(high - low) / (knots - 1)] * 3)
    return torch.cat([eye, grid, ramp, eye])


def compress(linear: torch.Tensor) -> torch.Tensor:
    """Linear colour in [0, 1] -> compressed colour (linear + FLOOR) ** (1/4), as two square roots."""
    return torch.sqrt(torch.sqrt(linear.clamp(0.0, 1.0) + FLOOR))


def expand(compressed: torch.Tensor) -> torch.Tensor:
    """Compressed colour -> linear colour clamped to [0, 1]: the inverse of ``compress``, as two squares."""
    return (torch.square(torch.square(compressed)) - FLOOR).clamp(0.0, 1.0)


def _lookup(u: torch.Tensor, start: torch.Tensor, step: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Curves sampled on uniform grids, read by linear interpolation, constant outside.

    u [B, 3, P]; start, step [B, 3, 1] (knot k of a channel sits at start + k * step);
    values [B, 3, K]  ->  [B, 3, P]. The knot is found by arithmetic, not a search, and
    read with one Gather from the flattened tables: a few operations per point and
    channel, each exact, so a point's value does not depend on how points are batched.
    """
    b, c, _ = u.shape
    knots = values.shape[-1]
    t = ((u - start) / step.clamp_min(_MIN_STEP)).clamp(0.0, knots - 1.0)
    knot = torch.floor(t).clamp(max=knots - 2.0)
    frac = t - knot
    rows = torch.arange(b, dtype=torch.int64, device=u.device).reshape(b, 1, 1) * (c * knots)
    channels = torch.arange(c, dtype=torch.int64, device=u.device).reshape(1, c, 1) * knots
    index = rows + channels + knot.to(torch.int64)
    flat = values.reshape(-1)
    below, above = flat[index], flat[index + 1]
    return below + frac * (above - below)


def _matvec3(m: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """m [B,3,3] times v [B,3,P] -> [B,3,P], as three products added in a fixed order."""
    return m[:, :, 0:1] * v[:, 0:1] + m[:, :, 1:2] * v[:, 1:2] + m[:, :, 2:3] * v[:, 2:3]


def apply_colour(rgb: torch.Tensor, colour: torch.Tensor) -> torch.Tensor:
    """Colour raw decoder output with per-texture tables.

    rgb float32 [B, P, 3] raw linear colour, colour float32 [B, colour_size] (one table
    per row of codes)  ->  float32 [B, P, 3] linear colour clamped to [0, 1].

    Channel-major inside ([B, 3, P]): every broadcast then repeats whole rows of points,
    ONNX Runtime's fast path (a trailing axis of 3 made the same ops ~2x slower).
    """
    b, k = colour.shape[0], (colour.shape[1] - 24) // 3
    a = colour[:, :9].reshape(b, 3, 3)
    start = colour[:, 9:12].reshape(b, 3, 1)
    step = colour[:, 12:15].reshape(b, 3, 1)
    values = colour[:, 15 : 15 + 3 * k].reshape(b, 3, k)
    back = colour[:, 15 + 3 * k :].reshape(b, 3, 3)
    d = _lookup(_matvec3(a, compress(rgb.transpose(1, 2))), start, step, values)
    return expand(_matvec3(back, d)).transpose(1, 2)


def compressed_moments(linear: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean [N,3] and covariance [N,3,3] of images [N,3,H,W] (linear RGB) in compressed colour."""
    return _moments(compress(linear).flatten(2))


def _moments(flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean [N,3] and covariance [N,3,3] of colours [N,3,M]."""
    mean = flat.mean(dim=2)
    centred = flat - mean.unsqueeze(2)
    return mean, centred @ centred.transpose(1, 2) / flat.shape[2]


def ridged(covariance: torch.Tensor) -> torch.Tensor:
    """Covariances [N,3,3] plus ``RIDGE`` times each one's mean variance (at least ``RIDGE_FLOOR``)."""
    share = (RIDGE * torch.diagonal(covariance, dim1=-2, dim2=-1).mean(-1)).clamp_min(RIDGE_FLOOR)
    return covariance + share[..., None, None] * torch.eye(3, dtype=covariance.dtype, device=covariance.device)


def transfer_colour_moments(linear: torch.Tensor, mean: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """Give images [N,3,H,W] (linear RGB) a compressed-colour mean [N,3] and covariance
    [N,3,3] by an affine map in compressed colour (Cholesky whitening, then colouring).

    Training's stand-in for the colour table: the loss then judges structure under the
    exemplar's colours, whatever colours the decoder produced, as the sampler will show
    them. Differentiable; a ridge (``ridged``) keeps flat patches finite.
    """
    flat = compress(linear).flatten(2)  # [N,3,HW]
    own_mean, own_covariance = _moments(flat)
    own = torch.linalg.cholesky(ridged(own_covariance))
    target = torch.linalg.cholesky(ridged(covariance))
    white = torch.linalg.solve_triangular(own, flat - own_mean.unsqueeze(2), upper=False)
    # clamped at 0 first: a negative compressed value would square back to a bright colour
    return expand((target @ white + mean.unsqueeze(2)).clamp_min(0.0)).reshape(linear.shape)
