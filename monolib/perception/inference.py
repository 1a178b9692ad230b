"""The perception networks prepared once for a localizer's queries (`prepare_network`): each BatchNorm after a
convolution folded into it, the network kept in evaluation mode (`QueryNetwork`). The same functions up to float
rounding, faster on one CPU thread; the study's stages load the networks as they are (`monolib.localize` alone
prepares them, for the images a user brings)."""
from __future__ import annotations

import torch

FOLD_BATCHNORM = True  # `prepare_network`'s default: each BatchNorm after a convolution folded into it


class QueryNetwork(torch.nn.Module):
    """A perception network prepared for the localizer's queries (`prepare_network`), read by the stages' own
    `segmentation.predict` and `depth.predict` like the network it wraps: the same ``input_size``, and a depth
    network's ``mode`` and ``scale``. It stays in evaluation mode: its `train` sets its own flag only, so the
    ``eval()`` and ``train()`` that each `predict` call makes do not walk the network's few hundred modules (about
    8 ms a call on one CPU thread of a busy machine)."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net.eval()
        self.input_size = net.input_size
        if hasattr(net, "mode"):
            self.mode = net.mode

    @property
    def scale(self) -> torch.Tensor:
        return self.net.scale

    def train(self, mode: bool = True) -> "QueryNetwork":
        self.training = mode  # (the network it wraps stays in evaluation mode)
        return self

    def forward(self, x):
        return self.net(x)


def conv_batchnorm_pairs(net: torch.nn.Module) -> list[tuple[str, str]]:
    """(convolution, BatchNorm) module names of `net` (in evaluation mode) where the BatchNorm's input is the
    convolution's output and that output is the input of no other module, found by one forward pass of zeros at
    ``net.input_size`` on the network's device. Plain `nn.BatchNorm2d`, and timm's `BatchNormAct2d`; the forward
    pass sees the data flow whatever the modules' names or nesting. A use of the output by a function outside a
    module (``conv(x) + x``) is not seen: the networks the localizer loads have none, and the tests compare the
    folded networks' outputs with the plain ones'."""
    names = {m: n for n, m in net.named_modules()}
    seen: list[torch.Tensor] = []  # every tensor looked at, kept alive: no id is reused during the pass
    made: dict[int, torch.nn.Module] = {}
    readers: dict[int, list[torch.nn.Module]] = {}

    def conv_hook(m, args, out):
        seen.append(out)
        made[id(out)] = m

    def read_hook(m, args):
        for a in args:
            if isinstance(a, torch.Tensor):
                seen.append(a)
                readers.setdefault(id(a), []).append(m)

    leaves = [m for m in net.modules() if not list(m.children()) or isinstance(m, torch.nn.BatchNorm2d)]
    hooks = [m.register_forward_pre_hook(read_hook) for m in leaves]
    hooks += [m.register_forward_hook(conv_hook) for m in leaves if type(m) in _conv_types()]
    p = next(net.parameters())
    try:
        with torch.inference_mode():
            net(torch.zeros(1, 3, *net.input_size, device=p.device, dtype=p.dtype))
    finally:
        for h in hooks:
            h.remove()
    pairs = []
    for key, conv in made.items():
        users = readers.get(key, [])
        if len(users) == 1 and isinstance(users[0], torch.nn.BatchNorm2d) and _foldable(conv, users[0]):
            pairs.append((names[conv], names[users[0]]))
    return pairs


def _conv_types() -> tuple[type, ...]:
    """The convolutions a BatchNorm is folded into: their forward reads only ``weight`` and ``bias`` (timm's
    `Conv2dSame`, TensorFlow's "same" padding of the EfficientNet-Lite encoders, pads the input first)."""
    from timm.layers import Conv2dSame  # deferred: timm is imported only with a network to prepare

    return (torch.nn.Conv2d, Conv2dSame)


def _foldable(conv: torch.nn.Conv2d, bn: torch.nn.BatchNorm2d) -> bool:
    from timm.layers import BatchNormAct2d

    return (type(bn) in (torch.nn.BatchNorm2d, BatchNormAct2d) and bn.track_running_stats
            and bn.running_mean is not None and bn.num_features == conv.out_channels)


def fold_batchnorm(net: torch.nn.Module) -> int:
    """Fold each BatchNorm that follows a convolution (`conv_batchnorm_pairs`) into the convolution's weight and
    bias (evaluation mode: the running statistics), in place: the BatchNorm becomes its activation (timm's
    `BatchNormAct2d`) or nothing. The same function up to float rounding; returns the number folded."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    pairs = conv_batchnorm_pairs(net)
    for conv_name, bn_name in pairs:
        conv, bn = net.get_submodule(conv_name), net.get_submodule(bn_name)
        fused = fuse_conv_bn_eval(conv, bn)
        weight = torch.empty_strided(conv.weight.shape, conv.weight.stride(), dtype=conv.weight.dtype,
                                     device=conv.weight.device)  # the layout the network was given
        fused.weight = torch.nn.Parameter(weight.copy_(fused.weight.detach()), requires_grad=False)
        net.set_submodule(conv_name, fused)
        after = [m for m in (getattr(bn, "drop", None), getattr(bn, "act", None))
                 if m is not None and not isinstance(m, torch.nn.Identity)]
        net.set_submodule(bn_name, torch.nn.Sequential(*after) if after else torch.nn.Identity())
    return len(pairs)


def prepare_network(net: torch.nn.Module, fold: bool = FOLD_BATCHNORM) -> QueryNetwork:
    """A loaded perception network (`segmentation.for_inference`'s or `depth.load_model`'s, in evaluation mode)
    prepared once for queries: with `fold`, its BatchNorms folded into the convolutions before them
    (`fold_batchnorm`), in a `QueryNetwork`: faster on one CPU thread (docs/benchmarks.md, what a localizer
    costs), the outputs equal up to float rounding (tests/test_localize_prepared.py). Works on any device: the
    folded weights stay where the network is, in its memory format."""
    net = net.eval()
    if fold:
        fold_batchnorm(net)
    return QueryNetwork(net)
