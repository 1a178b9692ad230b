"""Semantic segmentation: torchvision DeepLabV3 (ASPP head), 40 NYU40 classes, trained from the study's frames.

Label convention: NYU40 id k (1..40) is class k-1; unlabelled pixels (-1) are ignored by the loss and by the
metrics. `predict` returns NYU40 ids again (int16, 1..40), at the input's size.

Also holds the small tensor helpers the depth network shares (image normalisation, resizing, augmentation).
"""
from __future__ import annotations

import contextlib
import copy
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from monolib.data.labels import NUM_CLASSES
from monolib.device import device, seed_everything
from monolib.io import save_torch
from monolib.params import EFFICIENTNET_BACKBONES
from monolib.perception import imagenet
from monolib.progress import tqdm

log = logging.getLogger(__name__)

IGNORE = 255
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


class PretrainedUnavailable(RuntimeError):
    """Pretrained weights were asked for but are not in torch hub's cache (this machine has no internet)."""


# ---- shared tensor helpers ---------------------------------------------------------------------------------

def resize_image(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8 -> (height, width, 3) uint8, bilinear (antialiased when shrinking)."""
    if rgb.shape[:2] == (height, width):
        return rgb
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float()
    t = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    return t[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def resize_nearest(a: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) label or depth map -> (height, width), nearest neighbour (no label mixing, NaN stays local)."""
    if a.shape[:2] == (height, width):
        return a
    rows = np.minimum(((np.arange(height) + 0.5) * a.shape[0] / height).astype(int), a.shape[0] - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * a.shape[1] / width).astype(int), a.shape[1] - 1)
    return a[rows[:, None], cols[None, :]]


def normalise(x_uint8: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) uint8 (or float 0..255) -> ImageNet-normalised float."""
    x = x_uint8.float() / 255.0
    return (x - MEAN.to(x.device)) / STD.to(x.device)  # the constants live on the CPU; the images may not


def as_images(rgb: np.ndarray | Sequence[np.ndarray] | torch.Tensor) -> torch.Tensor:
    """uint8 images -> one (N, H, W, 3) uint8 tensor: an (N, H, W, 3) or (H, W, 3) array, a list of (H, W, 3)
    arrays, or a uint8 tensor of those shapes (a DataLoader's batch; it stays on its device, pinned or not)."""
    if not isinstance(rgb, torch.Tensor):
        arr = np.stack(list(rgb)) if not isinstance(rgb, np.ndarray) else rgb
        if arr.dtype != np.uint8:
            raise ValueError(f"expected uint8 images (N, H, W, 3), got {arr.dtype} {arr.shape}")
        rgb = torch.from_numpy(np.ascontiguousarray(arr))
    x = rgb[None] if rgb.ndim == 3 else rgb
    if x.dtype != torch.uint8 or x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"expected uint8 images (N, H, W, 3), got {x.dtype} {tuple(rgb.shape)}")
    return x


def to_batch(rgb: np.ndarray | Sequence[np.ndarray] | torch.Tensor) -> torch.Tensor:
    """(N, H, W, 3) uint8 array, list of (H, W, 3) or uint8 tensor (`as_images`) -> (N, 3, H, W) uint8 tensor."""
    return as_images(rgb).permute(0, 3, 1, 2).contiguous()


def on_device(images: torch.Tensor, dev: torch.device) -> torch.Tensor:
    """(N, H, W, 3) uint8 images -> (N, 3, H, W) uint8 on `dev`: copied as they are (asynchronously from pinned
    memory), then laid out channels-first there."""
    return images.to(dev, non_blocking=True).permute(0, 3, 1, 2).contiguous()


def precision(dev: torch.device, amp: bool):
    """The context of a forward pass for inference: float16 autocast on CUDA when `amp`, else float32 (the CPU
    always: its predictions stay bit-identical)."""
    if amp and dev.type == "cuda":
        return torch.autocast(device_type="cuda", dtype=torch.float16)
    return contextlib.nullcontext()


def colour_jitter(x: torch.Tensor, gen: torch.Generator, strength: float = 0.3) -> torch.Tensor:
    """Per-image brightness, contrast and saturation jitter on a float 0..255 batch (N, 3, H, W)."""
    n = x.shape[0]

    def factor():
        return (1.0 + (torch.rand(n, 1, 1, 1, generator=gen) * 2 - 1) * strength)

    x = x * factor()
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * factor() + mean
    grey = (0.299 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3])
    x = (x - grey) * factor() + grey
    return x.clamp(0, 255)


