"""What a texture space is, as data: the variants of the paper's comparison (``VARIANTS``)
and the model's configuration (``ModelConfig``), which checkpoints store as a dict under
``"config"``. No torch here: photo analysis (model/structure/) reads the model's
defaults without the train extra.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Variant:
    noise: bool  # lattice noise input
    transforms: bool  # learned per-octave transforms T_k(z)
    decoder: bool  # MLP decoder (else: octaves mixed by learned RGB weights)
    position: bool  # the point's position is a decoder input


VARIANTS: dict[str, Variant] = {
    "perlin": Variant(noise=True, transforms=False, decoder=False, position=False),
    "perlinT": Variant(noise=True, transforms=True, decoder=False, position=False),
    "mlp": Variant(noise=False, transforms=False, decoder=True, position=True),
    "oursP": Variant(noise=True, transforms=True, decoder=True, position=True),
    "oursNoT": Variant(noise=True, transforms=False, decoder=True, position=False),
    "ours": Variant(noise=True, transforms=True, decoder=True, position=False),
}


@dataclass
class ModelConfig:
    variant: str = "ours"
    dims: int = 3  # 3: solid texture (sliced 2D-to-3D training); 2: planar
    code_size: int = 8
    extended_size: int = 64
    n_octaves: int = 8
    hidden: int = 128
    n_hidden_layers: int = 4
    nearest_input: bool = True  # feed the nearest-cell value as well as the interpolated one
    smooth: bool = False  # smoothstep interpolation weights instead of linear
    octave_rotations: bool = True  # fixed random rotation per octave: hides the lattice axes
    # Each learned per-octave transform is replaced by the isotropic scale of the same volume,
    # |det T|^(1/D) I. Free transforms learned one stretch direction shared by many textures
    # (a 3D diagonal that shows on every slice plane): blobs and streaks leaned 20-30 degrees
    # in every 2D tile. Grain is a fixed input stretch (``grain``), unaffected.
    isotropic_transforms: bool = False
    # A learned linear map of world x and y before the noise, I + W (``TextureField.warp``),
    # for fits of photos whose features lean without being a grain (the validation granite:
    # 1.26x longer along -39 degrees). A fit starts it at the photo's lean
    # (model.structure.photo_lean); a space never has one (isotropic_transforms, above).
    warp: bool = False
    pixels_per_unit: float = 256.0  # exemplar pixels per world unit; octave k has 2^k cells per unit
    encoder_width: int = 32
    # The encoder sees each crop with its colour removed (every channel to zero mean, unit
    # spread), so codes carry structure only: colour is the texture's colour table
    # (model/colour.py), measured from the photo itself. False: the original encoder,
    # which also read the crop's channel means and spreads.
    colour_blind_encoder: bool = False
    exemplar_short_side: int = 256  # working resolution of exemplars (shorter side, pixels)
    # Anisotropic textures (wood, brushed metal): the world axis the grain runs along ("x" or
    # "y"; None: isotropic) and how much longer every noise cell is along it. Value-noise
    # octaves stretched this way are already fibres; a fit then only has to learn colours
    # and the cross-section, which it can in minutes (rotated isotropic octaves never formed
    # grain in 15).
    grain: str | None = None
    grain_stretch: float = 8.0
    # Regular textures (bricks, tile grids, perforated metal): the 2D lattice the photo
    # repeats on, two basis vectors in world units (ax, ay, bx, by) in the xy plane, or
    # None. The decoder then also reads the point's phase on that lattice, sin and cos of
    # 2 pi k u for k = 1..lattice_harmonics per lattice axis. Noise octaves have no period,
    # and a decoder fed only noise drew bricks as irregular patches; with the phases a 60-s
    # fit draws rows of bricks (docs/DECISIONS.md, "Lattice phases and the mean repeat cell").
    lattice: tuple[float, float, float, float] | None = None
    lattice_harmonics: int = 4
    # The photo's mean repeat cell (``lattice_mean_cell``, a fit measures it): its size in
    # samples along the lattice's two axes, or None. The decoder also reads the mean cell's
    # colour at the point's phase: grout lines and bonds drawn exactly where the photo has
    # them, while what differs from one repeat to the next averages away and is left to noise.
    lattice_cell: tuple[int, int] | None = None
    # Each repeat cell its own shade: three values hashed from the cell's index on the
    # lattice and the seed (``model/noise.py: cell_shade``), the same over the whole cell, as
    # more decoder inputs. Phases and the mean cell are the same in every cell, and the noise
    # knows no cell borders, so a fitted tile floor had one shade in every tile where the
    # photo's tiles, bricks and planks each have their own.
    lattice_shade: bool = False

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose from {sorted(VARIANTS)}")
        if self.dims not in (2, 3):
            raise ValueError("dims must be 2 or 3")
        if self.grain not in (None, "x", "y"):
            raise ValueError(f"grain must be None, 'x' or 'y', got {self.grain!r}")
        if self.lattice is not None:
            self.lattice = tuple(float(v) for v in self.lattice)  # (a list, read back from JSON)
            a, b = self.lattice[:2], self.lattice[2:]
            if len(self.lattice) != 4 or not abs(a[0] * b[1] - a[1] * b[0]) > 0:
                raise ValueError(f"lattice must be two independent 2D vectors (ax, ay, bx, by), got {self.lattice!r}")
        if self.lattice_cell is not None:
            self.lattice_cell = tuple(int(v) for v in self.lattice_cell)
            if self.lattice is None or len(self.lattice_cell) != 2 or min(self.lattice_cell) < 2:
                raise ValueError(f"lattice_cell needs a lattice and two sizes >= 2, got {self.lattice_cell!r}")
        if self.lattice_shade and self.lattice is None:
            raise ValueError("lattice_shade needs a lattice")

    @property
    def flags(self) -> Variant:
        return VARIANTS[self.variant]

    def to_dict(self) -> dict:
        return asdict(self)
