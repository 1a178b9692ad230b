"""Where the networks run: the GPU when there is one (a real Hypersim study), else the CPU.

`MONOLIB_DEVICE=cpu|cuda|auto` (default auto) overrides the choice.
"""
from __future__ import annotations

import ctypes
import functools
import os
import platform

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
    ``torch.use_deterministic_algorithms`` on (without its NaN fill of new tensors), cuBLAS with a fixed workspace.
    Returns a CPU generator seeded with `seed` for the caller's own draws.

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
        # Deterministic mode also fills every new uninitialised tensor (`torch.empty`) with NaN, so that a kernel
        # that reads memory it never wrote shows it; none of ours does (results are the same bits without it), and
        # the fills were 7 % of a graph encoder's training (figures/cell_profile.md).
        torch.utils.deterministic.fill_uninitialized_memory = False
    g = torch.Generator()
    g.manual_seed(seed)
    return g


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4


@functools.lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Let this process keep the memory it frees for its next allocations, instead of returning it to the kernel.

    glibc's malloc serves every block above its mmap threshold (128 kB to 32 MB) with a fresh ``mmap`` and unmaps it
    on ``free``; a tensor of a training step or a prediction batch is such a block, so every step the kernel maps
    and zeroes the same megabytes again, which on this project's 2-core machine took more CPU than the arithmetic
    in `imagenet_triplet`'s cells (`make bench-allocator`). With ``mmap`` off for blocks (``M_MMAP_MAX`` 0) and the
    heap never trimmed (``M_TRIM_THRESHOLD`` 2 GiB), freed blocks go back to malloc's own lists and the next step
    reuses them: the process keeps its peak memory, and computes the same numbers (PyTorch aligns every CPU tensor
    to 64 bytes whatever malloc returns). Called by every entry point that computes (the CLI, a notebook's
    `prepare`, a cell). ``MONOLIB_ALLOCATOR=default`` leaves malloc as it is (``keep``, the default, does this).
    Returns whether it took effect (only with glibc: elsewhere the allocator is left as it is)."""
    choice = os.environ.get("MONOLIB_ALLOCATOR", "keep").lower()
    if choice not in ("keep", "default"):
        raise ValueError(f"MONOLIB_ALLOCATOR: expected keep or default, got {choice!r}")
    if choice == "default" or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        return bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    except (OSError, AttributeError):
        return False


def cpu_signature() -> str:
    """The CPU as the numbers move with it: model name, family and model, and the widest vector unit the kernels of
    torch, numpy and Embree pick (AVX-512, AVX2, or neither), e.g. ``AMD EPYC (family 25, model 17, AVX-512)``:
    results that are identical on one machine may differ in their last bits on another signature."""
    import platform

    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the first processor is enough
                key, _, value = line.partition(":")
                fields[key.strip()] = value.strip()
    except OSError:
        return platform.processor() or platform.machine()
    flags = set(fields.get("flags", "").split())
    isa = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    name = fields.get("model name") or platform.processor() or platform.machine()
    return f"{name} (family {fields.get('cpu family', '?')}, model {fields.get('model', '?')}, {isa})"
