"""2D slices of a solid texture: where the pixels of a synthesised patch lie in 3D.

Training (2D-to-3D) and evaluation both look at a 3D texture through square patches
on planes. A plane is an origin and two orthonormal in-plane axes; the patch's pixel
(i, j) sits at ``origin + (j + 0.5) / ppu * u + (i + 0.5) / ppu * v`` (rows along v),
so one patch pixel is one exemplar pixel, as at the tiles' native zoom.
"""

from __future__ import annotations

import numpy as np
import torch

from worker.contract import PLANE_AXES

#: the world axes each axis-aligned plane spans (u, v): the tiles' planes
AXIS_PLANES = {plane: axes[:2] for plane, axes in PLANE_AXES.items()}
LATTICE_PARTNER_STEPS = 2  # a partner lies up to this many lattice vectors away along each


def plane_points(origins: torch.Tensor, axes: torch.Tensor, size: int, pixels_per_unit: float) -> torch.Tensor:
    """Pixel centres of square patches.

    origins : float64 [B,3], axes : float64 [B,2,3] (u, v)  ->  float64 [B, size*size, 3]
    """
    steps = (torch.arange(size, dtype=torch.float64, device=origins.device) + 0.5) / pixels_per_unit
    rows, cols = torch.meshgrid(steps, steps, indexing="ij")  # [S,S]
    offsets = cols.reshape(1, -1, 1) * axes[:, None, 0, :] + rows.reshape(1, -1, 1) * axes[:, None, 1, :]
    return origins[:, None, :] + offsets


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """n uniformly random 3D rotation matrices [n,3,3] (QR of Gaussian matrices)."""
    q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def random_planes(
    n: int, rng: np.random.Generator, *, oblique_fraction: float = 0.5, extent: float = 1000.0, dims: int = 3,
    grain: str | None = None, photo_plane: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random slice planes: (origins float64 [n,3], axes float64 [n,2,3]).

    Axis-aligned planes pick xy / xz / yz with random in-plane sign flips; the rest
    are uniformly random orientations (oblique). Origins are uniform in
    [-extent, extent]^3 so training sees many different lattice cells. ``dims=2``
    keeps every plane at xy (planar textures).

    ``grain="x"`` or ``"y"`` is for anisotropic exemplars (wood, brushed metal) whose
    grain runs along the image's x (columns) or y (rows) axis: every plane then contains
    that world axis in the same role (``x``: u = world x, v turned about x; ``y``: v =
    world y, u turned about y), so the grain shows on all of them in the exemplar's own
    orientation; planes across the grain are left free for the solid to fill with
    whatever cross-section is consistent.

    ``photo_plane``: every plane is xy with u = world x, v = world y (rows), no flips: the
    exemplar's own orientation, for a lattice fit whose phases are fixed in xy.
    """
    if grain not in (None, "x", "y"):
        raise ValueError(f"grain must be None, 'x' or 'y', got {grain!r}")
    origins = rng.uniform(-extent, extent, size=(n, 3))
    axes = np.zeros((n, 2, 3))
    for k in range(n):  # n is a batch size (a handful), not a pixel count
        if photo_plane:
            axes[k, 0, 0] = axes[k, 1, 1] = 1.0
            continue
        if grain and dims == 3:
            turn = rng.uniform(0, 2 * np.pi) if rng.random() < oblique_fraction else rng.integers(0, 4) * np.pi / 2
            along, across = (0, 1) if grain == "x" else (1, 0)  # which of u, v follows the grain
            axes[k, along] = (1.0, 0.0, 0.0) if grain == "x" else (0.0, 1.0, 0.0)
            axes[k, across] = (0.0, np.cos(turn), np.sin(turn)) if grain == "x" else (np.cos(turn), 0.0, np.sin(turn))
            continue
        if dims == 2:
            a, b = AXIS_PLANES["xy"]
        elif rng.random() < oblique_fraction:
            axes[k] = random_rotations(1, rng)[0][:2]
            continue
        else:
            a, b = list(AXIS_PLANES.values())[rng.integers(0, 3)]
        axes[k, 0, a] = rng.choice([-1.0, 1.0])
        axes[k, 1, b] = rng.choice([-1.0, 1.0])
    if dims == 2:
        origins[:, 2] = 0.0
    return torch.from_numpy(origins), torch.from_numpy(axes)


def fixed_planes(kind: str, n: int, seed: int = 0, extent: float = 4.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic evaluation planes: kind 'axis' (xy, xz, yz in turn) or 'oblique'.

    Near the origin (``extent``), where position-input baselines were trained, so every
    variant is compared on ground it knows.
    """
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-extent, extent, size=(n, 3))
    if kind == "oblique":
        axes = random_rotations(n, rng)[:, :2]
    elif kind == "axis":
        axes = np.zeros((n, 2, 3))
        for k in range(n):
            a, b = list(AXIS_PLANES.values())[k % 3]
            axes[k, 0, a] = axes[k, 1, b] = 1.0
    else:
        raise ValueError(f"kind must be 'axis' or 'oblique', got {kind!r}")
    return torch.from_numpy(origins), torch.from_numpy(axes)


