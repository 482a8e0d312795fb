"""Networks of the neural 3D texture space (Henzler, Mitra, Ritschel, CVPR 2020).

    exemplar [B,3,128,128] --Encoder--> z [B,8] --Translator--> e [B,64], T [B,K,D,D]
    point x [B,P,D] --(T_k 2^k x, octave k)--> lattice noise --Decoder(noise, e)--> rgb

One ``TextureField`` evaluates every variant of the paper's comparison; a variant is a
set of switches (``VARIANTS``), so baselines and ours share every line they can.
Shapes: B codes (exemplars, or points when codes vary per point), P points per code,
K octaves, D spatial dimensions (2 or 3).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from model.config import ModelConfig
from model.noise import cell_shade, noise_features, octave_seeds


# ----------------------------------------------------------------------------- encoder


class ResidualBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.norm1 = nn.InstanceNorm2d(c_out, affine=True)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.norm2 = nn.InstanceNorm2d(c_out, affine=True)
        self.skip = (
            nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.InstanceNorm2d(c_out, affine=True))
            if stride != 1 or c_in != c_out
            else nn.Identity()
        )

    def forward(self, x):
        y = F.relu(self.norm1(self.conv1(x)))
        return F.relu(self.norm2(self.conv2(y)) + self.skip(x))


class Encoder(nn.Module):
    """Exemplar -> code z. A ResNet-18-like layout (one block per stage, instance norm).

    Instance norm discards each channel's mean and contrast, which *are* the texture's
    colour, so the input's per-channel mean and std join the pooled features; a
    ``colour_blind`` encoder instead normalises every channel of its input first and
    feeds zeros there (the layout stays the same, so either warm-starts the other).
    image float32 [B,3,H,W] in [-1,1] (sRGB-encoded, RGB)  ->  z float32 [B,code_size]
    """

    def __init__(self, code_size: int = 8, width: int = 32, colour_blind: bool = False):
        super().__init__()
        self.colour_blind = colour_blind
        w = width
        self.stem = nn.Sequential(
            nn.Conv2d(3, w, 5, 2, 2, bias=False), nn.InstanceNorm2d(w, affine=True), nn.ReLU()
        )
        self.stages = nn.Sequential(
            ResidualBlock(w, w, 1),
            ResidualBlock(w, 2 * w, 2),
            ResidualBlock(2 * w, 4 * w, 2),
            ResidualBlock(4 * w, 8 * w, 2),
        )
        self.head = nn.Sequential(nn.Linear(8 * w + 6, 128), nn.ReLU(), nn.Linear(128, code_size))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        stats = torch.cat([image.mean(dim=(2, 3)), image.std(dim=(2, 3))], dim=1)  # [B,6]
        if self.colour_blind:
            image = (image - stats[:, :3, None, None]) / (stats[:, 3:, None, None] + 1e-3)
            stats = torch.zeros_like(stats)
        pooled = self.stages(self.stem(image)).mean(dim=(2, 3))  # [B,8w]
        return self.head(torch.cat([pooled, stats], dim=1))


# ----------------------------------------------------------------------------- field


# Octave k's turn about z in periodic (tileable) synthesis, as (a, b, c) with cos = a/c,
# sin = b/c: a lattice turned by a rational angle repeats after whole cells along both
# tile axes, an irrational one never. Octave 0 stays axis-aligned as in
# ``_fixed_rotations``; small c for the coarse octaves (a period spans fewest of their
# cells); alternating signs so neighbouring octaves do not share a direction.
TILEABLE_ROTATIONS = ((1, 0, 1), (0, 1, 1), (4, 3, 5), (3, -4, 5), (12, 5, 13), (5, -12, 13), (15, 8, 17), (8, -15, 17))
# A grain fit's octaves turn by quarter turns only (c = 1). A turn with c > 1 quantises the
# frequency along x to multiples of c per period, and along a 16x grain every octave of a
# 256-px tileable image wanted under half of its c (the finest: 8 cells, c = 17). Its cells are
# long along the grain whatever the turn (the stretch comes first), as on the infinite plane.
TILEABLE_GRAIN_ROTATIONS = ((1, 0, 1), (0, 1, 1), (-1, 0, 1), (0, -1, 1))


def _fixed_rotations(n: int, dims: int, seed: int = 20200614) -> torch.Tensor:
    """n deterministic random rotation matrices [n, dims, dims] (QR of Gaussians)."""
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(n, dims, dims, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    det = torch.linalg.det(q)
    q[..., :, 0] *= det.sign().unsqueeze(-1)  # proper rotations (det +1)
    q[0] = torch.eye(dims, dtype=torch.float64)  # octave 0 stays axis-aligned
    return q


def _determinant(m: torch.Tensor) -> torch.Tensor:
    """det of [..., D, D] matrices, D in (2, 3), written out (ONNX Runtime has no float Det)."""
    if m.shape[-1] == 2:
        return m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    return (m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
            - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
            + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0]))


class Translator(nn.Module):
    """z [B,8] -> extended code e [B,64], transforms T [B,K,D,D], RGB octave weights [B,K+1,3]."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        k, d = cfg.n_octaves, cfg.dims
        self.cfg = cfg
        self.body = nn.Sequential(nn.Linear(cfg.code_size, 128), nn.ReLU(), nn.Linear(128, 128), nn.ReLU())
        self.to_extended = nn.Linear(128, cfg.extended_size)
        self.to_transform = nn.Linear(128, k * d * d)
        self.to_mix = nn.Linear(128, (k + 1) * 3)
        # Variance-preserving init: with PyTorch's default the code's influence on e shrank
        # ~30x through the translator, the decoder learned one average texture first and
        # then never used the code.
        for layer in self.body:
            if isinstance(layer, nn.Linear):
                nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
                nn.init.zeros_(layer.bias)
        nn.init.normal_(self.to_extended.weight, std=1.0 / 128**0.5)
        nn.init.zeros_(self.to_extended.bias)
        # Start every transform at the identity: the network learns departures from it.
        nn.init.zeros_(self.to_transform.weight)
        nn.init.zeros_(self.to_transform.bias)

    def forward(self, z: torch.Tensor):
        """z float32 [B,8] -> e float32 [B,64], transforms float64 [B,K,D,D], mix float32 [B,K+1,3].

        The transforms run in float64 from the code on. They scale lattice coordinates that
        reach the millions far from the origin (128 cells per unit at the finest octave), so
        one float32 rounding step in them moved a far tile's finest octaves by whole cells:
        a code changed by one part in 10^7 changed torch's own colours by up to 0.05 at
        5,000 units, as much as torch and ONNX Runtime then differed there (whose GEMMs
        round differently, as CPUs' kernels may). In float64 such steps are 10^-16."""
        k, d = self.cfg.n_octaves, self.cfg.dims
        h = z.to(torch.float64)
        for layer in self.body:  # Linear, ReLU, Linear, ReLU
            h = F.linear(h, layer.weight.double(), layer.bias.double()) if isinstance(layer, nn.Linear) else layer(h)
        eye = torch.eye(d, dtype=torch.float64, device=z.device)
        weight, bias = self.to_transform.weight.double(), self.to_transform.bias.double()
        transforms = eye + F.linear(h, weight, bias).reshape(-1, k, d, d)
        if self.cfg.isotropic_transforms:
            scale = _determinant(transforms).abs().clamp_min(1e-12) ** (1.0 / d)
            transforms = scale[..., None, None] * eye
        h = h.to(z.dtype)
        mix = self.to_mix(h).reshape(-1, k + 1, 3)
        return self.to_extended(h), transforms, mix


