"""Where a run's steps go and in what arithmetic: the torch device (``resolve_device``) and the
autocast dtype of its VGG loss and decoder (``resolve_precision``, ``autocast``).
"""

from __future__ import annotations

from pathlib import Path

import torch


def resolve_device(name: str) -> torch.device:
    """``auto`` | ``cpu`` | ``cuda`` -> a torch device; ``cuda`` without CUDA is an error."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda: this torch build or machine has no CUDA device (use cpu or auto)")
        # TF32 convolutions and matmuls: the VGG loss dominates a step, and its Gram targets
        # need no more than TF32's 10-bit mantissa. The noise stays exact 32-bit integer
        # arithmetic (int32 in torch), which TF32 does not touch.
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    return torch.device(name)


def resolve_precision(name: str, device: torch.device) -> torch.dtype | None:
    """``auto`` | ``fp32`` | ``bf16`` -> the autocast dtype of a run's VGG and decoder (None: float32).

    ``auto`` picks bfloat16 where the hardware computes it natively: CUDA GPUs that support it,
    and CPUs with AVX-512 BF16 or AMX (oneDNN then runs bf16 convolutions at about twice the
    float32 rate: VGG16 to relu5_1, two 128-px patches, forward and backward, one thread of an
    AMD EPYC: 462-496 ms -> 239-251 ms). Elsewhere oneDNN would emulate bfloat16, no faster
    than float32, so ``auto`` keeps float32 there.
    """
    if name == "fp32":
        return None
    if name == "bf16":
        return torch.bfloat16
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    return torch.bfloat16 if cpu_has_native_bf16() else None


def autocast(device: torch.device, precision: torch.dtype | None) -> torch.autocast:
    """The mixed-precision context of ``resolve_precision``'s dtype on ``device`` (a no-op at None: float32)."""
    return torch.autocast(device.type, dtype=precision or torch.float32, enabled=precision is not None)


def cpu_has_native_bf16() -> bool:
    """Whether this CPU has bfloat16 dot-product instructions (Linux: /proc/cpuinfo flags)."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags
