"""The style error a photo scores against itself (its floor), and syntheses over it.

A Gram error means little on its own: a busy photo (gravel, a grill) scores errors in the
tens against anything, a bland one (concrete) hundredths. Parts of the photo itself do not
score 0 against each other either, so each photo gets its own yardstick:

* floor: the four 128^2 corner crops of the photo at the working size, each scored against
  the mean Gram of the other three; the mean of the four scores. What a crop of the real
  material costs (a perfectly periodic image scores 0);
* a synthesis's error: each of its 128^2 crops (the four quadrants of a 256^2 tile; all
  tiles and seeds) scored against the mean Gram of the photo's four corner crops, averaged;
* ratio = error / floor: a synthesis as good as more of the photo scores about 1;
* the photo off the grid (``off_grid_error``): the photo's own crops at random offsets,
  scored as a synthesis is. Where the photo repeats with a period that divides the crop
  size (a tile grid, 2 x 2 copies of one tile), its four corners all show the pattern at
  one phase and agree far better than crops at other phases do, so its floor is low and
  even the photo itself, cut elsewhere, scores well above 1 (of the 40 validation families
  of docs/eval/quality-large: 0ad's road_tropic_b 7.2, tropic_citytile_a 8.0; the others
  0.49-1.81). A synthesis draws its pattern at any phase: that ratio, not 1, is the most
  it can hope for there.

The score is the quality protocol's style metric, ``model.losses.gram_loss`` (VGG16,
relu1_1..relu5_1, the fixed default layer weights), at the crop size the layer weights
were measured at (128 px at short side 256).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from model.losses import gram_loss, gram_matrices
from model.vgg import GATYS_LAYERS, shared_vgg

CROP = 128
OFF_GRID_CROPS = 8  # crops of the photo at random offsets (``off_grid_error``)


def vgg_features(images: np.ndarray, batch: int = 4) -> dict[str, torch.Tensor]:
    """VGG16 Gatys-layer features of sRGB images (N, H, W, 3) float 0..1 -> {layer: (N, C, h, w)}."""
    vgg = shared_vgg(GATYS_LAYERS)
    parts = []
    with torch.no_grad():
        for start in range(0, len(images), batch):
            chunk = np.asarray(images[start:start + batch], np.float32).transpose(0, 3, 1, 2)
            parts.append(vgg(torch.from_numpy(np.ascontiguousarray(chunk))))
    return {name: torch.cat([p[name] for p in parts]) for name in parts[0]}


def corner_crops(image: np.ndarray, size: int = CROP) -> np.ndarray:
    """(H, W, 3) -> (4, size, size, 3): top-left, top-right, bottom-left, bottom-right crops."""
    height, width = image.shape[:2]
    if height < size or width < size:
        raise ValueError(f"image {height}x{width} is smaller than a {size} px crop")
    return np.stack([image[y:y + size, x:x + size] for y in (0, height - size) for x in (0, width - size)])


def tile_crops(tiles: np.ndarray, size: int = CROP) -> np.ndarray:
    """(N, H, W, 3) -> (N * (H // size) * (W // size), size, size, 3): every whole crop of a
    size x size grid over each tile (the four quadrants of a 256 px tile), tile-major."""
    n, height, width, channels = tiles.shape
    rows, cols = height // size, width // size
    grid = tiles[:, :rows * size, :cols * size].reshape(n, rows, size, cols, size, channels)
    return grid.transpose(0, 1, 3, 2, 4, 5).reshape(n * rows * cols, size, size, channels)


@dataclass(frozen=True)
class PhotoFloor:
    """A photo's yardstick.

    floor : float, mean of ``corner_errors``
    corner_errors : (4,) float64, each corner crop against the mean Gram of the other three
    target : {layer: (1, C, C)} the mean Gram of the four corner crops (what syntheses are scored against)
    """

    floor: float
    corner_errors: np.ndarray
    target: dict[str, torch.Tensor]


def photo_floor(photo: np.ndarray, size: int = CROP) -> PhotoFloor:
    """photo : (H, W, 3) float sRGB 0..1 at the working size -> its floor and corner target."""
    features = vgg_features(corner_crops(photo, size))
    with torch.no_grad():
        grams = gram_matrices(features)  # {layer: (4, C, C)}
        # leave one out: the mean of the other three is (sum - own) / 3
        others = {name: (g.sum(0, keepdim=True) - g) / (len(g) - 1) for name, g in grams.items()}
        errors = gram_loss(features, others, reduction="none").double().numpy()
        target = {name: g.mean(0, keepdim=True) for name, g in grams.items()}
    return PhotoFloor(float(errors.mean()), errors, target)


def crop_errors(tiles: np.ndarray, floor: PhotoFloor, size: int = CROP) -> np.ndarray:
    """tiles : (N, H, W, 3) float sRGB 0..1 -> (N * crops per tile,) float64: each crop's Gram
    error against the photo's mean corner Gram."""
    with torch.no_grad():
        return gram_loss(vgg_features(tile_crops(tiles, size)), floor.target, reduction="none").double().numpy()


def off_grid_error(photo: np.ndarray, floor: PhotoFloor, size: int = CROP, count: int = OFF_GRID_CROPS,
                   seed: int = 0) -> float:
    """The photo's own ``count`` crops at random offsets (fixed by ``seed``), scored against
    its mean corner Gram as a synthesis's crops are: the mean error, what the photo itself
    scores off its corner grid."""
    height, width = photo.shape[:2]
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, [height - size + 1, width - size + 1], size=(count, 2))
    crops = np.stack([photo[y:y + size, x:x + size] for y, x in starts])
    return float(crop_errors(crops, floor, size).mean())  # (each crop is one whole crop of itself)


def style_ratio(error: float, floor: float) -> float | None:
    """error / floor, or None where the photo has no floor to measure against (floor <= 0: a
    perfectly periodic photo, whose every crop is the same) or either figure is not finite."""
    if not (np.isfinite(error) and np.isfinite(floor)) or floor <= 0.0:
        return None
    return float(error) / float(floor)
