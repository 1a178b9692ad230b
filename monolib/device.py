"""Where the networks run: the GPU when there is one (a real Hypersim study), else the CPU.

`MONOLIB_DEVICE=cpu|cuda|auto` (default auto) overrides the choice.
"""
from __future__ import annotations

import functools
import os

import torch


@functools.lru_cache(maxsize=1)
def device() -> torch.device:
    choice = os.environ.get("MONOLIB_DEVICE", "auto").lower()
    if choice not in ("auto", "cpu", "cuda"):
        raise ValueError(f"MONOLIB_DEVICE: expected auto, cpu or cuda, got {choice!r}")
    if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()):
        return torch.device("cuda")
    return torch.device("cpu")
