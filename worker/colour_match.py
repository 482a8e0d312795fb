"""A texture's colour table: the photo's colour statistics, matched to the sampler's output.

The sampler applies the table as its last stage (``model/colour.py`` says how and what
the flat vector holds). This module computes it when a texture is encoded or refitted.
Statistics are taken in compressed colour, ``(rgb + FLOOR) ** (1/4)``, a log-like space
(model/colour.py says why).

1. The photo's principal colour axes ``B`` (eigenvectors of its compressed-colour
   covariance, largest first).
2. The texture's *raw* synthesis (the same sampler with the identity table) at many
   random 3D points and a few seeds, whitened by ``A`` so that, were its channels matched
   linearly, the table would be exactly the moment transfer training judges patches
   under (``model.colour.transfer_colour_moments``: Cholesky whitening of the raw colours,
   colouring by the photo's Cholesky factor), read on the photo's axes. (A symmetric
   whitening on the photo's axes mixed the raw output's near-silent colour directions into
   the photo's lightness axis: fits drew speckle they were never judged by.)
3. Per channel, a curve sampled on an even grid of ``u`` from the raw sample's smallest to
   its largest value: ``curves="quantile"``: ``photo quantile(raw CDF(u))``, so the tiles
   have the photo's colour histogram per decorrelated channel (an upload's encoder code,
   unless linear ones draw nearer the photo: ``worker.encode.code_colour``);
   ``"linear"``: the straight line that gives the photo's mean and spread, the moment
   transfer itself (a fit, which was optimised under it: quantile curves stretched the
   flat metal of a grill fit into speckle).

The curves are increasing, so structure (which pixels are darker than which) comes from
the network unchanged. Deterministic: the same sampler, code and photo give the same table.
"""
from __future__ import annotations

import numpy as np

from worker.colour import srgb_to_linear
from worker.errors import InvalidParameter

# Raw-synthesis sample: random points in a cube of this many world units (hundreds of
# exemplar widths, so the sample sees the texture's largest features many times) ...
CALIBRATION_EXTENT = 64.0
# ... this many points per seed, for these seeds. 16k points: the 1/32 quantiles are
# known to ~0.3% of the range; it costs ~20 ms of sampling.
CALIBRATION_POINTS = 4096
CALIBRATION_SEEDS = (0, 1, 2, 3)
MAX_PHOTO_PIXELS = 1 << 16  # photo pixels used for its statistics (a fixed-stride subset)
FLOOR = 1.0 / 256.0  # compressed colour is (rgb + FLOOR) ** (1/4): a finite slope at black
MIN_STEP = 1e-6  # the smallest raw range a curve spans (a flat raw channel)
# Ridge added to each covariance before its Cholesky factor, a share of its mean variance
# (and at least RIDGE_FLOOR); training's moment transfer (model/colour.py) imports all three. A
# flat raw channel stays finite. (A fixed 1e-6 was the size of a near-grey fit's raw colour
# variance and took ~30% of its tiles' chroma spread: CIELAB a/b std 0.56-0.69x the photo's
# on four of 40 validation photos.)
RIDGE = 1e-6
RIDGE_FLOOR = 1e-8
CURVES = ("quantile", "linear")  # an encoder code's table, a fit's (the module docstring)
# The recipe a stored table was made by, kept with it (service: Texture.colour_calibration).
# 1: the symmetric whitening on the photo's axes and quantile curves for every sampler;
# 2: the moment whitening above, quantile curves for an encoder code, linear for a fit;
# 3: as 2 with a ridge relative to each covariance's scale (``RIDGE``), not a fixed 1e-6.
# 4: as 3, an encoder code's curves linear where its tile lies nearer the photo's style
#    (``worker.encode.code_colour``; models without style statistics: quantile, as 3).
# Bump it whenever calibrate_texture makes different tables for the same inputs:
# ``texspace recolour`` then brings the stored ones up to date.
COLOUR_CALIBRATION = 4


