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


@pytest.mark.parametrize("choice", [{}, {"label": "embedding", "colour": "standardised", "pooling": "meanmax"},
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
