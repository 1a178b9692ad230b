"""The frames' RGB as the perception stage reads it: through a DataLoader of worker processes (`image_loader`), and
read once for all of the stage's passes (the three networks and the ImageNet features) when it fits in memory
(`FrameRgb`).

Reading a frame's RGB is two HDF5 reads and Hypersim's percentile tonemap (`monolib.data.hypersim.tonemap`), about
15 ms at 256x192 on this project's machine; before `FrameRgb`, each of the four passes read every frame again.
Whichever way a batch is read, it holds the same uint8 values in the same (N, H, W, 3) layout, so every pass
predicts the same, bit for bit (`tests/test_perception.py`).
"""
from __future__ import annotations

from typing import Iterator, Optional

import numpy as np
import torch

from monolib.io import DataFileError

HOLD_BYTES = 2 * 2**30  # at most this much RGB held in memory (quick: 1,944 frames at 256x192, 287 MB)


class FrameImages(torch.utils.data.Dataset):
    """The frames' RGB as a map-style dataset of a `torch.utils.data.DataLoader`: item i is frame i's uint8
    (H, W, 3) image, read where the loader runs it (a worker process, or the main one). It holds the dataset and
    each frame's (setting, scene, index), and reads each image through a new `Frame`, so no image stays in memory."""

    def __init__(self, frames, purpose: str = "the RGB a prediction is made from"):
        self.frames = [(f.dataset, f.setting, f.scene, f.index) for f in frames]
        self.purpose = purpose

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> np.ndarray:
        dataset, setting, scene, index = self.frames[i]
        frame = dataset.frame(setting, scene, index)
        rgb = frame.rgb
        if rgb is None:
            raise DataFileError(f"{frame.files['color']}: file not found ({self.purpose})")
        return rgb


def image_loader(frames, batch: int, workers: int, dev: torch.device,
                 purpose: str = "the RGB a prediction is made from"):
    """A DataLoader of the frames' RGB (`FrameImages`) in their order: (N, H, W, 3) uint8 tensors of `batch`
    frames, read by `workers` processes (0: in the main process; never more than the batches), in pinned memory when
    `dev` is CUDA. A missing colour file is one `DataFileError` naming it and `purpose`."""
    from torch.utils.data import DataLoader

    batches = -(-len(frames) // batch)
    return DataLoader(FrameImages(frames, purpose), batch_size=batch, shuffle=False,
                      num_workers=min(workers, batches), pin_memory=dev.type == "cuda", persistent_workers=False)


class FrameRgb:
    """Where the passes of one stage get their frames' RGB: the first pass reads the frames (through `image_loader`'s
    `workers` processes) and keeps them when they fit in `hold_bytes`; every later pass over those frames takes them
    from memory. Frames that do not fit are read by each pass, as without it."""

    def __init__(self, workers: int, hold_bytes: int = HOLD_BYTES):
        self.workers, self.hold_bytes = int(workers), int(hold_bytes)
        self.held: Optional[np.ndarray] = None   # (N, H, W, 3) uint8
        self.index: dict[str, int] = {}           # frame key -> row of `held`

    def batches(self, frames, batch: int, dev: torch.device,
                purpose: str = "the RGB a prediction is made from") -> Iterator[torch.Tensor]:
        """The frames' RGB as consecutive (N, H, W, 3) uint8 tensors of `batch` frames, in their order."""
        if not frames:
            return
        if not self._hold(frames, dev, purpose):
            yield from image_loader(frames, batch, self.workers, dev, purpose)
            return
        rows = np.array([self.index[f.key] for f in frames])
        for s in range(0, len(frames), batch):
            x = torch.from_numpy(self.held[rows[s : s + batch]])  # (fancy indexing: a new contiguous array)
            yield x.pin_memory() if dev.type == "cuda" else x

    def _hold(self, frames, dev: torch.device, purpose: str) -> bool:
        """Whether every frame of `frames` is held now: read those not held yet when all of them fit."""
        new = list({f.key: f for f in frames if f.key not in self.index}.values())
        if not new:
            return True
        if self.hold_bytes <= 0:
            return False
        first = new[0].rgb
        if first is None:
            raise DataFileError(f"{new[0].files['color']}: file not found ({purpose})")
        size = (0 if self.held is None else self.held.nbytes) + len(new) * first.nbytes
        if size > self.hold_bytes or (self.held is not None and self.held.shape[1:] != first.shape):
            return False
        read = np.concatenate([b.numpy() for b in image_loader(new, 32, self.workers, dev, purpose)])
        self.held = read if self.held is None else np.concatenate([self.held, read])
        base = len(self.index)
        self.index.update({f.key: base + i for i, f in enumerate(new)})
        return True