def knots_of(colour_size: int) -> int:
    """Curve samples per channel of a table of ``colour_size`` numbers (24 + 3 * knots)."""
    knots, rest = divmod(colour_size - 24, 3)
    if rest or knots < 2:
        raise InvalidParameter(f"a colour table has 24 + 3 * knots numbers, got {colour_size}")
    return knots


def identity_colour(colour_size: int) -> np.ndarray:
    """The table that leaves colours in [0, 1] unchanged. Returns (colour_size,) float32."""
    knots = knots_of(colour_size)
    eye = np.eye(3, dtype=np.float32).ravel()
    low, high = FLOOR**0.25, (1.0 + FLOOR) ** 0.25
    grid = [low] * 3 + [(high - low) / (knots - 1)] * 3
    ramp = np.tile(np.linspace(low, high, knots), 3)
    return np.concatenate([eye, grid, ramp, eye]).astype(np.float32)


def photo_axes(pixels: np.ndarray) -> np.ndarray:
    """Principal colour axes of pixels (N, 3) float: columns of an orthonormal (3, 3).

    Largest variance first; each axis points the way its components sum positive
    (brighter), so the table's channels are the same for two similar photos and a
    blend of two tables does not flip a channel through zero.
    """
    covariance = np.cov(pixels, rowvar=False) + np.eye(3) * 1e-12
    _, vectors = np.linalg.eigh(covariance)
    vectors = vectors[:, ::-1]
    signs = np.where(vectors.sum(axis=0) < 0, -1.0, 1.0)
    return vectors * signs


