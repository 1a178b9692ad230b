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


def seed_everything(seed: int, deterministic: bool = True) -> torch.Generator:
    """Seed every random source a training run draws from, and choose deterministic kernels (as torchvision's
    references do with ``--use-deterministic-algorithms``): cuDNN's autotuner off and cuDNN in deterministic mode,
    ``torch.use_deterministic_algorithms`` on, cuBLAS with a fixed workspace. Returns a CPU generator seeded with
    `seed` for the caller's own draws.

    What this buys: on a CPU, a run is bit-reproducible on the same machine with the same thread count. On a GPU,
    two runs with the same seed on the same GPU model and software give the same weights, except where an operation
    has no deterministic CUDA kernel: PyTorch then warns (``warn_only``: the run goes on rather than stopping), and
    that operation's result may differ in the last bits (bilinear upsampling's backward pass in DeepLabV3 and the
    depth decoder is one). Different GPU models, drivers or library versions are not bit-compatible.
    """
    import random

    import numpy as np

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)  # also seeds every CUDA device
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # cuBLAS's condition for deterministic GEMMs
        torch.backends.cudnn.benchmark = False
        torch.backends.cudnn.deterministic = True
        torch.use_deterministic_algorithms(True, warn_only=True)
    g = torch.Generator()
    g.manual_seed(seed)
    return g
