"""One device everywhere, checked without a GPU: every network's forward pass and loss run on tensors of the `meta`
device, where any tensor left on the CPU (a constant built at import, a mask made without `device=`) is an error.

(A branch on the data cannot run on `meta`: the losses are written without one, so that the tests call them whole.)
"""
import types

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch, Data

from monolib.data.labels import NUM_CLASSES
from monolib.params import GCNSpec
from monolib.perception import depth, segmentation
from monolib.retrieval import baselines, gcn

META = torch.device("meta")


def images(n=2, h=48, w=64):
    return torch.zeros((n, 3, h, w), dtype=torch.uint8, device=META)


def test_normalise_keeps_the_images_device():
    out = segmentation.normalise(images())
    assert out.device == META and out.dtype == torch.float32


def test_deeplab_forward_and_loss_on_one_device():
    spec = types.SimpleNamespace(backbone="mobilenet_v3_large", pretrained=False, train_height=48, train_width=64)
    model = segmentation.build_model(spec).to(META)
    out = model(segmentation.normalise(images()))["out"]
    target = torch.zeros((2, 48, 64), dtype=torch.long, device=META)
    loss = torch.nn.CrossEntropyLoss(ignore_index=segmentation.IGNORE)(out, target)
    assert out.device == META and out.shape == (2, NUM_CLASSES, 48, 64) and loss.device == META


@pytest.mark.parametrize("backbone", ["resnet18", "resnet34"])
def test_depth_forward_and_loss_terms_on_one_device(backbone):
    spec = types.SimpleNamespace(backbone=backbone, pretrained=False, train_height=48, train_width=64, decoder_width=16)
    model = depth.build_model(spec).to(META)
    log_pred = model(segmentation.normalise(images()))[:, 0]
    gt = torch.ones((2, 48, 64), device=META)
    loss = depth.depth_loss(log_pred, gt)  # the loss itself: no branch on the data, so it runs on `meta`
    assert log_pred.device == META and log_pred.shape == (2, 48, 64) and loss.device == META and loss.ndim == 0


@pytest.mark.parametrize("choice", [{}, {"label_encoding": "embedding", "colour_encoding": "standardised",
                                         "pooling": "meanmax"},
                                    {"conv": "gine"}, {"edge_weight": "inverse"}])
def test_graph_encoder_forward_and_losses_on_one_device(choice):
    import torch.fx.experimental._config as fx_config

    # GCNConv's self-loops call nonzero(), whose size depends on data: let meta assume every element is non-zero
    with fx_config.patch(meta_nonzero_assume_all_nonzero=True):
        graph_encoder_on_meta(choice)


def graph_encoder_on_meta(choice):
    spec = GCNSpec(**choice)
    model = gcn.GraphEncoder(spec)
    graphs = []
    for i in range(4):
        x = torch.tensor([[1.0, 0.2, 0.3, 0.4], [2.0, 0.5, 0.5, 0.5], [5.0, 0.1, 0.9, 0.3]])
        graphs.append(Data(x=x, edge_index=torch.tensor([[0, 1], [1, 0]]), edge_attr=torch.tensor([[1.0], [1.0]]),
                           num_nodes=3))
    batch = Batch.from_data_list(graphs).to(META)
    model.to(META)
    z = model(batch)
    loss = torch.nn.TripletMarginLoss(margin=spec.margin)(z[:1], z[1:2], z[2:3])
    codes = torch.as_tensor(np.array([0, 0, 1, 1]), device=z.device)
    same = codes[:, None] == codes[None, :]
    eye = torch.eye(len(z), dtype=torch.bool, device=z.device)
    hardest = torch.cdist(z, z).masked_fill(~same | eye, float("-inf")).amax(dim=1)
    assert z.device == META and loss.device == META and hardest.device == META


def test_image_encoder_forward_on_one_device():
    model = baselines.ImageEncoder().to(META)
    z = model(baselines._normalise(images(3, *baselines.CNN_SIZE)))
    assert z.device == META and z.shape[0] == 3


def test_a_cpu_constant_on_the_path_fails_here(monkeypatch):
    """The check itself can fail: the constants moved back to the CPU (the bug of the GPU run) are caught."""
    def normalise_on_cpu(x_uint8):
        x = x_uint8.float() / 255.0
        return (x - segmentation.MEAN) / segmentation.STD

    monkeypatch.setattr(segmentation, "normalise", normalise_on_cpu)
    with pytest.raises((RuntimeError, NotImplementedError)):
        segmentation.normalise(images())


# ---- the allocator ------------------------------------------------------------------------------------------------

STEPS = """
import hashlib, resource, sys
import torch
from monolib.device import keep_freed_memory

assert keep_freed_memory() == (sys.argv[1] == "keep")
torch.set_num_threads(1)
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Conv2d(3, 32, 3, padding=1), torch.nn.BatchNorm2d(32), torch.nn.ReLU(),
                          torch.nn.Conv2d(32, 32, 1))
opt = torch.optim.SGD(net.parameters(), lr=0.01)
x = torch.randn(8, 3, 192, 256)  # activations of 50 MB: above glibc's largest mmap threshold (32 MB)

def step():
    opt.zero_grad()
    net(x).square().mean().backward()
    opt.step()

step()
step()
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    step()
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
digest = hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in net.parameters())).hexdigest()
print(faults, digest)
"""


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc's mallopt only")
@pytest.mark.slow
def test_freed_tensors_are_reused_and_compute_the_same():
    """`keep_freed_memory`: once two training steps of a small conv net have run, the next three fault in fewer
    pages than one step does without it (without it every step maps its activations again; with it none on a quiet
    machine, and some while other tests run beside it, as `make test` runs them), and they end with the same
    weights, bit for bit. ``MONOLIB_ALLOCATOR=default`` leaves malloc as it is."""
    import os
    import subprocess
    import sys

    out = {mode: subprocess.run([sys.executable, "-c", STEPS, mode], capture_output=True, text=True, check=True,
                                env={**os.environ, "MONOLIB_ALLOCATOR": mode}).stdout.split()
           for mode in ("default", "keep")}
    faults = {mode: int(v[0]) for mode, v in out.items()}
    assert 3 * faults["keep"] < faults["default"], faults
    assert out["default"][1] == out["keep"][1]


def test_an_unknown_allocator_choice_is_one_clear_error(monkeypatch):
    from monolib import device

    monkeypatch.setenv("MONOLIB_ALLOCATOR", "jemalloc")
    device.keep_freed_memory.cache_clear()
    try:
        with pytest.raises(ValueError, match="MONOLIB_ALLOCATOR: expected keep or default, got 'jemalloc'"):
            device.keep_freed_memory()
    finally:
        device.keep_freed_memory.cache_clear()
