"""The graph encoder (paper section 2, "Graph Neural Network"): GCN + triplet loss, trained per setting.

Encoder: 5 GCNConv layers of 128 channels (each followed by ReLU), a linear layer to 64, global max pooling.
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
import torch.nn.functional as F
from torch_geometric.nn import GATv2Conv, GCNConv, GINEConv, global_max_pool, global_mean_pool

from monolib.graph import NODE_FEATURES
from monolib.labels import NUM_CLASSES
from monolib.params import GCNSpec

log = logging.getLogger(__name__)


class GraphEncoder(nn.Module):
    """The paper's encoder by default; `GCNSpec`'s choice fields switch the variants of the encoder ablation."""

    def __init__(self, spec: GCNSpec, in_channels: int = NODE_FEATURES):
        super().__init__()
        self.spec = spec
        label_dim = {"raw": 1, "embedding": 16, "onehot": NUM_CLASSES + 1}[spec.label]
        if spec.label == "embedding":
            self.label_embedding = nn.Embedding(NUM_CLASSES + 1, 16)
        self.register_buffer("colour_mean", torch.zeros(in_channels - 1))
        self.register_buffer("colour_std", torch.ones(in_channels - 1))
        dims = [label_dim + in_channels - 1] + [spec.hidden] * spec.layers
        if not spec.linear:
            dims[-1] = spec.out
        self.convs = nn.ModuleList(self._conv(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.lin = nn.Linear(spec.hidden, spec.out) if spec.linear else None
        self.out_channels = spec.out * (2 if spec.pooling == "meanmax" else 1)

    def _conv(self, a: int, b: int) -> nn.Module:
        if self.spec.conv == "gine":
            return GINEConv(nn.Sequential(nn.Linear(a, b), nn.ReLU(), nn.Linear(b, b)), edge_dim=1)
        if self.spec.conv == "gatv2":
            return GATv2Conv(a, b, heads=1, edge_dim=1)
        return GCNConv(a, b)

    def set_colour_stats(self, graphs: list[Data]) -> None:
        """Training-set mean and std of the colour features (used when `colour: standardised`)."""
        xs = [g.x[:, 1:] for g in graphs if g.num_nodes]
        if xs:
            c = torch.cat(xs)
            self.colour_mean.copy_(c.mean(0))
            self.colour_std.copy_(c.std(0).clamp_min(1e-6))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        label, colour = x[:, :1], x[:, 1:]
        if self.spec.label == "embedding":
            label = self.label_embedding(label[:, 0].long().clamp(0, NUM_CLASSES))
        elif self.spec.label == "onehot":
            label = F.one_hot(label[:, 0].long().clamp(0, NUM_CLASSES), NUM_CLASSES + 1).float()
        if self.spec.colour == "standardised":
            colour = (colour - self.colour_mean) / self.colour_std
        return torch.cat([label, colour], dim=1)

    def forward(self, batch: Batch) -> torch.Tensor:
        h = self.features(batch.x)
        length = batch.edge_attr if batch.edge_attr is not None else batch.x.new_zeros((batch.edge_index.shape[1], 1))
        for i, conv in enumerate(self.convs):
            if self.spec.conv in ("gine", "gatv2"):
                h = conv(h, batch.edge_index, length)
            elif self.spec.edge_weight == "inverse":
                h = conv(h, batch.edge_index, 1.0 / (1.0 + length[:, 0]))
            else:
                h = conv(h, batch.edge_index)
            if i < len(self.convs) - 1 or self.lin is not None:  # no ReLU on a last conv that maps to the output
                h = h.relu()
        if self.lin is not None:
            h = self.lin(h)
        # size= makes an empty graph (no node) a zero vector instead of a missing row
        pooled = global_max_pool(h, batch.batch, size=batch.num_graphs)
        if self.spec.pooling == "meanmax":
            pooled = torch.cat([global_mean_pool(h, batch.batch, size=batch.num_graphs), pooled], dim=1)
        return pooled


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


def batch_hard_batches(settings: np.ndarray, batch_size: int, rng: np.random.Generator, per_setting: int = 4) -> list[np.ndarray]:
    """Batches of `per_setting` graphs from each of batch_size // per_setting random settings (P x K sampling),
    covering about every graph once per epoch."""
    settings = np.asarray(settings)
    names = np.unique(settings)
    members = {n: rng.permutation(np.flatnonzero(settings == n)) for n in names}
    p = max(2, batch_size // per_setting)
    batches = []
    for _ in range(max(1, len(settings) // (p * per_setting))):
        chosen = rng.choice(names, size=min(p, len(names)), replace=False)
        batches.append(np.concatenate([rng.choice(members[n], size=per_setting, replace=len(members[n]) < per_setting)
                                       for n in chosen]))
    return batches


def batch_hard_loss(z: torch.Tensor, settings: np.ndarray, margin: float) -> torch.Tensor:
    """Triplet loss with the hardest positive and the hardest negative of each anchor within the batch."""
    codes = torch.as_tensor(np.unique(settings, return_inverse=True)[1], device=z.device)
    d = torch.cdist(z, z)
    same = codes[:, None] == codes[None, :]
    eye = torch.eye(len(z), dtype=torch.bool, device=z.device)
    hardest_pos = d.masked_fill(~same | eye, float("-inf")).amax(dim=1)
    hardest_neg = d.masked_fill(same, float("inf")).amin(dim=1)
    ok = torch.isfinite(hardest_pos) & torch.isfinite(hardest_neg)
    return F.relu(hardest_pos[ok] - hardest_neg[ok] + margin).mean() if ok.any() else z.sum() * 0.0


def embed(model: GraphEncoder, graphs: list[Data], batch_size: int = 256) -> torch.Tensor:
    """(N, out) embeddings of graphs, in order, on the CPU (the model runs on the device of its weights)."""
    model.eval()
    dev = next(model.parameters()).device
    out = []
    with torch.inference_mode():
        for batch in DataLoader(graphs, batch_size=batch_size, shuffle=False):
            out.append(model(batch.to(dev)).cpu())
    return torch.cat(out) if out else torch.zeros((0, model.out_channels))


def leave_one_out_recall(emb: torch.Tensor, settings: np.ndarray) -> float:
    """Share of graphs whose nearest other graph is of the same setting (validation metric)."""
    d = torch.cdist(emb, emb)
    d.fill_diagonal_(float("inf"))
    nn_idx = d.argmin(dim=1).cpu().numpy()
    return float((np.asarray(settings)[nn_idx] == np.asarray(settings)).mean())


class EarlyStopping:
    """Validation after each epoch (leave-one-out recall@1 on the validation settings, then triplet loss on fixed
    validation triplets), the history, the best state, and the stop after `patience` epochs without progress.
    Shared by every encoder trained with the triplet loss (graphs here, images in `monolib.baselines`)."""

    def __init__(self, patience: int, seed: int, model: nn.Module):
        self.patience, self.seed = patience, seed
        self.best = (-1.0, float("inf"))
        self.best_state, self.best_epoch, self.bad_epochs = copy.deepcopy(model.state_dict()), 0, 0
        self.history: list[dict] = []

    def step(self, model: nn.Module, epoch: int, train_loss: float, val_emb, val_settings, loss_fn,
             progress: bool = False) -> bool:
        """Record the epoch; True when training should stop."""
        val_settings = np.asarray(val_settings)
        if val_emb is not None and len(set(val_settings)) > 1:
            val_recall = leave_one_out_recall(val_emb, val_settings)
            va, vp, vn = draw_triplets(val_settings, np.random.default_rng(self.seed + 1))
            val_loss = float(loss_fn(val_emb[va], val_emb[vp], val_emb[vn]))
        else:
            val_recall, val_loss = float("nan"), train_loss
        self.history.append({"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "val_recall@1": val_recall})
        if progress:
            log.info("epoch %d loss %.4f val loss %.4f val recall@1 %.3f", epoch, train_loss, val_loss, val_recall)
        score = (0.0 if np.isnan(val_recall) else val_recall, -val_loss)
        if score > (self.best[0], -self.best[1]):
            self.best, self.best_epoch, self.bad_epochs = (score[0], val_loss), epoch, 0
            self.best_state = copy.deepcopy(model.state_dict())
            return False
        self.bad_epochs += 1
        return self.bad_epochs >= self.patience


@dataclass
class TrainResult:
    model: GraphEncoder
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0


def train(train_graphs: list[Data], val_graphs: list[Data], spec: GCNSpec, seed: int, threads: int = 2,
          progress: bool = False, deterministic: bool = True) -> TrainResult:
    """Train the encoder with the triplet loss; keep the state with the best validation recall@1 (early stop)."""
    from monolib.device import device, seed_everything

    torch.set_num_threads(threads)
    seed_everything(seed, deterministic)
    rng = np.random.default_rng(seed)
    dev = device()
    model = GraphEncoder(spec)
    model.set_colour_stats(train_graphs)
    model.to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    loss_fn = nn.TripletMarginLoss(margin=spec.margin, p=2)
    settings = np.array([g.setting for g in train_graphs])
    val_settings = np.array([g.setting for g in val_graphs])
    stopper = EarlyStopping(spec.patience, seed, model)
    t0 = time.perf_counter()
    for epoch in range(1, spec.epochs + 1):
        model.train()
        losses, seen = [], 0
        if spec.mining == "batch_hard":
            for idx in batch_hard_batches(settings, spec.batch_size, rng):
                z = model(Batch.from_data_list([train_graphs[i] for i in idx]).to(dev))
                loss = batch_hard_loss(z, settings[idx], spec.margin)
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(loss.item() * len(idx))
                seen += len(idx)
        else:
            a, p, n = draw_triplets(settings, rng)
            perm = rng.permutation(len(a))
            for s in range(0, len(perm), spec.batch_size):
                idx = perm[s : s + spec.batch_size]
                b = len(idx)
                batch = Batch.from_data_list([train_graphs[i] for i in np.concatenate([a[idx], p[idx], n[idx]])])
                z = model(batch.to(dev))
                loss = loss_fn(z[:b], z[b : 2 * b], z[2 * b :])
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(loss.item() * b)
                seen += b
        train_loss = sum(losses) / max(seen, 1)
        val_emb = embed(model, val_graphs) if len(val_graphs) else None
        if stopper.step(model, epoch, train_loss, val_emb, val_settings, loss_fn, progress):
            break
    model.load_state_dict(stopper.best_state)
    return TrainResult(model, stopper.history, stopper.best_epoch, time.perf_counter() - t0)