def compressed_colour(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB (..., 3) -> float64 compressed colour, as the sampler graph computes it."""
    return np.sqrt(np.sqrt(np.clip(np.asarray(rgb, np.float64), 0.0, 1.0) + FLOOR))


def colour_table(photo_linear: np.ndarray, raw: np.ndarray, knots: int, curves: str = "quantile") -> np.ndarray:
    """Colour table that maps raw synthesis onto the photo's colour distribution.

    photo_linear : (N, 3) float, the photo's linear-RGB pixels.
    raw : (M, 3) float32, raw sampler output (identity table) at random points.
    curves : "quantile" (histograms) or "linear" (mean and covariance), see the module docstring.
    Returns (24 + 3 * knots,) float32 (layout in model/colour.py).
    """
    if curves not in CURVES:
        raise ValueError(f"curves must be one of {CURVES}, got {curves!r}")
    photo = compressed_colour(photo_linear).reshape(-1, 3)
    raw = compressed_colour(raw).reshape(-1, 3)
    if len(photo) < 2 or len(raw) < 2:
        raise InvalidParameter("colour statistics need at least two photo pixels and two samples")
    axes = photo_axes(photo)  # B: d -> rgb is axes @ d; rgb -> d is axes.T @ rgb
    a = moment_whitening(photo, raw, axes)  # u = A rgb
    u = np.sort(raw @ a.T, axis=0)  # (M, 3)
    d = np.sort(photo @ axes, axis=0)  # (N, 3)
    start, stop = u[0], u[-1]
    step = np.maximum(stop - start, MIN_STEP) / (knots - 1)
    grid = start + np.arange(knots)[:, None] * step  # (knots, 3)
    if curves == "linear":
        values = (d.mean(0) + d.std(0) * (grid - u.mean(0))).T  # u as whitened: the transfer exactly
    else:
        values = np.empty((3, knots))
        for c in range(3):  # three channels: the work inside is vectorised
            # the raw CDF at each grid value (mid-rank of ties), then the photo's quantile there
            below = np.searchsorted(u[:, c], grid[:, c], side="left")
            at_or_below = np.searchsorted(u[:, c], grid[:, c], side="right")
            level = np.clip((below + at_or_below) / (2.0 * len(u)), 0.0, 1.0)
            values[c] = np.quantile(d[:, c], level)
        values[:, 0], values[:, -1] = d[0], d[-1]  # the grid's ends are the raw extremes
    return np.concatenate([a.ravel(), start, step, values.ravel(), axes.ravel()]).astype(np.float32)


def moment_whitening(photo: np.ndarray, raw: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """``A`` (3, 3): compressed raw colour -> white channels, one per photo axis, such that
    ``axes @ diag(photo std on the axes) @ A`` is training's moment transfer ``Lp Lr^-1``
    (Cholesky factors of the photo's and the raw colours' covariances). ``axes.T @ Lp`` is
    ``diag(std) Q`` with Q orthogonal (its rows are orthogonal: ``axes`` diagonalise the
    photo's covariance), so ``A = Q Lr^-1``; Q is taken as the orthogonal polar factor."""
    raw_factor, photo_factor = (np.linalg.cholesky(ridged_covariance(colours)) for colours in (raw, photo))
    left, _, right = np.linalg.svd(axes.T @ photo_factor)
    return (left @ right) @ np.linalg.inv(raw_factor)


def ridged_covariance(colours: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of colours (N, 3) plus ``RIDGE`` times its mean variance (at least ``RIDGE_FLOOR``)."""
    covariance = np.cov(colours, rowvar=False)
    return covariance + max(RIDGE * np.trace(covariance) / 3, RIDGE_FLOOR) * np.eye(3)


def photo_pixels(image: np.ndarray) -> np.ndarray:
    """Linear-RGB pixels (N, 3) float32 of an sRGB photo (H, W, 3), at most MAX_PHOTO_PIXELS."""
    flat = np.asarray(image, np.float32).reshape(-1, 3)
    stride = max(1, len(flat) // MAX_PHOTO_PIXELS)
    return srgb_to_linear(flat[::stride])


def calibration_points() -> np.ndarray:
    """The fixed random points (CALIBRATION_POINTS, 3) float64 the raw synthesis is read at."""
    return np.random.default_rng(20200614).random((CALIBRATION_POINTS, 3)) * CALIBRATION_EXTENT


def calibrate_texture(sampler, code: np.ndarray, image: np.ndarray, curves: str = "quantile") -> np.ndarray:
    """The colour table of a texture: ``code`` (8,) synthesised by ``sampler``, photo ``image``;
    ``curves``: "quantile" for an encoder code, "linear" for a fitted sampler (``colour_table``).

    sampler : a SamplerSession (worker/runtime.py) whose graph has a colour input.
    image : (H, W, 3) float32 sRGB 0..1, the texture's exemplar at the model's working
        resolution (``worker.photo.resize_short_side(image, exemplar_short_side)``).
    Returns (sampler.colour_size,) float32; empty (0,) when the sampler has no colour stage.
    """
    size = getattr(sampler, "colour_size", 0)
    if not size:
        return np.zeros(0, np.float32)
    code = np.asarray(code, np.float32).reshape(-1)[: sampler.code_size]
    vector = np.concatenate([code, identity_colour(size)])
    points = calibration_points()
    raw = np.concatenate([sampler.sample(points, vector, seed) for seed in CALIBRATION_SEEDS])
    return colour_table(photo_pixels(image), raw, knots_of(size), curves)


def texture_vector(code, colour) -> np.ndarray:
    """What samplers take as a texture's code: z (8) followed by its colour table, if any."""
    parts = [np.asarray(code, np.float32).reshape(-1)]
    if colour is not None and len(colour):
        parts.append(np.asarray(colour, np.float32).reshape(-1))
    return np.concatenate(parts)


def blend_textures(a, b, t: float, colour_size: int) -> tuple[list[float], list[float] | None]:
    """(1 - t) a + t b of two textures' (code, colour table) pairs in one model's space.
    Tables blend knot by knot; a texture without one has the identity (``colour_size`` 0:
    the model has no colour stage, and the blend none)."""
    (za, ca), (zb, cb) = a, b
    code = (1.0 - t) * np.asarray(za, np.float64) + t * np.asarray(zb, np.float64)
    ca, cb = (np.asarray(c or identity_colour(colour_size), np.float64) if colour_size else np.zeros(0)
              for c in (ca, cb))
    return [float(c) for c in code], [float(c) for c in (1.0 - t) * ca + t * cb] or None
