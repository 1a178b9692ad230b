"""Monocular depth in the spirit of AdelaiDepth's LeReS: a torchvision ResNet/ResNeXt encoder and LeReS's
multi-scale fusion decoder (FTB/FFM blocks: top-down fusion of the four encoder stages, then an upsampling head).

Two modes share one module structure (`LeReSDepthModel`: ``encoder_modules`` + ``decoder_modules``, the names of
AdelaiDepth's ``DepthModel``):

* ``log`` (trained here): the head predicts log planar depth; `predict` returns ``exp`` of it, metres. Trained with
  a scale-invariant log loss plus a multi-scale gradient-matching term, NaN ground truth masked. The decoder is
  narrower than LeReS's (``decoder_width`` channels instead of 256) so it trains on a CPU.
* ``leres`` (an original AdelaiDepth checkpoint, `load_adelai_checkpoint`): the original architecture with the
  original widths (ResNet50 or ResNeXt101-32x8d encoder, decoder 256/256/256/512). LeReS predicts *relative*
  (affine-invariant) depth; it is turned into metres by one rule, without test-time ground truth:
  ``metres = scale * (raw - min(raw) + 0.01)`` (LeReS's own shift to positive values), with ONE ``scale`` fitted once
  on the training split as the median over training frames of ``median(gt / shifted_raw)`` (`fit_scale`).
"""
from __future__ import annotations

import copy
import logging
import time
from typing import Callable, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from monolib.device import device, seed_everything
from monolib.io import save_torch
from monolib.params import EFFICIENTNET_BACKBONES
from monolib.perception import imagenet
from monolib.perception.segmentation import (
    FitOptions, as_images, cached_weights, colour_jitter, fit, normalise, on_device, precision, resize_image,
    resize_nearest, to_batch
)
from monolib.progress import tqdm

log = logging.getLogger(__name__)

ENCODER_CHANNELS = {
    "resnet18": [64, 128, 256, 512],
    "resnet34": [64, 128, 256, 512],
    "resnet50": [256, 512, 1024, 2048],
    "resnet101": [256, 512, 1024, 2048],
    "resnext50_32x4d": [256, 512, 1024, 2048],
    "resnext101_32x8d": [256, 512, 1024, 2048],
}
LERES_BACKBONES = ("resnet50", "resnext101_32x8d")  # the two released AdelaiDepth LeReS checkpoints
MIN_DEPTH = 0.05


# ---- LeReS decoder blocks (names as in AdelaiDepth lib/network_auxi.py) --------------------------------------

class FTB(nn.Module):
    """Feature transfer block: conv, residual branch (ReLU-conv-BN-ReLU-conv), ReLU."""

    def __init__(self, inchannels: int, midchannels: int = 512):
        super().__init__()
        self.conv1 = nn.Conv2d(inchannels, midchannels, 3, padding=1, stride=1, bias=True)
        self.conv_branch = nn.Sequential(
            nn.ReLU(inplace=True),
            nn.Conv2d(midchannels, midchannels, 3, padding=1, stride=1, bias=True),
            nn.BatchNorm2d(midchannels),
            nn.ReLU(inplace=True),
            nn.Conv2d(midchannels, midchannels, 3, padding=1, stride=1, bias=True),
        )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x):
        x = self.conv1(x)
        x = x + self.conv_branch(x)
        return self.relu(x)


class FFM(nn.Module):
    """Feature fusion: FTB on the lateral (encoder) feature, add the coarser decoder feature, FTB, upsample x2."""

    def __init__(self, inchannels: int, midchannels: int, outchannels: int, upfactor: int = 2):
        super().__init__()
        self.ftb1 = FTB(inchannels, midchannels)
        self.ftb2 = FTB(midchannels, outchannels)
        self.upsample = nn.Upsample(scale_factor=upfactor, mode="bilinear", align_corners=True)

    def forward(self, low_x, high_x):
        x = self.ftb1(low_x)
        if x.shape[-2:] != high_x.shape[-2:]:  # odd sizes (e.g. 96x128 -> 3x4 at 1/32)
            high_x = F.interpolate(high_x, size=x.shape[-2:], mode="bilinear", align_corners=True)
        x = x + high_x
        x = self.ftb2(x)
        return self.upsample(x)