@dataclass
class FitOptions:
    """How `fit` runs, beside what it trains: the progress bar, a step limit (tests), a callback per step, the
    resume file and a callback per epoch. Shared by the segmentation and depth trainers."""
    progress: bool = True
    max_steps: Optional[int] = None
    step_callback: Optional[Callable[[int, float], None]] = None
    resume: Optional[Path] = None
    on_epoch: Optional[Callable[[nn.Module, dict], None]] = None


@dataclass
class _FitState:
    """The state of a training run that a resume file holds beside the model, optimiser and schedule."""
    best: float = -np.inf
    best_state: Optional[dict] = None
    step: int = 0
    epoch: int = 0
    spent: float = 0.0


def _load_resume(path: Path, model, opt, sched, gen: torch.Generator, history: dict, spec) -> _FitState:
    state = torch.load(path, map_location="cpu", weights_only=False)
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    sched.load_state_dict(state["scheduler"])
    gen.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    np.random.set_state(state["numpy_rng"])
    history.update(state["history"])
    log.info("%s: resumed after epoch %d of %d (%s)", spec.name, state["epoch"], spec.epochs, path)
    print(f"{spec.name}: resumed after epoch {state['epoch']} of {spec.epochs} ({path})", flush=True)
    return _FitState(state["best"], state["best_state"], state["step"], state["epoch"], state["spent"])


def _save_resume(path: Path, model, opt, sched, gen: torch.Generator, history: dict, st: _FitState) -> None:
    save_torch(path, {"model": model.state_dict(), "optimizer": opt.state_dict(),
                      "scheduler": sched.state_dict(), "generator": gen.get_state(),
                      "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(),
                      "best": st.best, "best_state": st.best_state, "step": st.step, "epoch": st.epoch,
                      "spent": st.spent, "history": {k: v for k, v in history.items()}})


def _train_epoch(model, spec, n_train: int, batch_loss: Callable, opt, sched, gen: torch.Generator, epoch: int,
                 total: int, st: _FitState, options: FitOptions) -> list[float]:
    """One epoch of shuffled batches; the losses of its steps (advances ``st.step``)."""
    steps_per_epoch = max(1, int(np.ceil(n_train / spec.batch_size)))
    model.train()
    order = torch.randperm(n_train, generator=gen)
    losses = []
    bar = tqdm(range(steps_per_epoch), desc=f"{spec.name} epoch {epoch + 1}/{spec.epochs}",
               disable=not options.progress, leave=False)
    for b in bar:
        idx = order[b * spec.batch_size : (b + 1) * spec.batch_size]
        if len(idx) < 2:  # BatchNorm needs two samples
            continue
        loss = batch_loss(model, idx)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if st.step < total:
            sched.step()
        st.step += 1
        losses.append(loss.item())
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        if options.step_callback:
            options.step_callback(st.step, losses[-1])
        if options.max_steps and st.step >= options.max_steps:
            break
    if not losses:  # never cache an untrained network as trained
        raise ValueError(f"{spec.name}: epoch {epoch + 1} ran no training step ({n_train} training frames, "
                         f"batch_size {spec.batch_size}): a step needs a batch of at least 2 frames")
    return losses


