"""The graph encoder (paper section 2, "Graph Neural Network"): GCN + triplet loss, trained per setting.

Encoder: 5 GCNConv layers of 128 channels (ReLU between), a linear layer to 64, global max pooling over nodes.
Triplets (paper): every training graph is an anchor once per epoch; its positive is a random other graph of the
same setting, its negative a random graph of another setting; drawn afresh each epoch from the seed.
"""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn
from torch_geometric.data import Batch, Data
from torch_geometric.loader import DataLoader
from torch_geometric.nn import GCNConv, global_max_pool

from monolib.graph import NODE_FEATURES
from monolib.params import GCNSpec

log = logging.getLogger(__name__)


class GraphEncoder(nn.Module):
    def __init__(self, spec: GCNSpec, in_channels: int = NODE_FEATURES):
        super().__init__()
        dims = [in_channels] + [spec.hidden] * spec.layers
        self.convs = nn.ModuleList(GCNConv(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.lin = nn.Linear(spec.hidden, spec.out)
        self.out_channels = spec.out

    def forward(self, batch: Batch) -> torch.Tensor:
        h = batch.x
        for i, conv in enumerate(self.convs):
            h = conv(h, batch.edge_index)
            if i < len(self.convs) - 1:
                h = h.relu()
        h = self.lin(h)
        # size= makes an empty graph (no node) a zero vector instead of a missing row
        return global_max_pool(h, batch.batch, size=batch.num_graphs)


def draw_triplets(settings: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(anchor, positive, negative) index arrays: every graph is an anchor once, vectorised over anchors.

    A setting with a single graph uses the anchor itself as its positive.
    """
    settings = np.asarray(settings)
    n = len(settings)
    order = np.argsort(settings, kind="stable")
    _, group_of_sorted, sizes = np.unique(settings[order], return_inverse=True, return_counts=True)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    pos_in_group = np.arange(n) - starts[group_of_sorted]
    size = sizes[group_of_sorted]
    # positive: another member of the group (offset 1..size-1), or itself for a singleton
    offset = np.where(size > 1, rng.integers(1, np.maximum(size, 2)), 0)
    positive_sorted = starts[group_of_sorted] + (pos_in_group + offset) % size
    # negative: a rank among the n - size graphs of other settings, shifted past the anchor's own group
    if (n - size <= 0).any():
        raise ValueError("triplets need graphs of at least two settings")
    r = rng.integers(0, n - size)
    negative_sorted = np.where(r >= starts[group_of_sorted], r + size, r)
    anchor = order
    return anchor, order[positive_sorted], order[negative_sorted]


def embed(model: GraphEncoder, graphs: list[Data], batch_size: int = 256) -> torch.Tensor:
    """(N, out) embeddings of graphs, in order."""
    model.eval()
    out = []
    with torch.inference_mode():
        for batch in DataLoader(graphs, batch_size=batch_size, shuffle=False):
            out.append(model(batch))
    return torch.cat(out) if out else torch.zeros((0, model.out_channels))


def leave_one_out_recall(emb: torch.Tensor, settings: np.ndarray) -> float:
    """Share of graphs whose nearest other graph is of the same setting (validation metric)."""
    d = torch.cdist(emb, emb)
    d.fill_diagonal_(float("inf"))
    nn_idx = d.argmin(dim=1).numpy()
    return float((np.asarray(settings)[nn_idx] == np.asarray(settings)).mean())


@dataclass
class TrainResult:
    model: GraphEncoder
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0


def train(train_graphs: list[Data], val_graphs: list[Data], spec: GCNSpec, seed: int, threads: int = 2,
          progress: bool = False) -> TrainResult:
    """Train the encoder with the triplet loss; keep the state with the best validation recall@1 (early stop)."""
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = GraphEncoder(spec)
    opt = torch.optim.Adam(model.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    loss_fn = nn.TripletMarginLoss(margin=spec.margin, p=2)
    settings = np.array([g.setting for g in train_graphs])
    val_settings = np.array([g.setting for g in val_graphs])
    best = (-1.0, float("inf"))
    best_state, best_epoch, bad_epochs, history = copy.deepcopy(model.state_dict()), 0, 0, []
    t0 = time.perf_counter()
    for epoch in range(1, spec.epochs + 1):
        model.train()
        a, p, n = draw_triplets(settings, rng)
        perm = rng.permutation(len(a))
        losses = []
        for s in range(0, len(perm), spec.batch_size):
            idx = perm[s : s + spec.batch_size]
            b = len(idx)
            batch = Batch.from_data_list([train_graphs[i] for i in np.concatenate([a[idx], p[idx], n[idx]])])
            z = model(batch)
            loss = loss_fn(z[:b], z[b : 2 * b], z[2 * b :])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item() * b)
        train_loss = sum(losses) / len(a)
        if len(val_graphs) and len(set(val_settings)) > 1:
            val_emb = embed(model, val_graphs)
            val_recall = leave_one_out_recall(val_emb, val_settings)
            va, vp, vn = draw_triplets(val_settings, np.random.default_rng(seed + 1))
            val_loss = float(loss_fn(val_emb[va], val_emb[vp], val_emb[vn]))
        else:
            val_recall, val_loss = float("nan"), train_loss
        history.append({"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "val_recall@1": val_recall})
        if progress:
            log.info("epoch %d loss %.4f val loss %.4f val recall@1 %.3f", epoch, train_loss, val_loss, val_recall)
        score = (0.0 if np.isnan(val_recall) else val_recall, -val_loss)
        if score > (best[0], -best[1]):
            best, best_epoch, bad_epochs = (score[0], val_loss), epoch, 0
            best_state = copy.deepcopy(model.state_dict())
        else:
            bad_epochs += 1
            if bad_epochs >= spec.patience:
                break
    model.load_state_dict(best_state)
    return TrainResult(model, history, best_epoch, time.perf_counter() - t0)