def linear_to_srgb(rgb: torch.Tensor) -> torch.Tensor:
    """Linear-light colour in [0,1] -> sRGB-encoded (IEC 61966-2-1), differentiable."""
    rgb = rgb.clamp(0.0, 1.0)
    high = 1.055 * rgb.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055
    return torch.where(rgb <= 0.0031308, 12.92 * rgb, high)


def srgb_to_linear(srgb: torch.Tensor) -> torch.Tensor:
    srgb = srgb.clamp(0.0, 1.0)
    return torch.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def render_slices(
    field, z: torch.Tensor, seeds: torch.Tensor, origins: torch.Tensor, axes: torch.Tensor, size: int,
    pixels_per_unit: float | None = None,
) -> torch.Tensor:
    """Synthesise square patches on planes: sRGB-encoded images [B,3,size,size].

    field : a TextureField; z float32 [B,8]; seeds int64 [B]; origins/axes from
    ``random_planes`` or ``fixed_planes``; pixels_per_unit: the patches' pixel spacing
    (default: the field's config, one patch pixel per exemplar pixel; model/detail.py renders finer).
    """
    if not torch.is_grad_enabled() and len(origins) > 1:
        # Without gradients (a fit's probe), one plane at a time: the field's per-octave
        # tensors for four 256-px planes at once outgrow the caches (one thread, idle
        # machine: 2.91 s at once, 1.68 s a plane; bench/run.py --only fit).
        return torch.cat([render_slices(field, z[k:k + 1], seeds[k:k + 1], origins[k:k + 1], axes[k:k + 1], size,
                                        pixels_per_unit) for k in range(len(origins))])
    points = plane_points(origins, axes, size, pixels_per_unit or field.cfg.pixels_per_unit)
    # anchored at each plane's origin: same colours, gradients without the far-field shift term
    rgb = field(points, z, seeds, anchor=origins if torch.is_grad_enabled() else None)  # [B, S*S, 3] linear
    return linear_to_srgb(rgb).reshape(-1, size, size, 3).permute(0, 3, 1, 2)


def lattice_partners(origins: torch.Tensor, lattice: tuple[float, float, float, float],
                     rng: np.random.Generator) -> torch.Tensor:
    """Each origin moved by a random whole, nonzero combination of the lattice vectors
    (world units, in the xy plane): a patch there has the same phases, other noise."""
    steps = np.zeros((len(origins), 2), dtype=np.int64)
    while True:
        redraw = ~steps.any(axis=1)
        if not redraw.any():
            break
        steps[redraw] = rng.integers(-LATTICE_PARTNER_STEPS, LATTICE_PARTNER_STEPS + 1, size=(redraw.sum(), 2))
    basis = np.array([[lattice[0], lattice[1], 0.0], [lattice[2], lattice[3], 0.0]])
    return origins + torch.from_numpy(steps @ basis).to(origins)