def fit(model: nn.Module, spec, n_train: int, batch_loss: Callable, validate: Optional[Callable],
        gen: torch.Generator, history: dict, options: Optional[FitOptions] = None) -> nn.Module:
    """The training loop of both perception networks: AdamW + one-cycle schedule over `spec.epochs` epochs of
    shuffled batches, validation after each epoch, and the weights of the best epoch kept.

    `batch_loss(model, idx)` returns the loss of the training frames `idx`; `validate(model)` returns
    (record entries, selection metric; higher is better, NaN: fall back to minus the training loss). Appends one
    record per epoch to ``history["epochs"]`` and sets ``best_epoch`` and ``train_seconds``.

    ``options.resume``: a file written atomically after every epoch (weights, optimiser, schedule, every random
    state, the history so far, the best epoch's weights); when it exists the run goes on after its last epoch and
    ends with the same weights as an uninterrupted run. ``options.on_epoch(model, record)`` is called after
    validation (in eval mode) and may add entries to the record (the zoo's learning curve on another study's test
    split); its time is not counted in ``train_seconds``. Each record holds ``train_seconds``, the training time up
    to its epoch's end.
    """
    options = options or FitOptions()
    opt = torch.optim.AdamW(model.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    total = spec.epochs * max(1, int(np.ceil(n_train / spec.batch_size)))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=spec.lr, total_steps=total, pct_start=0.15)
    resume = options.resume
    st = (_load_resume(Path(resume), model, opt, sched, gen, history, spec)
          if resume is not None and Path(resume).is_file() else _FitState())
    t_train = time.perf_counter()
    for epoch in range(st.epoch, spec.epochs):
        te = time.perf_counter()
        losses = _train_epoch(model, spec, n_train, batch_loss, opt, sched, gen, epoch, total, st, options)
        rec = {"epoch": epoch + 1, "train_loss": float(np.mean(losses))}
        metric = float("nan")
        if validate is not None:
            entries, metric = validate(model)
            rec.update(entries)
        if not np.isfinite(metric):
            metric = -rec["train_loss"]
        rec["seconds"] = time.perf_counter() - te
        rec["train_seconds"] = st.spent + time.perf_counter() - t_train
        if metric > st.best or st.best_state is None:
            st.best, st.best_state, history["best_epoch"] = metric, copy.deepcopy(model.state_dict()), epoch + 1
        if options.on_epoch is not None:
            t_cb = time.perf_counter()
            model.eval()
            options.on_epoch(model, rec)
            t_train += time.perf_counter() - t_cb  # the callback's time is not training time
        history["epochs"].append(rec)
        log.info("%s epoch %d: %s", spec.name, epoch + 1, rec)
        if resume is not None:
            saved = _FitState(st.best, st.best_state, st.step, epoch + 1, st.spent + time.perf_counter() - t_train)
            _save_resume(resume, model, opt, sched, gen, history, saved)
        if options.max_steps and st.step >= options.max_steps:
            break
    history["train_seconds"] = st.spent + time.perf_counter() - t_train
    model.load_state_dict(st.best_state)
    model.eval()
    return model


# ---- the model ---------------------------------------------------------------------------------------------

_BUILDERS = {
    # backbone: (builder name, full-model weight enum, backbone weight enum)
    "mobilenet_v3_large": ("deeplabv3_mobilenet_v3_large", "DeepLabV3_MobileNet_V3_Large_Weights",
                           "MobileNet_V3_Large_Weights"),
    "resnet50": ("deeplabv3_resnet50", "DeepLabV3_ResNet50_Weights", "ResNet50_Weights"),
    "resnet101": ("deeplabv3_resnet101", "DeepLabV3_ResNet101_Weights", "ResNet101_Weights"),
}


def cached_weights(weights) -> Path:
    """The file torch hub would download `weights` to; `PretrainedUnavailable` when it is not there."""
    filename = weights.url.split("/")[-1]
    path = Path(torch.hub.get_dir()) / "checkpoints" / filename
    if not path.is_file():
        raise PretrainedUnavailable(
            f"pretrained weights {weights} are unavailable offline: this machine cannot download {weights.url}. "
            f"Copy that file to {path} (torch hub's cache), or set `checkpoint:` in the study file to a state "
            f"dict of the model, or set `pretrained: false`."
        )
    return path


class EfficientDeepLabV3(nn.Module):
    """DeepLabV3 (the paper's ASPP head, segmentation-models-pytorch) on an EfficientNet-Lite encoder (timm's
    ``tf_efficientnet_liteN``), output stride 16, 40 classes. `pretrained`: the encoder starts from the ImageNet
    checkpoint its package ships (`monolib.perception.imagenet`). Takes ImageNet-normalised input like torchvision's
    DeepLabV3 (`imagenet.Renormalise` converts it) and returns ``{"out": logits}`` as torchvision's does."""

    def __init__(self, backbone: str, pretrained: bool):
        super().__init__()
        import segmentation_models_pytorch as smp

        self.renormalise = imagenet.Renormalise()
        self.net = smp.DeepLabV3(encoder_name=f"tu-{imagenet.timm_name(backbone)}", encoder_weights=None,
                                 classes=NUM_CLASSES, encoder_output_stride=OUTPUT_STRIDE)
        if pretrained:
            imagenet.load_features(self.net.encoder.model, backbone)

    def forward(self, x):
        return {"out": self.net(self.renormalise(x))}


OUTPUT_STRIDE = 16  # of the EfficientNet DeepLabV3: input sides must be multiples of 32 (smp's check)


