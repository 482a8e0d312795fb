"""Plain helpers shared by several test folders (fixtures live in the conftests)."""
from __future__ import annotations

import subprocess
from collections.abc import Callable, Iterable
from pathlib import Path

import pytest

from service import spawn


def wait_ready(base_url: str, procs: Iterable[subprocess.Popen], timeout: float, *,
               output: Callable[[], str] = lambda: "", name: str = "texspace", path: str = "/readyz") -> None:
    """``service.spawn.wait_ready``, failing the test (with the processes' logs) instead of raising."""
    try:
        spawn.wait_ready(base_url, procs, timeout, output=output, name=name, path=path)
    except spawn.NotReady as exc:
        pytest.fail(str(exc))


def export_mask_noise_sampler(path) -> None:
    """The shipped space exported with the noise of samplers made before 2026-11-26 (full
    lowbias32 cell hash, three masked 10-bit fields at their bin centres), for checks that
    such stored samplers keep their own shader. Needs the train extra (torch)."""
    import torch

    import model.noise as noise
    from model.export import export_sampler
    from model.networks import load_checkpoint
    from worker.shader import CHANNEL_BITS, CHANNEL_LOW_BIT, HALF_BIN, MASKS

    masks = torch.tensor(MASKS, dtype=torch.int32)
    # level / 1024 + half a bin, in the unscaled units noise_features multiplies by 2**-32
    scales = torch.tensor([2.0 ** (32 - b - CHANNEL_BITS) for b in CHANNEL_LOW_BIT])

    def mask_fields(h, axis=-1):
        h = h.unsqueeze(axis)
        shape = [1] * h.dim()
        shape[axis] = 3
        fields = torch.bitwise_and(h, masks.reshape(shape)).to(torch.float32)
        return fields * scales.reshape(shape) + HALF_BIN * 2.0**32

    model, _ = load_checkpoint(str(Path(__file__).resolve().parents[1] / "model" / "weights" / "space.pt"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(noise, "cell_mix", noise.mix32)
        patch.setattr(noise, "channel_fields", mask_fields)
        export_sampler(model.field, Path(path))