def _bias_matmul(bias: torch.Tensor, x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``bias + x @ weight.T`` for x [B,P,I], bias [B,1,O], weight [O,I]: one ``baddbmm``,
    the bias added in the product's own pass (the shipped decoder's forward and backward, two
    codes of 16k points in bf16 on an AMX Xeon's two cores: 40-44 ms as Linear + add, 26-32 ms
    with the hidden layers so)."""
    return torch.baddbmm(bias, x, weight.t().expand(x.shape[0], -1, -1))


class Decoder(nn.Module):
    """MLP f(noise, position, e) -> colour logits, ReLU, ``n_hidden_layers`` x ``hidden``.

    The code e enters every layer as a per-code bias (``from_code`` gives one bias per
    hidden layer plus the output), which is the same as concatenating e to each layer's
    input. Every texture can therefore move its colours and features directly. With e
    only at the input, a space trained on CPU for a few hours ignored the code and
    collapsed to one average texture. Each bias is computed once per code, not once
    per point.
    """

    def __init__(self, n_noise: int, n_position: int, n_code: int, hidden: int, n_hidden_layers: int,
                 n_phase: int = 0):
        super().__init__()
        self.hidden, self.n_hidden_layers = hidden, n_hidden_layers
        self.from_noise = nn.Linear(n_noise, hidden, bias=False) if n_noise else None
        self.from_position = nn.Linear(n_position, hidden, bias=False) if n_position else None
        self.from_phase = nn.Linear(n_phase, hidden, bias=False) if n_phase else None
        self.from_code = nn.Linear(n_code, hidden * n_hidden_layers + 3)
        self.layers = nn.ModuleList(nn.Linear(hidden, hidden, bias=False) for _ in range(n_hidden_layers - 1))
        self.out = nn.Linear(hidden, 3, bias=False)
        # He initialisation keeps the activations' spread through the ReLU stack, so an
        # untrained decoder already varies with its noise input instead of being flat.
        for layer in self.modules():
            if isinstance(layer, nn.Linear):
                nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
                if layer.bias is not None:
                    nn.init.zeros_(layer.bias)
        nn.init.normal_(self.from_code.weight, std=1.0 / n_code**0.5)
        nn.init.normal_(self.out.weight, std=0.5 / hidden**0.5)
        if self.from_phase is not None:  # zero: the space's texture (a fit sets the mean cell's: start_on_mean_cell)
            nn.init.zeros_(self.from_phase.weight)

    def forward(self, noise, position, code, phase=None):
        points = noise if noise is not None else position  # [B,P,*]
        if code.shape[0] == 1 or points.shape[1] == 1:
            return self._forward_rows(noise, position, code, phase)
        biases = self.from_code(code).unsqueeze(1)  # [B,1,H*L+3]
        hidden = self.hidden
        h = biases[..., :hidden]
        if self.from_noise is not None:
            h = _bias_matmul(h, noise, self.from_noise.weight)
        if self.from_position is not None:
            h = h + self.from_position(position)
        if self.from_phase is not None:
            h = h + self.from_phase(phase)
        h = F.relu(h)
        for i, layer in enumerate(self.layers, start=1):
            h = F.relu(_bias_matmul(biases[..., i * hidden : (i + 1) * hidden], h, layer.weight))
        # (the output's bias added apart: in float32 under a bf16 autocast, as the logits were before)
        return self.out(h) + biases[..., -3:]

    def _forward_rows(self, noise, position, code, phase=None):
        """``forward`` where one code serves all points (B = 1) or each code one point
        (P = 1), the two shapes the exported sampler sees: then the points flatten to
        rows and each layer is one ``addmm`` with its code bias (an ONNX Gemm, which
        adds the bias and, fused by ONNX Runtime, the ReLU in the GEMM's own pass)."""
        biases = self.from_code(code)  # [B,H*L+3]: broadcast over the P rows when B = 1
        hidden = self.hidden
        h = biases[:, :hidden]
        if self.from_noise is not None:
            h = torch.addmm(h, noise.reshape(-1, noise.shape[-1]), self.from_noise.weight.t())
        if self.from_position is not None:
            h = h + self.from_position(position.reshape(-1, position.shape[-1]))
        if self.from_phase is not None:  # (addmm: the graph keeps the weight's name, which worker/shader.py reads)
            h = torch.addmm(h, phase.reshape(-1, phase.shape[-1]), self.from_phase.weight.t())
        h = F.relu(h)
        for i, layer in enumerate(self.layers, start=1):
            h = F.relu(torch.addmm(biases[:, i * hidden : (i + 1) * hidden], h, layer.weight.t()))
        rgb = torch.addmm(biases[:, -3:], h, self.out.weight.t())
        points = noise if noise is not None else position
        return rgb.reshape(points.shape[:-1] + (3,))


class TextureField(nn.Module):
    """Colour of the texture with code z and seed at any points.

    points float64 [B,P,3] (only the first ``dims`` coordinates are used),
    z float32 [B,code_size], seed int64 [] or [B]  ->  rgb float32 [B,P,3], linear 0..1
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        flags = cfg.flags
        k, d = cfg.n_octaves, cfg.dims
        self.translator = Translator(cfg)
        n_noise = k * 3 * (2 if cfg.nearest_input else 1) if flags.noise else 0
        n_phase = ((4 * cfg.lattice_harmonics if cfg.lattice else 0) + (3 if cfg.lattice_shade else 0)
                   + (3 if cfg.lattice_cell else 0))
        self.decoder = (
            Decoder(n_noise, d if flags.position else 0, cfg.extended_size, cfg.hidden, cfg.n_hidden_layers, n_phase)
            if flags.decoder
            else None
        )
        # Octave k has 2^k cells per world unit (a cell of octave 0 = pixels_per_unit pixels).
        frequencies = torch.tensor([2.0**i for i in range(k)], dtype=torch.float64)
        rotations = _fixed_rotations(k, d) if cfg.octave_rotations else torch.eye(d, dtype=torch.float64).repeat(k, 1, 1)
        self.register_buffer("octave_basis", rotations * frequencies[:, None, None], persistent=True)
        # A fixed fractional shift per octave, so no two octaves' cell borders line up at
        # integer world coordinates (where tile borders fall at native zoom). The noise's
        # distribution is shift-invariant, so this changes no learned statistics.
        g = torch.Generator().manual_seed(20200615)
        self.register_buffer("octave_offset", torch.rand(k, d, generator=g, dtype=torch.float64), persistent=False)
        scale = torch.ones(d, dtype=torch.float64)
        if cfg.grain:
            scale[{"x": 0, "y": 1}[cfg.grain]] = 1.0 / cfg.grain_stretch
        self.register_buffer("world_scale", scale, persistent=False)
        self.warp = nn.Parameter(torch.zeros(2, 2, dtype=torch.float64)) if cfg.warp else None
        if cfg.lattice:
            basis = torch.tensor(cfg.lattice, dtype=torch.float64).reshape(2, 2).t()  # columns a, b
            self.register_buffer("lattice_inverse", torch.linalg.inv(basis), persistent=False)
        if cfg.lattice_cell:  # [n_a, n_b, 3], standardised colour; a fit fills it in
            self.register_buffer("lattice_mean_cell", torch.zeros(*cfg.lattice_cell, 3), persistent=True)

    def warp_matrix(self) -> torch.Tensor:
        """float64 [D,D]: I + ``warp`` on x, y; in 3D, z scaled by that block's mean scale
        (sqrt |det|). A photo shows its lean in its own plane only, so depth takes the map's
        scale without its direction: with z as it was, a fit that grew its features in x, y
        left them the space's size along z (docs/DECISIONS.md, "A lean's depth")."""
        xy = torch.eye(2, dtype=torch.float64, device=self.warp.device) + self.warp
        if self.cfg.dims == 2:
            return xy
        mean_scale = (xy[0, 0] * xy[1, 1] - xy[0, 1] * xy[1, 0]).abs().sqrt()  # (written out: ONNX has no det)
        return torch.cat([F.pad(xy, (0, 1)), F.pad(mean_scale.reshape(1, 1), (2, 0))])

    def lattice_phases(self, points: torch.Tensor, period: torch.Tensor | None = None,
                       shade_seed: torch.Tensor | None = None) -> torch.Tensor:
        """float64 [B,P,>=2] -> float32 [B,P,4*H (+3) (+3)]: sin and cos of 2 pi k u, u the
        point's (x, y) in lattice coordinates, k = 1..H (``lattice_harmonics``); with
        ``lattice_shade`` the cell's three shade values in [-1, 1] (``cell_shade`` of floor(u)
        and ``shade_seed``, int32 [] or [B,1]); with a ``lattice_cell`` the mean cell's colour at
        the phase (last: ``start_on_mean_cell`` sets those columns). Exactly periodic on the
        lattice but for the shades; u is taken in float64 so far-away points keep their phase.

        ``period`` (float64 [], world units; tileable synthesis): the lattice nudged so that
        it also repeats every ``period`` in x and y: period x the inverse basis rounded to
        whole numbers (how many cells a period crosses along each lattice axis), divided by
        the period. A 256-px tile of the brick wall moves its bond offset by half a pixel.
        The shades repeat with it: cells a period apart are one cell (``wrap_cells``)."""
        inverse = self.lattice_inverse
        crossed = None
        if period is not None:
            crossed = torch.round(period * inverse)  # [2,2]: cells crossed per period, column j along world axis j
            inverse = crossed / period
        u = points[..., :2] @ inverse.t()  # [B,P,2]
        k = torch.arange(1, self.cfg.lattice_harmonics + 1, dtype=torch.float64, device=points.device)
        # the fractional part first: sin/cos of a small float32 angle, exact at any distance
        # (one Floor, subtracted from its own input: worker/shader.py finds u that way)
        cell = torch.floor(u)
        phase = u - cell
        angle = (2.0 * math.pi) * phase.unsqueeze(-1) * k  # [B,P,2,H]
        angle = angle.to(torch.float32).reshape(*u.shape[:-1], -1)
        features = [torch.sin(angle), torch.cos(angle)]
        if self.cfg.lattice_shade:
            if shade_seed is None:
                raise ValueError("a field with lattice_shade needs the shade_seed (forward: octave_seeds' one more)")
            wrap = crossed.t() if crossed is not None else None  # rows: the cell shifts of a period along x, y
            shade = cell_shade(cell[..., 0], cell[..., 1], shade_seed, wrap)
            features.append((shade - 0.5) * 2.0)  # centred, as the noise inputs
        if self.cfg.lattice_cell:
            features.append(self.mean_cell_colour(phase))
        return torch.cat(features, dim=-1)

    def mean_cell_colour(self, phase: torch.Tensor) -> torch.Tensor:
        """float64 [...,2] in [0,1)^2 -> float32 [...,3]: ``lattice_mean_cell`` read
        bilinearly at the phase, wrapping around the cell (samples at cell-centred phases)."""
        n_a, n_b = self.cfg.lattice_cell
        sizes = torch.tensor([n_a, n_b], dtype=torch.float64, device=phase.device)
        x = phase * sizes - 0.5
        low = torch.floor(x)
        # x + (-low), not x - low: worker/shader.py finds the noise and phase lattices in the
        # graph as the inputs of "x - floor(x)", and this is neither
        t = (x + low.neg()).to(torch.float32)
        low = low.to(torch.int64)
        i0, j0 = torch.remainder(low[..., 0], n_a), torch.remainder(low[..., 1], n_b)
        i1, j1 = torch.remainder(i0 + 1, n_a), torch.remainder(j0 + 1, n_b)
        cell = self.lattice_mean_cell  # (indexed whole: the graph keeps its name and shape for worker/shader.py)
        ta, tb = t[..., :1], t[..., 1:]
        top = cell[i0, j0] + ta * (cell[i1, j0] - cell[i0, j0])
        bottom = cell[i0, j1] + ta * (cell[i1, j1] - cell[i0, j1])
        return top + tb * (bottom - top)

    def lattice_points(self, points: torch.Tensor, transforms: torch.Tensor,
                       anchor: torch.Tensor | None = None) -> torch.Tensor:
        """points float64 [B,P,D], transforms [B,K,D,D] -> float64 [B,P,K,D] (one matmul).

        ``anchor`` (float64 [B,D], training only) changes the gradient, not the value: the
        lattice point M x is computed as M (x - a) + stop_gradient(M a). Without it, the
        gradient of a transform at a patch 1000 units from the origin is ~1000x larger and
        is nothing but "shift the noise", which leaves the texture's statistics unchanged
        (the noise is stationary); under the global gradient clip that term starved every
        other weight, and variants with transforms trained far slower than those without.
        """
        b, p, d = points.shape
        k = self.cfg.n_octaves
        if self.cfg.grain:  # (a Python branch: isotropic exports carry no extra node)
            points = points * self.world_scale
            anchor = anchor * self.world_scale if anchor is not None else None
        if self.warp is not None:  # (x, y) -> (I + W) (x, y); z by its mean scale
            warp = self.warp_matrix().t()
            points = points @ warp
            anchor = anchor[..., :d] @ warp if anchor is not None else None
        mats = self.octave_basis.unsqueeze(0)  # [1,K,D,D]
        if self.cfg.flags.transforms:
            mats = torch.matmul(transforms.to(torch.float64), mats)  # T_k (R_k 2^k)
        else:
            mats = mats.expand(b, k, d, d)
        # p[b,n,k,i] = sum_j M[b,k,i,j] x[b,n,j]  ->  x [B,P,D] @ M' [B,D,K*D]
        stacked = mats.permute(0, 3, 1, 2).reshape(mats.shape[0], d, k * d)
        if anchor is not None:
            anchor = anchor[:, None, :d]  # [B,1,D]
            local = torch.matmul(points - anchor, stacked) + torch.matmul(anchor, stacked).detach()
            return local.reshape(b, p, k, d) + self.octave_offset
        return torch.matmul(points, stacked).reshape(b, p, k, d) + self.octave_offset

    def periodic_lattice(self, points: torch.Tensor, transforms: torch.Tensor,
                         period: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Lattice points of the texture made to repeat every ``period`` world units in x and
        y (the plane of 2D tiles), and each octave's wrap: points float64 [B,P,D], period
        float64 []  ->  (float64 [B,P,K,D], float64 [2,2,B,1,K]).

        Each octave keeps its learned volume scale and grain, turns about z by its angle
        in ``TILEABLE_ROTATIONS`` (a grain fit's: ``TILEABLE_GRAIN_ROTATIONS``; cos = a/c,
        sin = b/c), and has its frequency along x and y rounded so that one period spans
        m = round(f L / c) >= 1 steps (>= 0 along a grain: none, constant along it): a period
        then moves the octave's lattice by the integer vectors m_x (a, b) and m_y (-b, a),
        which the noise wraps (``wrap_cells`` in model/noise.py). The rounding moves a
        frequency by at most c / (2 f L) of itself: ~6% for a 1024^2 tile (L = 4 units).
        With a ``warp`` W, each octave's whole 2x2 map f W diag(grain) L / c is rounded to
        integer steps N (its diagonal at least 1; where N would be singular, as at coarse
        octaves of a mild warp, its off-diagonal is dropped): a period along x then moves the
        lattice by R N e_x, along y by R N e_y, R the octave's turn.
        """
        b, p, d = points.shape
        k = self.cfg.n_octaves
        dev = points.device
        scale = torch.ones(b, k, dtype=torch.float64, device=dev)
        if self.cfg.flags.transforms:
            scale = _determinant(transforms.to(torch.float64)).abs().clamp_min(1e-12) ** (1.0 / d)
        freq = scale * torch.tensor([2.0**i for i in range(k)], dtype=torch.float64, device=dev)  # [B,K]
        turns = TILEABLE_GRAIN_ROTATIONS if self.cfg.grain else TILEABLE_ROTATIONS
        a, s, c = torch.tensor([turns[i % len(turns)] for i in range(k)],
                               dtype=torch.float64, device=dev).unbind(-1)  # [K] each
        grain = self.world_scale.to(dev)
        x, y = points[..., 0:1], points[..., 1:2]  # [B,P,1]
        if self.warp is None:
            # Along a grain, a coarse octave may round to no step per period: it is then constant
            # along the grain, as its cells, longer than the period, nearly are on the infinite
            # plane. A floor of one step made them one period long and round: a 16x wood fit's
            # 256-px tileable image had 4.2x the gradients across its grain as along it, the map 14x.
            floor_x, floor_y = (0.0 if self.cfg.grain == "x" else 1.0), (0.0 if self.cfg.grain == "y" else 1.0)
            steps_x = torch.clamp_min(torch.round(freq * grain[0] * period / c), floor_x)  # [B,K]
            steps_y = torch.clamp_min(torch.round(freq * grain[1] * period / c), floor_y)
            fx, fy = (steps_x / period).unsqueeze(1), (steps_y / period).unsqueeze(1)  # [B,1,K] (x c / c)
            axes = [a * fx * x - s * fy * y, s * fx * x + a * fy * y]
            # a wrap vector of an axis with no step only keeps the wrap basis invertible: no point
            # moves along it (one step of the turned axis, an integer vector)
            wrap_x, wrap_y = torch.clamp_min(steps_x, 1.0), torch.clamp_min(steps_y, 1.0)
            u = torch.stack([wrap_x * a, wrap_x * s])  # [2,B,K]
            v = torch.stack([-wrap_y * s, wrap_y * a])
        else:
            warp = self.warp_matrix()
            g = warp[:2, :2] * grain[:2]  # W diag(grain), as lattice_points maps (x, y)
            n = [[torch.round(freq * g[i, j] * period / c) for j in range(2)] for i in range(2)]  # [B,K] each
            n[0][0], n[1][1] = torch.clamp_min(n[0][0], 1.0), torch.clamp_min(n[1][1], 1.0)
            singular = n[0][0] * n[1][1] == n[0][1] * n[1][0]
            n[0][1], n[1][0] = (torch.where(singular, torch.zeros_like(m), m) for m in (n[0][1], n[1][0]))
            qx = (n[0][0] / period).unsqueeze(1) * x + (n[0][1] / period).unsqueeze(1) * y  # [B,P,K]
            qy = (n[1][0] / period).unsqueeze(1) * x + (n[1][1] / period).unsqueeze(1) * y
            axes = [a * qx - s * qy, s * qx + a * qy]
            u = torch.stack([a * n[0][0] - s * n[1][0], s * n[0][0] + a * n[1][0]])  # R N e_x
            v = torch.stack([a * n[0][1] - s * n[1][1], s * n[0][1] + a * n[1][1]])  # R N e_y
        if d == 3:  # depth as the sampler has it (a warp's mean scale of x, y)
            depth = points[..., 2:3] * warp[2, 2] if self.warp is not None else points[..., 2:3]
            axes.append(freq.unsqueeze(1) * depth)
        lattice = torch.stack(axes, dim=-1) + self.octave_offset  # [B,P,K,D]
        return lattice, torch.stack([u, v]).unsqueeze(3)  # [2,2,B,1,K]

    def forward(self, points: torch.Tensor, z: torch.Tensor, seed: torch.Tensor,
                anchor: torch.Tensor | None = None, period: torch.Tensor | None = None) -> torch.Tensor:
        """``period`` (float64 [], world units): synthesise the texture made periodic in x
        and y with that period (``periodic_lattice``) instead of the infinite one."""
        cfg, flags = self.cfg, self.cfg.flags
        points = points[..., : cfg.dims]
        extended, transforms, mix = self.translator(z)
        b, p = points.shape[0], points.shape[1]

        noise, shade_seed = None, None
        if flags.noise or cfg.lattice_shade:
            # one seed per octave; with lattice_shade one more, for the cell shades (they differ
            # with the seed, as the noise does)
            seeds = octave_seeds(seed, cfg.n_octaves + int(cfg.lattice_shade))  # [K(+1)] or [B,K(+1)]
            if cfg.lattice_shade:
                seeds, shade_seed = seeds[..., :cfg.n_octaves], seeds[..., cfg.n_octaves:]  # shade: [1] or [B,1]
        if flags.noise:
            if seeds.dim() == 2:
                seeds = seeds.unsqueeze(1)  # [B,1,K]
            if period is None:
                lattice, wrap = self.lattice_points(points, transforms, anchor), None
            else:
                lattice, wrap = self.periodic_lattice(points, transforms, period)
            nearest, interpolated = noise_features(lattice, seeds, cfg.smooth, wrap, nearest=cfg.nearest_input)
            noise = interpolated  # [B,P,K,3]

        if self.decoder is None:  # perlin / perlinT: octaves mixed by RGB weights, plus a bias
            logits = mix[:, :1, :] + ((noise - 0.5) * mix[:, 1:, :].unsqueeze(1)).sum(dim=2)
        else:
            features = None
            if flags.noise:
                parts = [nearest, interpolated] if cfg.nearest_input else [interpolated]
                # Centred to [-1, 1]: zero-mean inputs suit the ReLU layers' init.
                features = (torch.cat(parts, dim=-1).reshape(b, p, -1) - 0.5) * 2.0
            position = points.to(torch.float32) if flags.position else None
            phase = self.lattice_phases(points, period, shade_seed) if cfg.lattice else None
            logits = self.decoder(features, position, extended, phase)
        return torch.sigmoid(2.0 * logits)  # = (tanh + 1) / 2, the authors' output range


class TextureSpace(nn.Module):
    """Encoder + field: the whole learned texture space."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.code_size, cfg.encoder_width, cfg.colour_blind_encoder)
        self.field = TextureField(cfg)

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        return self.encoder(image)

    def sample(self, points: torch.Tensor, z: torch.Tensor, seed) -> torch.Tensor:
        seed = torch.as_tensor(seed, dtype=torch.int64)
        return self.field(points, z, seed)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def load_checkpoint(path, map_location="cpu") -> tuple[TextureSpace, dict]:
    """Rebuild a model from a checkpoint file alone: {'config', 'model', 'step', ...}."""
    ckpt = torch.load(path, map_location=map_location, weights_only=False)
    model = TextureSpace(ModelConfig(**ckpt["config"]))
    model.load_state_dict(ckpt["model"])
    model.eval()
    return model, ckpt