def build_model(spec) -> nn.Module:
    """DeepLabV3 with the spec's backbone, 40 classes, no auxiliary classifier; offline unless `pretrained`
    (torchvision backbones: weights in torch hub's cache; EfficientNet-Lite: the ImageNet file of its package)."""
    if spec.backbone in EFFICIENTNET_BACKBONES:
        model = EfficientDeepLabV3(spec.backbone, spec.pretrained)
        model.input_size = (spec.train_height, spec.train_width)
        return model
    import torchvision.models.segmentation as seg

    builder_name, full_enum, _ = _BUILDERS[spec.backbone]
    builder = getattr(seg, builder_name)
    if spec.pretrained:
        weights = getattr(seg, full_enum).DEFAULT
        cached_weights(weights)  # fail fast and clearly instead of trying the network
        model = builder(weights=weights, aux_loss=None)
        model.aux_classifier = None
        last = model.classifier[-1]
        model.classifier[-1] = nn.Conv2d(last.in_channels, NUM_CLASSES, kernel_size=1)
    else:
        model = builder(weights=None, weights_backbone=None, num_classes=NUM_CLASSES, aux_loss=False)
        # torchvision's MobileNetV3 uses BatchNorm momentum 0.01 (tuned for ImageNet-length training): from scratch
        # on a few hundred steps its running statistics would stay at their initial values and evaluation mode
        # would predict one class. PyTorch's default momentum lets them follow the data.
        for m in model.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.momentum = 0.1
    model.input_size = (spec.train_height, spec.train_width)
    return model


def targets_from_semantic(semantic: np.ndarray) -> np.ndarray:
    """NYU40 ids (1..40, -1) -> class indices 0..39, IGNORE elsewhere (uint8)."""
    s = np.asarray(semantic)
    return np.where((s >= 1) & (s <= NUM_CLASSES), s - 1, IGNORE).astype(np.uint8)


# ---- data --------------------------------------------------------------------------------------------------

