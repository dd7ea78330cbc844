"""Arithmetic and storage precision of neural models, decided once per process.

``compute_precision = "auto"`` means bf16 hidden layers where they pay off (CUDA, or a CPU with
native bf16: AVX512-BF16 or AMX) and fp32 elsewhere. The CPU check reads /proc/cpuinfo once per
process. So one model file answers slightly differently on CPUs with and without native bf16
(the output layer always runs in fp32). Measured on two small LSNIF ``lq`` models (plates,
statue(0); 2^16 rays of the training distribution), bf16 vs fp32 inference: hit/miss differs on
0.003-0.006% of the rays, |t| by a median 0.007-0.012% of the box diagonal (max 0.13-0.39%),
normals by a median 0.14-0.21 degrees. Pin ``"fp32"`` (or ``"bf16"``) in the config for answers
that do not depend on the CPU; the training record stores which precision trained a model
(``compute_precision``).
"""

from __future__ import annotations

import functools

import torch

__all__ = ["cpu_has_native_bf16", "compute_dtype", "precision_name", "STORAGE_DTYPES", "STORAGE_BYTES"]

STORAGE_DTYPES = {"fp16": torch.float16, "fp32": torch.float32}
STORAGE_BYTES = {"fp16": 2, "fp32": 4}


@functools.cache
def cpu_has_native_bf16() -> bool:
    """Whether this CPU does bf16 arithmetic natively (AVX512-BF16 or AMX); read once per process."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        return False
    return " avx512_bf16" in flags or " amx_bf16" in flags


def compute_dtype(choice: str, device: torch.device | str) -> torch.dtype:
    """The dtype of hidden-layer arithmetic for a config value ``auto``/``fp32``/``bf16`` on ``device``."""
    if choice == "auto":
        return torch.bfloat16 if (torch.device(device).type == "cuda" or cpu_has_native_bf16()) else torch.float32
    if choice == "bf16":
        return torch.bfloat16
    if choice == "fp32":
        return torch.float32
    raise ValueError(f"compute precision must be auto, fp32 or bf16, got {choice!r}")


def precision_name(dtype: torch.dtype) -> str:
    """``"bf16"`` or ``"fp32"`` (what the training record stores)."""
    return {torch.bfloat16: "bf16", torch.float32: "fp32"}[dtype]
