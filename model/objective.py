"""What a run minimises: VGG statistics (Gram matrices, or sliced Wasserstein) of its
synthesised patches against the exemplars', with the colour, spectrum and lattice-pair terms
(``Objective``).
"""

from __future__ import annotations

import numpy as np
import torch

from model.colour import compressed_moments, transfer_colour_moments
from model.device import autocast
from model.lattice import lattice_contrast
from model.losses import (gram_energy, gram_loss, gram_matrices, sliced_wasserstein_loss, spectrum_loss,
                          spectrum_target, target_grams)
from model.slices import linear_to_srgb, srgb_to_linear
from model.vgg import shared_vgg
from worker.photo import crop_starts as evenly_spread

# A lattice fit's tiles must differ from one another as much as the photo's tiles do. A
# Gram loss cannot tell: it let the phase inputs stamp one blotch into every floor tile of
# a 4-minute fit, where the photo's tiles each have their own marbling. So its patches come
# in pairs a whole number of lattice vectors apart (same seed and depth) and a hinge holds
# their mean squared difference up to the photo's own (``lattice_contrast``).
LATTICE_CONTRAST_WEIGHT = 1.0
# Pairs only where the photo's repeats differ by at least this share of the difference
# between two random pixels of it. The grill's holes repeat almost exactly (0.035; floor
# tiles 0.16, bricks 0.26): there the hinge never has anything to hold up, and pairs would
# only halve the fit's steps (60-s grill fits, seeds 1 and 2: 9.25 and 5.03 with pairs,
# 3.22 and 5.26 without).
LATTICE_PAIRS_MIN = 0.1


def colour_moments(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image mean [N,3] and covariance [N,3,3] of sRGB pixel colours; images [N,3,H,W]."""
    flat = images.flatten(2)  # [N,3,HW]
    mean = flat.mean(dim=2)
    centred = flat - mean.unsqueeze(2)
    return mean, centred @ centred.transpose(1, 2) / flat.shape[2]


# A Gram target for patches smaller than the photo averages crops of their size at up to
# CROP_SPAN // size places along each side (two at least), half a crop apart or more
# (``crop_starts``): 3 x 3 crops of 128 px on a 256-px photo, 4 x 4 on a 1024-px one (the detail
# stage's), 2 x 2 of its probe's 256 px. At most 16 crops of 128 px, the VGG of four 256-px
# photos: a fraction of a second a target.
CROP_SPAN = 512


def crop_starts(length: int, size: int) -> list[int]:
    """Where crops of ``size`` start along a side of ``length``: half a crop apart, first and last
    flush with the edges, at most ``max(2, CROP_SPAN // size)`` of them, evenly spread."""
    count = min(max(2, CROP_SPAN // size), -(-2 * (length - size) // size) + 1)
    return evenly_spread(length, size, count).tolist()


class Objective:
    """VGG statistics of the exemplars, computed once; loss of synthesised patches.

    ``colour_weight`` adds the squared error of the patch's mean colour and colour
    covariance to the exemplar's. The Gram loss alone let a 6000-step space settle on
    wrong hues (olive wood, blue-grey marble) whose deeper-layer statistics matched.

    ``lattice_px`` (a lattice fit, pixels): called with ``pairs=True``, the batch's second
    half are the first half's lattice partners, and their mean squared difference short of
    the photo's ``lattice_contrast`` adds ``LATTICE_CONTRAST_WEIGHT * (1 - ratio)^2``.
    ``self.pairs`` says whether training should use pairs (``LATTICE_PAIRS_MIN``).

    ``spectrum_weight`` (``--spectrum``) adds, per patch, that weight times the exemplar's Gram
    magnitude (``gram_energy``) times its ``spectrum_loss``: the radially averaged luminance
    spectrum against the photo's (off by default: it brought the spectra closer, but grass fits got
    worse in 3 of 3 and lattice fits were hurt; docs/DECISIONS.md, "Tried, not adopted").
    """

    def __init__(self, images: list[np.ndarray], layers: tuple[str, ...], kind: str, colour_weight: float = 0.0,
                 colour_normalise: bool = False, device: torch.device | str = "cpu",
                 lattice_px: tuple[float, float, float, float] | None = None, spectrum_weight: float = 0.0,
                 precision: torch.dtype | None = None):
        self.images, self.spectra = images, {}  # spectra: (k, size) -> band powers
        self.vgg = shared_vgg(layers, device)  # one per device: moving the shared one would move it for all
        self.device = device
        self.precision = precision  # the VGG's autocast dtype (None: float32); targets stay float32
        self.contrasts = [lattice_contrast(image, lattice_px) for image in images] if lattice_px else None
        # whether a lattice fit trains on pairs: every photo's repeats differ enough to charge
        self.pairs = self.contrasts is not None and all(
            contrast >= LATTICE_PAIRS_MIN * 2 * image.reshape(-1, 3).var(axis=0).sum()
            for contrast, image in zip(self.contrasts, images))
        self.kind = kind
        self.colour_weight = 0.0 if colour_normalise else colour_weight
        self.colour_normalise = colour_normalise
        self.targets = []  # per exemplar: whole-photo Grams (gram) or features (swd)
        self.crop_grams = {}  # (k, size) -> mean Gram of the photo's crops of that size (``gram_target``)
        self.colours = []  # per exemplar: (mean [1,3], covariance [1,3,3])
        self.compressed = []  # per exemplar: compressed-colour (mean [1,3], covariance [1,3,3])
        # the spectrum term in proportion to each photo's Gram magnitude (``gram_energy``): it
        # weighs as much against the Gram loss on a bland concrete (energy 0.17) as on gravel (35)
        self.spectrum_weights = []
        with torch.no_grad():
            for image in images:
                tensor = torch.from_numpy(image.transpose(2, 0, 1).copy())[None].to(device)
                feats = self.vgg(tensor)
                grams = gram_matrices(feats)
                self.targets.append(grams if kind == "gram" else feats)
                self.spectrum_weights.append(spectrum_weight * gram_energy(grams) if spectrum_weight else 0.0)
                self.colours.append(colour_moments(tensor))
                self.compressed.append(compressed_moments(srgb_to_linear(tensor)))

    def __call__(self, synth: torch.Tensor, indices: np.ndarray, pairs: bool = False) -> torch.Tensor:
        if self.colour_normalise:
            mean = torch.cat([self.compressed[k][0] for k in indices])
            covariance = torch.cat([self.compressed[k][1] for k in indices])
            synth = linear_to_srgb(transfer_colour_moments(srgb_to_linear(synth), mean, covariance))
        contrast = self.pair_contrast(synth, indices) if pairs else 0.0
        if torch.is_grad_enabled():
            feats = self.features(synth)
        else:  # scoring (the probe), one image at a time: 4 x 256 px on one thread, with two other
            # torch processes running, 4.3 s -> 2.9 s (idle, the same: 1.48 s -> 1.54 s; bench/run.py --only fit)
            parts = [self.features(image[None]) for image in synth]
            feats = {name: torch.cat([part[name] for part in parts]) for name in parts[0]}
        losses = []
        means, covariances = colour_moments(synth)
        spectral = None  # each patch against its own photo's spectrum, the batch at once
        if any(self.spectrum_weights[k] for k in indices):
            spectral = spectrum_loss(synth, torch.stack([self.spectrum(k, synth.shape[-1]) for k in indices]))
        for b, k in enumerate(indices):
            one = {name: value[b : b + 1] for name, value in feats.items()}
            if self.kind == "gram":
                losses.append(gram_loss(one, self.gram_target(k, synth.shape[-1])))
            else:
                losses.append(sliced_wasserstein_loss(one, self.targets[k]))
            if self.spectrum_weights[k]:
                losses[-1] = losses[-1] + self.spectrum_weights[k] * spectral[b]
            if self.colour_weight:
                mean, covariance = self.colours[k]
                colour = (means[b] - mean[0]).square().sum() + (covariances[b] - covariance[0]).square().sum()
                losses[-1] = losses[-1] + self.colour_weight * colour
        return torch.stack(losses).mean() + contrast

    def features(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """VGG features of ``images``, float32 whatever the precision of the convolutions: the
        Gram matrices and their differences from the targets are taken in float32 (bfloat16's
        8-bit mantissa would round a Gram entry by up to 0.4%, the size of a good fit's error)."""
        with autocast(torch.device(self.device), self.precision):
            feats = self.vgg(images)
        return {name: value.float() for name, value in feats.items()}

    def gram_target(self, k: int, size: int) -> dict[str, torch.Tensor]:
        """Exemplar k's Gram target for square patches of ``size`` px: the mean Gram of its
        crops of that size (computed once per size), or its whole Gram where it is no larger.

        A Gram depends on the image's size as well as its content: the convolutions' zero
        padding reaches a larger share of a small image's deep features (relu5_1 of a 128-px
        crop is 8 x 8). The photo's own 128-px crops scored 1.5-8.7x the photo's floor against
        its whole 256-px Gram, 0.4-0.8x against their mean (the 9 validation photos, crops
        every 32 px), so a patch trained toward the whole Gram is pulled off the photo's look.
        """
        image = self.images[k]
        height, width = image.shape[:2]
        if size >= min(height, width):
            return self.targets[k]
        if (k, size) not in self.crop_grams:  # (CROP_SPAN bounds the crops to one 512-px image's pixels)
            crops = np.stack([image[top:top + size, left:left + size] for top in crop_starts(height, size)
                              for left in crop_starts(width, size)]).transpose(0, 3, 1, 2)
            grams = target_grams(torch.from_numpy(np.ascontiguousarray(crops)).to(self.device), self.vgg)
            self.crop_grams[k, size] = {name: g.mean(0, keepdim=True) for name, g in grams.items()}
        return self.crop_grams[k, size]

    def spectrum(self, k: int, size: int) -> torch.Tensor:
        """Exemplar k's band powers for patches of ``size`` (computed once per size)."""
        if (k, size) not in self.spectra:
            self.spectra[k, size] = spectrum_target(self.images[k], size).to(self.device)
        return self.spectra[k, size]

    def pair_contrast(self, synth: torch.Tensor, indices: np.ndarray) -> torch.Tensor:
        """The hinge on lattice partners (first half of the batch against the second)."""
        if self.contrasts is None:
            raise ValueError("pairs=True needs an Objective built with lattice_px")
        half = len(synth) // 2
        difference = (synth[:half] - synth[half:]).square().sum(dim=1).mean(dim=(1, 2))
        target = torch.tensor([self.contrasts[k] for k in indices[:half]], dtype=synth.dtype, device=synth.device)
        return LATTICE_CONTRAST_WEIGHT * torch.relu(1 - difference / target).square().mean()