def load_cache(frames, height: int, width: int, progress: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Read frames once: (N, 3, h, w) uint8 images and (N, h, w) uint8 class targets at training resolution."""
    imgs = np.zeros((len(frames), height, width, 3), np.uint8)
    tgts = np.full((len(frames), height, width), IGNORE, np.uint8)
    for i, f in enumerate(tqdm(frames, desc="read frames", disable=not progress, leave=False)):
        imgs[i] = resize_image(f.rgb, height, width)
        sem = f.semantic
        if sem is not None:
            tgts[i] = targets_from_semantic(resize_nearest(sem, height, width))
    return to_batch(imgs), torch.from_numpy(tgts)


def augment(x: torch.Tensor, y: torch.Tensor, gen: torch.Generator, max_scale: float = 1.5):
    """Flip, random scale-up + crop back to size (labels nearest), colour jitter. x uint8 (N,3,H,W), y (N,H,W)."""
    n, _, h, w = x.shape
    xf = x.float()
    yl = y.long()
    out_x, out_y = [], []
    for i in range(n):
        xi, yi = xf[i : i + 1], yl[i : i + 1]
        if torch.rand(1, generator=gen).item() < 0.5:
            xi, yi = xi.flip(-1), yi.flip(-1)
        s = 1.0 + torch.rand(1, generator=gen).item() * (max_scale - 1.0)
        if s > 1.02:
            hh, ww = int(round(h * s)), int(round(w * s))
            xi = F.interpolate(xi, size=(hh, ww), mode="bilinear", align_corners=False)
            yi = F.interpolate(yi[:, None].float(), size=(hh, ww), mode="nearest")[:, 0].long()
            top = int(torch.randint(0, hh - h + 1, (1,), generator=gen))
            left = int(torch.randint(0, ww - w + 1, (1,), generator=gen))
            xi, yi = xi[..., top : top + h, left : left + w], yi[..., top : top + h, left : left + w]
        out_x.append(xi)
        out_y.append(yi)
    return colour_jitter(torch.cat(out_x), gen), torch.cat(out_y)


# ---- metrics -----------------------------------------------------------------------------------------------

def confusion(gt: np.ndarray, pred: np.ndarray, n: int = NUM_CLASSES) -> np.ndarray:
    """(n, n) int64 confusion matrix [true class, predicted class] over labelled pixels (NYU40 ids 1..n)."""
    gt = np.asarray(gt).ravel().astype(np.int64)
    pred = np.asarray(pred).ravel().astype(np.int64)
    ok = (gt >= 1) & (gt <= n) & (pred >= 1) & (pred <= n)
    return np.bincount((gt[ok] - 1) * n + (pred[ok] - 1), minlength=n * n).reshape(n, n)


def scores(conf: np.ndarray) -> dict:
    """Pixel accuracy and mIoU (over classes present in the ground truth or the prediction)."""
    total = conf.sum()
    tp = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - tp
    present = union > 0
    return {
        "pixel_accuracy": float(tp.sum() / total) if total else float("nan"),
        "miou": float((tp[present] / union[present]).mean()) if present.any() else float("nan"),
        "classes": int(present.sum()),
        "pixels": int(total),
    }


# ---- training and inference --------------------------------------------------------------------------------

def for_inference(model: nn.Module) -> nn.Module:
    """`model` (in place) with its weights in the channels-last memory format, for prediction only: its
    convolutions run about 2.4 times faster on the CPU (42 -> 17 ms a 256x192 frame on 2 threads of the project's
    AMD EPYC; quick's perception stage predicted its 1,944 frames in 71 s instead of 115 s) and gave
    the same class as the default layout for all but 4 of their 95.6 million pixels (a tie of two classes' logits
    rounded the other way). Never during training (another layout may round the gradients otherwise)."""
    return model.to(memory_format=torch.channels_last)


@torch.inference_mode()
def predict(model: nn.Module, rgb, batch_size: int = 8, amp: bool = False) -> np.ndarray:
    """uint8 images (N, H, W, 3), a numpy array or a tensor (`as_images`) -> int16 (N, H, W) NYU40 ids 1..40 (numpy),
    predicted at the model's resolution. `amp`: the forward pass in float16 autocast when the model is on CUDA."""
    was_training = model.training
    model.eval()
    x = as_images(rgb)
    dev = next(model.parameters()).device
    h, w = model.input_size
    out = []
    for i in range(0, len(x), batch_size):
        xb = normalise(on_device(x[i : i + batch_size], dev))
        if xb.shape[-2:] != (h, w):
            xb = F.interpolate(xb, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        with precision(dev, amp):
            logits = model(xb)["out"]
        cls = logits.float().argmax(1, keepdim=True).float()
        if cls.shape[-2:] != x.shape[1:3]:
            cls = F.interpolate(cls, size=tuple(x.shape[1:3]), mode="nearest")
        out.append(cls[:, 0].to(torch.int16).cpu() + 1)
    model.train(was_training)
    return torch.cat(out).numpy()


def evaluate_cached(model: nn.Module, x: torch.Tensor, y: torch.Tensor, batch_size: int = 16) -> dict:
    """Scores on cached tensors (images at the model's resolution)."""
    pred = predict(model, x.permute(0, 2, 3, 1).numpy(), batch_size=batch_size)
    gt = np.where(y.numpy() == IGNORE, -1, y.numpy().astype(np.int16) + 1)
    return scores(confusion(gt, pred))


def train(spec, train_frames, val_frames, seed: int = 0, progress: bool = True,
          max_steps: Optional[int] = None, step_callback: Optional[Callable[[int, float], None]] = None,
          deterministic: bool = True, resume: Optional[Path] = None, on_epoch: Optional[Callable] = None):
    """Train DeepLabV3 with cross-entropy (`fit`, which `resume` and `on_epoch` are passed to); keep the epoch
    with the best validation mIoU.

    Returns (model, history) where history = {"epochs": [{"epoch", "train_loss", "val_pixel_accuracy",
    "val_miou", "seconds"}], "best_epoch", "train_seconds", ...}. `max_steps` stops early (tests).
    """
    gen = seed_everything(seed, deterministic)
    model = build_model(spec).to(device())
    h, w = spec.train_height, spec.train_width
    t0 = time.perf_counter()
    x, y = load_cache(train_frames, h, w, progress)
    xv, yv = load_cache(val_frames, h, w, progress) if val_frames else (None, None)
    history = {"epochs": [], "read_seconds": time.perf_counter() - t0, "train_frames": len(x),
               "val_frames": 0 if xv is None else len(xv)}
    loss_fn = nn.CrossEntropyLoss(ignore_index=IGNORE)

    def batch_loss(model, idx):
        xb, yb = augment(x[idx], y[idx], gen)
        return loss_fn(model(normalise(xb.to(device())))["out"], yb.to(device()))

    def validate(model):
        sc = evaluate_cached(model, xv, yv)
        return {"val_pixel_accuracy": sc["pixel_accuracy"], "val_miou": sc["miou"]}, sc["miou"]

    model = fit(model, spec, len(x), batch_loss, validate if xv is not None else None, gen, history,
                FitOptions(progress, max_steps, step_callback, resume, on_epoch))
    return model, history


def load_model(spec, path) -> nn.Module:
    """A model saved by `save_model` (or a bare state dict given as `checkpoint:`)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    spec_nopre = copy.copy(spec)
    spec_nopre.pretrained = False  # the file holds every weight: never fetch pretrained ones
    model = build_model(spec_nopre)
    model.load_state_dict(state, strict=True)
    model.eval()
    return model.to(device())


def save_model(model: nn.Module, path) -> None:
    save_torch(path, {"state_dict": model.state_dict()})