class AO(nn.Module):
    """Output head: conv-BN-ReLU-conv to one channel, upsample x2."""

    def __init__(self, inchannels: int, outchannels: int, upfactor: int = 2):
        super().__init__()
        self.adapt_conv = nn.Sequential(
            nn.Conv2d(inchannels, inchannels // 2, 3, padding=1, stride=1, bias=True),
            nn.BatchNorm2d(inchannels // 2),
            nn.ReLU(inplace=True),
            nn.Conv2d(inchannels // 2, outchannels, 3, padding=1, stride=1, bias=True),
            nn.Upsample(scale_factor=upfactor, mode="bilinear", align_corners=True),
        )

    def forward(self, x):
        return self.adapt_conv(x)


class Decoder(nn.Module):
    """LeReS decoder: FTB on the 1/32 feature, then FFMs at 1/16, 1/8, 1/4, 1/2, then AO to full size."""

    def __init__(self, inchannels=(256, 512, 1024, 2048), midchannels=(256, 256, 256, 512), outchannels: int = 1):
        super().__init__()
        self.inchannels, self.midchannels = list(inchannels), list(midchannels)
        self.conv = FTB(self.inchannels[3], self.midchannels[3])
        self.conv1 = nn.Conv2d(self.midchannels[3], self.midchannels[2], 3, padding=1, stride=1, bias=True)
        self.upsample = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
        self.ffm2 = FFM(self.inchannels[2], self.midchannels[2], self.midchannels[2], 2)
        self.ffm1 = FFM(self.inchannels[1], self.midchannels[1], self.midchannels[1], 2)
        self.ffm0 = FFM(self.inchannels[0], self.midchannels[0], self.midchannels[0], 2)
        self.outconv = AO(self.midchannels[0], outchannels, upfactor=2)

    def forward(self, features):
        x = self.conv1(self.conv(features[3]))
        x = self.upsample(x)
        x = self.ffm2(features[2], x)
        x = self.ffm1(features[1], x)
        x = self.ffm0(features[0], x)
        return self.outconv(x)


class Encoder(nn.Module):
    """A torchvision ResNet/ResNeXt without avgpool/fc, returning the four stage outputs (LeReS's key names)."""

    def __init__(self, backbone: str, weights=None):
        super().__init__()
        import torchvision.models as tvm

        net = getattr(tvm, backbone)(weights=weights)
        self.conv1, self.bn1, self.relu, self.maxpool = net.conv1, net.bn1, net.relu, net.maxpool
        self.layer1, self.layer2, self.layer3, self.layer4 = net.layer1, net.layer2, net.layer3, net.layer4

    def forward(self, x):
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        f1 = self.layer1(x)
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f1, f2, f3, f4]


class EfficientEncoder(nn.Module):
    """An EfficientNet-Lite encoder (timm's ``tf_efficientnet_liteN``, ``features_only``) returning its features at
    1/4, 1/8, 1/16 and 1/32, the four scales of the LeReS decoder. `pretrained`: the ImageNet file of its package
    (`monolib.perception.imagenet`). Takes ImageNet-normalised input (`imagenet.Renormalise` converts it)."""

    def __init__(self, backbone: str, pretrained: bool = False):
        super().__init__()
        import timm

        self.renormalise = imagenet.Renormalise()
        self.model = timm.create_model(imagenet.timm_name(backbone), pretrained=False, features_only=True,
                                       out_indices=(1, 2, 3, 4))
        self.channels = list(self.model.feature_info.channels())
        if pretrained:
            imagenet.load_features(self.model, backbone)

    def forward(self, x):
        return self.model(self.renormalise(x))




class LeReSDepthModel(nn.Module):
    """``encoder_modules`` + ``decoder_modules`` (AdelaiDepth's DepthModel). mode 'log' or 'leres' (see module doc)."""

    def __init__(self, backbone: str, decoder_width: int = 64, mode: str = "log", weights=None,
                 input_size: tuple[int, int] = (192, 256)):
        super().__init__()
        w = decoder_width
        if backbone in EFFICIENTNET_BACKBONES:
            self.encoder_modules = EfficientEncoder(backbone, pretrained=weights == "imagenet")
            channels = self.encoder_modules.channels
        else:
            self.encoder_modules = Encoder(backbone, weights)
            channels = ENCODER_CHANNELS[backbone]
        self.decoder_modules = Decoder(channels, (w, w, w, 2 * w), 1)
        self.mode = mode
        self.input_size = tuple(input_size)
        self.register_buffer("scale", torch.ones(()), persistent=False)  # leres mode: metres per relative unit

    def forward(self, x):
        """Normalised images (N, 3, H, W) -> (N, 1, H, W) raw output (log metres in 'log' mode)."""
        out = self.decoder_modules(self.encoder_modules(x))
        if out.shape[-2:] != x.shape[-2:]:
            out = F.interpolate(out, size=x.shape[-2:], mode="bilinear", align_corners=False)
        return out


def build_model(spec) -> LeReSDepthModel:
    """The trainable model for a DepthSpec (offline; pretrained encoder weights only when cached locally)."""
    weights = None
    if spec.pretrained and spec.backbone in EFFICIENTNET_BACKBONES:
        weights = "imagenet"  # the ImageNet file of the encoder's package (monolib.perception.imagenet)
    elif spec.pretrained:
        import torchvision.models as tvm

        enum_name = {"resnet18": "ResNet18_Weights", "resnet34": "ResNet34_Weights", "resnet50": "ResNet50_Weights",
                     "resnet101": "ResNet101_Weights", "resnext50_32x4d": "ResNeXt50_32X4D_Weights",
                     "resnext101_32x8d": "ResNeXt101_32X8D_Weights"}[spec.backbone]
        weights = getattr(tvm, enum_name).DEFAULT
        cached_weights(weights)
    model = LeReSDepthModel(spec.backbone, getattr(spec, "decoder_width", 64), "log", weights,
                            (spec.train_height, spec.train_width))
    with torch.no_grad():  # start near a typical indoor depth (exp(1) ~ 2.7 m)
        model.decoder_modules.outconv.adapt_conv[3].bias.fill_(1.0)
    return model


# ---- the original AdelaiDepth checkpoint ------------------------------------------------------------------

def build_leres(backbone: str, input_size: tuple[int, int] = (448, 448)) -> LeReSDepthModel:
    """AdelaiDepth's LeReS DepthModel structure with its original widths (decoder 256/256/256/512)."""
    if backbone not in LERES_BACKBONES:
        raise ValueError(f"AdelaiDepth released LeReS checkpoints for {LERES_BACKBONES}; got backbone {backbone!r}")
    return LeReSDepthModel(backbone, 256, "leres", None, input_size)


def load_adelai_checkpoint(model: LeReSDepthModel, path) -> LeReSDepthModel:
    """Load an original AdelaiDepth LeReS checkpoint (``res50.pth`` / ``res101.pth``) strictly.

    The file is a dict whose ``depth_model`` entry is the state dict of LeReS's ``RelDepthModel``
    (``LeReS/Minist_Test/lib/multi_depth_model_woauxi.py``: ``RelDepthModel.depth_model = DepthModel``, whose
    ``encoder_modules`` is ``network_auxi.DepthNet`` holding the ResNet as ``.encoder``). Its keys are therefore
    ``[module.]depth_model.encoder_modules.encoder.<ResNet keys>`` and ``[module.]depth_model.decoder_modules.*``
    (406 tensors for ResNet50, 712 for ResNeXt101-32x8d, ``num_batches_tracked`` included). As in AdelaiDepth's
    ``strip_prefix_if_present``, ``module.`` is stripped only when every key has it. The keys under ``depth_model.``
    are mapped onto `model` (``encoder_modules.encoder.X`` -> ``encoder_modules.X``, as the project's encoder holds
    the ResNet's layers directly; the project's own layout ``encoder_modules.X`` is accepted too) and loaded with
    ``strict=True``; `model` must be `build_leres(backbone)` (ResNet50 -> ``res50.pth``, ResNeXt101-32x8d ->
    ``res101.pth``). Keys outside ``depth_model.`` count as unexpected (AdelaiDepth loads the entry strictly).
    Missing ``num_batches_tracked`` buffers (checkpoints from PyTorch < 0.4.1) are tolerated, as PyTorch's own
    strict load does for them. Any mismatch raises ValueError naming the file with the numbers of missing,
    unexpected and wrongly shaped keys (and the first few names). The shift/focal models are not used.
    The result predicts relative depth; call `fit_scale` on training frames before using it in metres.
    """
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is reported as a bad checkpoint
        raise ValueError(f"{path}: cannot be read as a torch checkpoint: {exc}") from exc
    state = ckpt.get("depth_model", ckpt) if isinstance(ckpt, dict) else ckpt
    if not isinstance(state, dict) or not state:
        raise ValueError(f"{path}: not an AdelaiDepth checkpoint (expected a dict with a 'depth_model' state dict)")
    if all(isinstance(k, str) and k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    target = model.state_dict()
    sub, unexpected = {}, []
    for k, v in state.items():
        if not (isinstance(k, str) and k.startswith("depth_model.")):
            unexpected.append(str(k))
            continue
        name = k[len("depth_model."):]
        if name.startswith("encoder_modules.encoder.") and name not in target:
            name = "encoder_modules." + name[len("encoder_modules.encoder."):]
        if name in sub or name not in target:
            unexpected.append(k)
            continue
        sub[name] = v
    if not sub:
        raise ValueError(f"{path}: no keys under 'depth_model.' (found e.g. {list(state)[:3]})")
    missing = [k for k in target if k not in sub and not k.endswith(".num_batches_tracked")]
    wrong = [f"{k} {tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__} vs {tuple(target[k].shape)}"
             for k, v in sub.items() if not isinstance(v, torch.Tensor) or v.shape != target[k].shape]

    def few(names, what):
        return f"{len(names)} {what}" + (f" (e.g. {', '.join(names[:4])})" if names else "")

    if missing or unexpected or wrong:
        raise ValueError(f"{path}: does not match the LeReS architecture built here: {few(missing, 'missing keys')}; "
                         f"{few(unexpected, 'unexpected keys')}; {few(wrong, 'keys of the wrong shape')} "
                         f"({len(state)} keys in the file, {len(target)} in the model)")
    try:
        model.load_state_dict(sub, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path}: does not match the LeReS architecture built here: {exc}") from exc
    model.mode = "leres"
    model.eval()
    return model


def fit_scale(model: LeReSDepthModel, frames, batch_size: int = 4) -> float:
    """The one metric rule for relative depth: median over training frames of median(gt / shifted prediction)."""
    model.scale.fill_(1.0)
    ratios = []
    for i in range(0, len(frames), batch_size):
        chunk = frames[i : i + batch_size]
        pred = predict(model, np.stack([f.rgb for f in chunk]), batch_size=batch_size)
        for f, p in zip(chunk, pred):
            gt = f.depth
            ok = np.isfinite(gt) & (gt > 0) & np.isfinite(p) & (p > 0)
            if ok.any():
                ratios.append(float(np.median(gt[ok] / p[ok])))
    s = float(np.median(ratios)) if ratios else 1.0
    model.scale.fill_(s)
    return s


# ---- loss --------------------------------------------------------------------------------------------------

def _grad_loss(d: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Mean |gradient| of the log-depth error d where both neighbours are valid. d, m: (N, H, W)."""
    mx = m[:, :, 1:] * m[:, :, :-1]
    my = m[:, 1:, :] * m[:, :-1, :]
    gx = (d[:, :, 1:] - d[:, :, :-1]).abs() * mx
    gy = (d[:, 1:, :] - d[:, :-1, :]).abs() * my
    return (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp(min=1.0)


def depth_loss(log_pred: torch.Tensor, gt: torch.Tensor, lam: float = 0.5, grad_weight: float = 0.5,
               scales: int = 4) -> torch.Tensor:
    """Scale-invariant log loss (Eigen et al., lambda < 1 keeps the absolute scale) + multi-scale gradient matching.

    log_pred: (N, H, W) log metres; gt: (N, H, W) metres, NaN / <= 0 invalid (masked).
    """
    m = torch.isfinite(gt) & (gt > 0)
    mf = m.float()
    d = (log_pred - torch.log(torch.where(m, gt, torch.ones_like(gt)))) * mf
    n = mf.sum(dim=(1, 2))
    has = (n > 0).to(log_pred.dtype)  # frames with a valid pixel; no branch on the data (any device, `meta` too)
    mean_d = d.sum(dim=(1, 2)) / n.clamp(min=1)
    mean_d2 = (d * d).sum(dim=(1, 2)) / n.clamp(min=1)
    si = ((mean_d2 - lam * mean_d * mean_d) * has).sum() / has.sum().clamp(min=1)  # 0 when no frame has one
    g = 0.0
    dd, mm = d, mf
    for s in range(scales):
        if s:
            dd, mm = dd[:, ::2, ::2], mm[:, ::2, ::2]
        g = g + _grad_loss(dd, mm)
    return si + grad_weight * g / scales


# ---- data, metrics, training, inference ----------------------------------------------------------------------

def load_cache(frames, height: int, width: int, progress: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3, h, w) uint8 images and (N, h, w) float32 planar depth (nearest resize, NaN kept)."""
    imgs = np.zeros((len(frames), height, width, 3), np.uint8)
    deps = np.full((len(frames), height, width), np.nan, np.float32)
    for i, f in enumerate(tqdm(frames, desc="read frames", disable=not progress, leave=False)):
        imgs[i] = resize_image(f.rgb, height, width)
        deps[i] = resize_nearest(f.depth, height, width)
    return to_batch(imgs), torch.from_numpy(deps)


def depth_errors(pred: np.ndarray, gt: np.ndarray) -> Optional[dict]:
    """AbsRel, RMSE, delta<1.25, median(pred/gt) over valid GT pixels of one frame; None when none is valid."""
    ok = np.isfinite(gt) & (gt > 0) & np.isfinite(pred)
    if not ok.any():
        return None
    p = np.maximum(pred[ok].astype(np.float64), 1e-6)
    g = gt[ok].astype(np.float64)
    ratio = np.maximum(p / g, g / p)
    return {"abs_rel": float(np.mean(np.abs(p - g) / g)), "rmse": float(np.sqrt(np.mean((p - g) ** 2))),
            "delta1": float(np.mean(ratio < 1.25)), "median_ratio": float(np.median(p / g)), "pixels": int(ok.sum())}


def summarise(per_frame: list[Optional[dict]]) -> dict:
    """Mean over frames with valid pixels (median of median ratios); frames without any are skipped."""
    rows = [r for r in per_frame if r is not None]
    if not rows:
        return {"abs_rel": float("nan"), "rmse": float("nan"), "delta1": float("nan"), "median_ratio": float("nan"),
                "frames": 0}
    out = {k: float(np.mean([r[k] for r in rows])) for k in ("abs_rel", "rmse", "delta1")}
    out["median_ratio"] = float(np.median([r["median_ratio"] for r in rows]))
    out["frames"] = len(rows)
    return out


@torch.inference_mode()
def predict(model: LeReSDepthModel, rgb, batch_size: int = 8, amp: bool = False) -> np.ndarray:
    """uint8 images (N, H, W, 3), a numpy array or a tensor (`segmentation.as_images`) -> float32 (N, H, W) planar
    depth in metres (numpy; model resolution, resized back). `amp`: the forward pass in float16 autocast when the
    model is on CUDA; its output is cast to float32 before the exp."""
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
            raw = model(xb)
        raw = raw.float()
        if raw.shape[-2:] != x.shape[1:3]:
            raw = F.interpolate(raw, size=tuple(x.shape[1:3]), mode="bilinear", align_corners=False)
        raw = raw[:, 0]
        if model.mode == "log":
            d = torch.exp(raw.clamp(max=6.0))
        else:
            d = (raw - raw.amin(dim=(1, 2), keepdim=True) + 0.01) * model.scale
        out.append(d.float().cpu())
    model.train(was_training)
    return torch.cat(out).numpy()


def evaluate_cached(model, x: torch.Tensor, d: torch.Tensor, batch_size: int = 16) -> dict:
    pred = predict(model, x.permute(0, 2, 3, 1).numpy(), batch_size=batch_size)
    return summarise([depth_errors(p, g) for p, g in zip(pred, d.numpy())])


def train(spec, train_frames, val_frames, seed: int = 0, progress: bool = True,
          max_steps: Optional[int] = None, step_callback: Optional[Callable[[int, float], None]] = None,
          deterministic: bool = True, resume=None, on_epoch: Optional[Callable] = None):
    """Train with `depth_loss` (`segmentation.fit`, which `resume` and `on_epoch` are passed to); keep the epoch
    with the best validation delta<1.25.
    Returns (model, history)."""
    gen = seed_everything(seed, deterministic)
    model = build_model(spec).to(device())
    h, w = spec.train_height, spec.train_width
    t0 = time.perf_counter()
    x, d = load_cache(train_frames, h, w, progress)
    xv, dv = load_cache(val_frames, h, w, progress) if val_frames else (None, None)
    history = {"epochs": [], "read_seconds": time.perf_counter() - t0, "train_frames": len(x),
               "val_frames": 0 if xv is None else len(xv)}

    def batch_loss(model, idx):
        xb, db = x[idx].float(), d[idx]
        flip = torch.rand(len(idx), generator=gen) < 0.5
        xb = torch.where(flip[:, None, None, None], xb.flip(-1), xb)
        db = torch.where(flip[:, None, None], db.flip(-1), db)
        xb = colour_jitter(xb, gen)
        return depth_loss(model(normalise(xb.to(device())))[:, 0], db.to(device()))

    def validate(model):
        sc = evaluate_cached(model, xv, dv)
        return {f"val_{k}": v for k, v in sc.items() if k != "frames"}, sc["delta1"]

    model = fit(model, spec, len(x), batch_loss, validate if xv is not None else None, gen, history,
                FitOptions(progress, max_steps, step_callback, resume, on_epoch))
    return model, history


def save_model(model: LeReSDepthModel, path) -> None:
    save_torch(path, {"state_dict": model.state_dict(), "mode": model.mode, "scale": float(model.scale),
                      "input_size": list(model.input_size)})


def load_model(spec, path) -> LeReSDepthModel:
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if blob.get("mode") == "leres":
        model = build_leres(spec.backbone, tuple(blob["input_size"]))
    else:
        s = copy.copy(spec)
        s.pretrained = False
        model = build_model(s)
    model.load_state_dict(blob["state_dict"], strict=True)
    model.mode = blob.get("mode", "log")
    model.scale.fill_(float(blob.get("scale", 1.0)))
    model.input_size = tuple(blob.get("input_size", model.input_size))
    model.eval()
    return model.to(device())
