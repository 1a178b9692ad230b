"""What every benchmark shares: timing a call, naming the machine, writing a record and its page."""
from __future__ import annotations

import platform
import time
from pathlib import Path

import torch

from monolib import io
from monolib.io import write_json


def seconds_per_call(fn, repeat: int) -> float:
    fn()  # warm-up
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def device_name(dev: torch.device) -> str:
    """The GPU's name, or the CPU's model name (from /proc/cpuinfo where there is one)."""
    if dev.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(dev)}"
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
    except OSError:
        names = []
    return f"cpu: {names[0] if names else platform.processor() or platform.machine()}"


def written(record: dict, out: str | None, table) -> dict:
    """`record`, written to `out` (JSON) and beside it as the Markdown `table(record)` (docs/benchmarks.md)."""
    if out:
        write_json(out, record)
        io.write_text(Path(out).with_suffix(".md"), table(record))
        print(f"written: {out} and {Path(out).with_suffix('.md')}")
    return record
