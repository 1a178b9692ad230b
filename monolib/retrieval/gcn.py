"""The graph encoder (paper section 2, "Graph Neural Network"): GCN + triplet loss, trained per setting.

Encoder, as the original code ran it (PyG's `models.GCN(in, 128, num_layers=5, out_channels=64)`, max over the
nodes): 5 GCNConv layers, the first four of 128 channels each followed by ReLU, the fifth mapping straight to 64,
global max pooling. Its graphs hold each pair once, i -> j for i < j in ascending NYU40 id, and GCNConv passes
messages from source to target: a node hears only the nodes of lower label id, and the first node hears nobody.
The paper's text describes a linear layer to 64 after the convolutions; its code has none. The undirected encoder
(`edges: both`) and the linear head (`linear: true`) are ablations of it (params/direction.yaml).
Triplets (paper): every training graph is an anchor once per epoch; its positive is a random other graph of the
same setting, its negative a random graph of another setting; drawn afresh each epoch from the seed. The training
loop, its schedule and its model selection are every triplet encoder's (`monolib.retrieval.training`).
"""
from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass
from functools import partial
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch_geometric.data import Data
from torch_geometric.nn import (AttentionalAggregation, GATv2Conv, GCNConv, GINEConv, TransformerConv, global_max_pool,
                                global_mean_pool)
from torch_geometric.nn.conv.gcn_conv import gcn_norm
from torch_geometric.utils import to_torch_csr_tensor

from monolib.data.labels import NUM_CLASSES
from monolib.data.protocols import family
from monolib.graphs.build import (EDGE_LAYOUT, NODE_FEATURES, NODE_LAYOUT, at_threshold, directed_by,
                                  layout_graph, node_rank)
from monolib.params import TRANSFORMER_HEADS, GCNSpec
from monolib.retrieval import training
from monolib.retrieval.training import Batch, TrainResult, draw_triplets, training_rule, triplet_batches


def ragged_arange(starts: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """The concatenation of arange(start, start + count) for each pair, without a Python loop."""
    total = int(counts.sum())
    begin = torch.cumsum(counts, 0) - counts  # where each run begins in the output
    return (torch.repeat_interleave(starts - begin, counts, output_size=total)
            + torch.arange(total, device=starts.device))


@dataclass
class GraphBatch:
    """The fields of a `torch_geometric.data.Batch` that the encoder reads."""
    x: torch.Tensor
    edge_index: torch.Tensor
    edge_attr: Optional[torch.Tensor]
    batch: torch.Tensor
    num_graphs: int

    def to(self, device) -> "GraphBatch":
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return GraphBatch(move(self.x), move(self.edge_index), move(self.edge_attr), move(self.batch), self.num_graphs)


class GraphPool:
    """The graphs of one split held as one set of tensors, so that a batch of them is a few index operations
    instead of `Batch.from_data_list` over Python objects (about a sixth of a quick cell's training). A batch holds
    the same tensors as `Batch.from_data_list` of the same graphs, bit for bit: nodes and edges in list order, each
    graph's edge indices shifted by the nodes of the graphs before it (tests/test_gcn.py compares the two)."""

    def __init__(self, graphs: list[Data]):
        if not graphs:
            raise ValueError("a pool of graphs needs at least one graph")
        self.num_nodes = torch.tensor([g.num_nodes for g in graphs], dtype=torch.long)
        self.num_edges = torch.tensor([g.edge_index.shape[1] for g in graphs], dtype=torch.long)
        self.x = torch.cat([g.x for g in graphs])
        self.edge_index = torch.cat([g.edge_index for g in graphs], dim=1)
        with_attr = [getattr(g, "edge_attr", None) is not None for g in graphs]
        if any(with_attr) and not all(with_attr):
            raise ValueError("some graphs have edge_attr and some have not: build every graph of a split alike")
        self.edge_attr = torch.cat([g.edge_attr for g in graphs]) if all(with_attr) else None
        self.node_start = torch.cumsum(self.num_nodes, 0) - self.num_nodes
        self.edge_start = torch.cumsum(self.num_edges, 0) - self.num_edges

    def batch(self, idx) -> GraphBatch:
        """The graphs `idx` (in that order, repeats allowed) as one batch."""
        idx = torch.as_tensor(np.asarray(idx), dtype=torch.long)
        n, e = self.num_nodes[idx], self.num_edges[idx]
        nodes = ragged_arange(self.node_start[idx], n)
        edges = ragged_arange(self.edge_start[idx], e)
        shift = torch.repeat_interleave(torch.cumsum(n, 0) - n, e, output_size=int(e.sum()))
        return GraphBatch(x=self.x[nodes], edge_index=self.edge_index[:, edges] + shift,
                          edge_attr=None if self.edge_attr is None else self.edge_attr[edges],
                          batch=torch.repeat_interleave(torch.arange(len(idx)), n, output_size=int(n.sum())),
                          num_graphs=len(idx))


SPARSE_DEVICES = ("cpu", "cuda")  # where torch multiplies a sparse CSR matrix (not `meta`, not every backend)


def normalised_adjacency(edge_index: torch.Tensor, weight: Optional[torch.Tensor], num_nodes: int,
                         dtype: torch.dtype) -> tuple:
    """GCNConv's normalised adjacency (self-loops added, D^-1/2 A D^-1/2: PyG's own `gcn_norm`), computed once per
    batch for all five layers instead of once per layer. Where torch has sparse products (`SPARSE_DEVICES`) an
    `Adjacency` (sparse CSR, transposed as PyG's `adj_t`, and its transpose when gradients are on): each layer's
    propagation is one sparse-dense product instead of a gather and a scatter over the edges (a quick cell trains in
    about 0.65 of the time; its sums run in another order than the scatter's, so the weights differ from the
    edge-list path in the last bits, and are as reproducible); elsewhere the edge list and its weights, as a tuple
    of GCNConv's arguments after the features."""
    index, value = gcn_norm(edge_index, weight, num_nodes, False, True, "source_to_target", dtype)
    if index.device.type not in SPARSE_DEVICES:
        return index, value
    with warnings.catch_warnings():  # "Sparse CSR tensor support is in beta": CSR @ dense and its backward are used
        warnings.simplefilter("ignore", UserWarning)
        transposed = csr_of(index[0], index[1], value, num_nodes) if torch.is_grad_enabled() else None
        return Adjacency(csr_of(index[1], index[0], value, num_nodes), transposed)


@dataclass
class Adjacency:
    """A batch's normalised adjacency as sparse CSR (`matrix`: row = target, column = source) and, for training,
    its transpose (`transposed`), built once per batch for the five layers' backward passes."""
    matrix: torch.Tensor
    transposed: Optional[torch.Tensor] = None


class SparseProduct(torch.autograd.Function):
    """``matrix @ x`` for a constant sparse CSR `matrix`, with the gradient ``transposed @ grad``: the same products
    as autograd's own backward of `torch.sparse.mm` (which transposes the matrix to CSR again at every layer of
    every step, a quarter of a quick cell's training), bit for bit (tests/test_gcn.py)."""

    @staticmethod
    def forward(ctx, matrix: torch.Tensor, transposed: Optional[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        ctx.matrix, ctx.transposed = matrix, transposed
        return torch.sparse.mm(matrix, x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        t = ctx.transposed if ctx.transposed is not None else ctx.matrix.t().to_sparse_csr()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return None, None, torch.sparse.mm(t, grad)


def gcn_layer(conv: GCNConv, h: torch.Tensor, adjacency) -> torch.Tensor:
    """`conv` (a GCNConv without normalisation) on node features `h`: its own forward on an edge list; on an
    `Adjacency`, the same operations written out (its linear map, the sparse product, its bias), so that the
    product's backward is `SparseProduct`'s."""
    if not isinstance(adjacency, Adjacency):
        return conv(h, *adjacency)
    out = SparseProduct.apply(adjacency.matrix, adjacency.transposed, conv.lin(h))
    return out + conv.bias if conv.bias is not None else out


def csr_of(row: torch.Tensor, col: torch.Tensor, value: torch.Tensor, n: int) -> torch.Tensor:
    """The (n, n) sparse CSR matrix with `value` at (`row`, `col`), repeated pairs summed: PyG's
    `to_torch_csr_tensor`, one sort (its `coalesce`) and the row pointers, the same arrays as
    ``sparse_coo_tensor(...).coalesce().to_sparse_csr()`` without the COO tensor and its conversion."""
    return to_torch_csr_tensor(torch.stack([row, col]), value, (n, n))


def encoder_graph(g: Data, threshold: float, spec: GCNSpec, projection: Optional[str]) -> Data:
    """The graph of a cached scene graph `g` (nodes and every pair) that the encoder of `spec` reads at
    `threshold`: its edges (`at_threshold`: each pair once, directed along `spec.node_order` by `directed_by`, or
    both directions with `edges: both`) and, with `node_layout` / `edge_layout`, the layout features in the camera
    frame of `projection` (`layout_graph`)."""
    g = at_threshold(g, threshold, spec.edges == "both")
    if spec.edges == "upper":
        g = directed_by(g, spec.node_order)
    return layout_graph(g, projection, spec.node_layout, spec.edge_layout)


def reads_edge_attr(spec: GCNSpec) -> bool:
    """Whether an encoder of `spec` reads its graphs' edge attributes (lengths, layout): the paper's GCNConv without
    edge weights reads only which nodes are joined, so two graph sets with the same nodes and edges are the same
    input to it whatever depth placed the nodes (node layout columns, when read, are part of x)."""
    return (spec.conv != "gcn" or spec.edge_weight != "none" or spec.pair_readout or spec.edge_layout)


def input_fingerprint(graphs: list[Data], threshold: float, spec: GCNSpec, projection: Optional[str]) -> str:
    """A digest of what an encoder of `spec` reads of `graphs` at `threshold` (`encoder_graph`): each graph's
    setting, frame, node features and edges, and its edge attributes when the encoder reads them. Equal digests:
    the same training and the same embeddings, seed for seed."""
    h = hashlib.sha256()
    attrs = reads_edge_attr(spec)
    for g in graphs:
        e = encoder_graph(g, threshold, spec, projection)
        h.update(f"{g.setting}|{g.frame}|{e.num_nodes}|".encode())
        h.update(e.x.numpy().tobytes())
        h.update(e.edge_index.numpy().tobytes())
        if attrs and e.edge_attr is not None:
            h.update(e.edge_attr.numpy().tobytes())
    return h.hexdigest()


class GraphEncoder(nn.Module):
    """The paper's encoder by default; `GCNSpec`'s choice fields switch the variants of the encoder ablation.

    Input columns: x = [NYU40 id, R, G, B] and, with `node_layout`, the node's image column, row and log depth
    (`monolib.graphs.build.layout_graph`); edge_attr = [length] or, with `edge_layout`, [length, vertical offset,
    angle to up]. Colours are standardised with the training set's statistics when `colour_encoding: standardised`, the
    layout columns and edge attributes of the layout always (`set_colour_stats`)."""

    def __init__(self, spec: GCNSpec, in_channels: Optional[int] = None):
        super().__init__()
        self.spec = spec
        in_channels = in_channels or NODE_FEATURES + (NODE_LAYOUT if spec.node_layout else 0)
        self.edge_dim = EDGE_LAYOUT if spec.edge_layout else 1
        label_dim = {"raw": 1, "embedding": 16, "onehot": NUM_CLASSES + 1}[spec.label_encoding]
        if spec.label_encoding == "embedding":
            self.label_embedding = nn.Embedding(NUM_CLASSES + 1, 16)
        self.register_buffer("colour_mean", torch.zeros(in_channels - 1))
        self.register_buffer("colour_std", torch.ones(in_channels - 1))
        if spec.edge_layout:  # (only then: the state of every other encoder keeps its keys)
            self.register_buffer("edge_mean", torch.zeros(self.edge_dim))
            self.register_buffer("edge_std", torch.ones(self.edge_dim))
        dims = [label_dim + in_channels - 1] + [spec.hidden] * spec.layers
        if not spec.linear:
            dims[-1] = spec.out
        self.convs = nn.ModuleList(self._conv(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.lin = nn.Linear(spec.hidden, spec.out) if spec.linear else None
        if spec.pooling == "attention":
            self.attention = AttentionalAggregation(nn.Linear(spec.out, 1))
        self.out_channels = spec.out * (2 if spec.pooling in ("meanmax", "attention") else 1)
        if spec.pair_readout:  # (label, colour[, layout]) of both ends and the edge's features -> out, mean + max
            self.pair_mlp = nn.Sequential(nn.Linear(2 * dims[0] + self.edge_dim, spec.hidden), nn.ReLU(),
                                          nn.Linear(spec.hidden, spec.out))
            self.out_channels += 2 * spec.out

    def _conv(self, a: int, b: int) -> nn.Module:
        if self.spec.conv == "gine":
            return GINEConv(nn.Sequential(nn.Linear(a, b), nn.ReLU(), nn.Linear(b, b)), edge_dim=self.edge_dim)
        if self.spec.conv == "gatv2":
            return GATv2Conv(a, b, heads=1, edge_dim=self.edge_dim)
        if self.spec.conv == "transformer":  # relative-position attention: the edge's geometry in keys and values
            heads = TRANSFORMER_HEADS if b % TRANSFORMER_HEADS == 0 else 1
            return TransformerConv(a, b // heads, heads=heads, edge_dim=self.edge_dim, root_weight=True)
        return GCNConv(a, b, normalize=False)  # `normalised_adjacency`, once per batch in `forward`

    def set_colour_stats(self, graphs: list[Data]) -> None:
        """Training-set mean and std of the colour and layout columns of x (colours used when
        `colour_encoding: standardised`, the layout always) and, with `edge_layout`, of the edge attributes."""
        xs = [g.x[:, 1:] for g in graphs if g.num_nodes]
        if xs:
            c = torch.cat(xs)
            self.colour_mean.copy_(c.mean(0))
            self.colour_std.copy_(c.std(0).nan_to_num(1.0).clamp_min(1e-6))
        if self.spec.edge_layout:
            es = [g.edge_attr for g in graphs if g.edge_attr is not None and len(g.edge_attr)]
            if es:
                e = torch.cat(es)
                self.edge_mean.copy_(e.mean(0))
                self.edge_std.copy_(e.std(0).nan_to_num(1.0).clamp_min(1e-6))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        label, colour, layout = x[:, :1], x[:, 1:NODE_FEATURES], x[:, NODE_FEATURES:]
        if self.spec.label_encoding == "embedding":
            label = self.label_embedding(label[:, 0].long().clamp(0, NUM_CLASSES))
        elif self.spec.label_encoding == "onehot":
            label = F.one_hot(label[:, 0].long().clamp(0, NUM_CLASSES), NUM_CLASSES + 1).float()
        if self.spec.colour_encoding == "standardised":
            colour = (colour - self.colour_mean[:NODE_FEATURES - 1]) / self.colour_std[:NODE_FEATURES - 1]
        if layout.shape[1]:
            layout = (layout - self.colour_mean[NODE_FEATURES - 1:]) / self.colour_std[NODE_FEATURES - 1:]
        return torch.cat([label, colour, layout], dim=1)

    def edge_features(self, batch: GraphBatch) -> torch.Tensor:
        """(E, edge_dim): the edge attributes (lengths, or the layout's three columns standardised)."""
        if batch.edge_attr is None:
            return batch.x.new_zeros((batch.edge_index.shape[1], self.edge_dim))
        if batch.edge_attr.shape[1] != self.edge_dim:
            raise ValueError(f"edge attributes of {batch.edge_attr.shape[1]} columns, the encoder reads "
                             f"{self.edge_dim} (gcn.edge_layout: {self.spec.edge_layout})")
        if self.spec.edge_layout:
            return (batch.edge_attr - self.edge_mean) / self.edge_std
        return batch.edge_attr

    def forward(self, batch: GraphBatch) -> torch.Tensor:
        """(num_graphs, out) embeddings of a `GraphBatch` or a `torch_geometric.data.Batch`."""
        h, pairs = self.node_embeddings(batch)
        # size= makes an empty graph (no node) a zero vector instead of a missing row
        pooled = global_max_pool(h, batch.batch, size=batch.num_graphs)
        if self.spec.pooling == "meanmax":
            pooled = torch.cat([global_mean_pool(h, batch.batch, size=batch.num_graphs), pooled], dim=1)
        elif self.spec.pooling == "attention":
            pooled = torch.cat([self.attention(h, batch.batch, dim_size=batch.num_graphs), pooled], dim=1)
        return pooled if pairs is None else torch.cat([pooled, pairs], dim=1)

    def node_embeddings(self, batch: GraphBatch) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """((num_nodes, out) each node's embedding before the pooling, the pair readout's (num_graphs, 2 out) or
        None): what `forward` pools, and what tells which node each pooled entry came from."""
        h = self.features(batch.x)
        edges = self.edge_features(batch)
        pairs = self.pair_readout(h, batch, edges) if self.spec.pair_readout else None
        if not self.spec.message_passing:  # each node alone: the convolutions see no edge
            batch = GraphBatch(batch.x, batch.edge_index[:, :0], None, batch.batch, batch.num_graphs)
            edges = edges[:0]
        if self.spec.conv not in ("gine", "gatv2", "transformer"):
            length = batch.edge_attr[:, 0] if batch.edge_attr is not None else edges[:, 0]  # metres, as built
            weight = 1.0 / (1.0 + length) if self.spec.edge_weight == "inverse" else None
            adjacency = normalised_adjacency(batch.edge_index, weight, h.size(0), h.dtype)
        for i, conv in enumerate(self.convs):
            if self.spec.conv in ("gine", "gatv2", "transformer"):
                h = conv(h, batch.edge_index, edges)
            else:
                h = gcn_layer(conv, h, adjacency)
            if i < len(self.convs) - 1 or self.lin is not None:  # no ReLU on a last conv that maps to the output
                h = h.relu()
        if self.lin is not None:
            h = self.lin(h)
        return h, pairs

    def pair_readout(self, h: torch.Tensor, batch: GraphBatch, edges: torch.Tensor) -> torch.Tensor:
        """(num_graphs, 2 out): mean and max over each graph's edges i -> j of MLP([h_i, h_j, edge features]), the
        relation of two objects (which labels, which colours, how far apart, which one above); a graph without
        edges gives zeros."""
        src, dst = batch.edge_index
        m = self.pair_mlp(torch.cat([h[src], h[dst], edges], dim=1))
        graph = batch.batch[src]
        return torch.cat([global_mean_pool(m, graph, size=batch.num_graphs),
                          global_max_pool(m, graph, size=batch.num_graphs)], dim=1)


def family_negatives(settings: np.ndarray, negative: np.ndarray, share: float,
                     rng: np.random.Generator) -> np.ndarray:
    """`negative` with a `share` of the anchors' negatives redrawn from their own family (`family`: the same
    furniture and materials in another layout, the sibling of the `siblings` protocol): a random graph of another
    setting of the anchor's family. Anchors whose family has no other setting keep their random negative.
    Vectorised over anchors; the draws do not depend on which anchors qualify."""
    settings = np.asarray(settings)
    n = len(settings)
    fam_code = np.unique([family(s) for s in settings], return_inverse=True)[1].reshape(-1)
    set_code = np.unique(settings, return_inverse=True)[1].reshape(-1)
    order = np.lexsort((set_code, fam_code))  # grouped by family, then setting
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    fam_size = np.bincount(fam_code)[fam_code]
    set_size = np.bincount(set_code)[set_code]
    fam_start = (np.cumsum(np.bincount(fam_code)) - np.bincount(fam_code))[fam_code]
    set_start = np.full(n, n)
    np.minimum.at(set_start, set_code, rank)  # where each setting's block begins in `order`
    set_start = set_start[set_code]
    others = fam_size - set_size  # graphs of the anchor's family in other settings
    r = rng.integers(0, np.maximum(others, 1))
    pick = fam_start + r
    pick = np.where(pick >= set_start, pick + set_size, pick)
    chosen = (rng.random(n) < share) & (others > 0)
    out = np.array(negative, copy=True)
    out[chosen] = order[pick[chosen]]
    return out


def family_batches(settings: np.ndarray, batch_size: int, rng: np.random.Generator,
                   per_setting: int = 4) -> list[np.ndarray]:
    """Batches of whole families: every setting of batch_size // (per_setting * settings per family) random
    families, `per_setting` graphs each (P x K sampling over families), so that a batch-hard negative is often the
    anchor's sibling. About every graph once per epoch."""
    settings = np.asarray(settings)
    names = np.unique(settings)
    fams: dict[str, list[str]] = {}
    for name in names:
        fams.setdefault(family(name), []).append(name)
    fam_names = sorted(fams)
    members = {n: rng.permutation(np.flatnonzero(settings == n)) for n in names}
    per_family = per_setting * max(1, round(len(names) / len(fam_names)))
    p = min(len(fam_names), max(2, batch_size // per_family))
    batches = []
    for _ in range(max(1, len(settings) // (p * per_family))):
        chosen = rng.choice(len(fam_names), size=p, replace=False)
        batches.append(np.concatenate([rng.choice(members[n], size=per_setting, replace=len(members[n]) < per_setting)
                                       for f in chosen for n in fams[fam_names[f]]]))
    return batches


def batch_hard_batches(settings: np.ndarray, batch_size: int, rng: np.random.Generator,
                       per_setting: int = 4) -> list[np.ndarray]:
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
    pool = GraphPool(graphs) if graphs else None
    with torch.inference_mode():
        for start in range(0, len(graphs), batch_size):
            out.append(model(pool.batch(np.arange(start, min(start + batch_size, len(graphs)))).to(dev)).cpu())
    return torch.cat(out) if out else torch.zeros((0, model.out_channels))


def first_node_share(model: GraphEncoder, graphs: list[Data]) -> dict[str, float]:
    """Where the max-pooled embedding of the graphs comes from: ``share`` the mean over graphs with at least two
    nodes of the share of the `out` max-pooled entries taken from the graph's first node in the encoder's node
    order (`monolib.graphs.build.node_rank`; the node that hears nobody when each edge points from the earlier node
    to the later one), ``uniform`` that share if every node were as likely (the mean of 1 / nodes), ``graphs`` how
    many graphs were counted, and ``first_label`` the NYU40 id most often first."""
    model.eval()
    graphs = [g for g in graphs if g.num_nodes >= 2]
    if not graphs:
        return {"share": float("nan"), "uniform": float("nan"), "graphs": 0, "first_label": -1}
    pool = GraphPool(graphs)
    dev = next(model.parameters()).device
    with torch.inference_mode():
        h = model.node_embeddings(pool.batch(np.arange(len(graphs))).to(dev))[0].cpu()
    first = torch.stack([pool.node_start[i] + node_rank(g, model.spec.node_order).argmin()
                         for i, g in enumerate(graphs)])
    batch = torch.repeat_interleave(torch.arange(len(graphs)), pool.num_nodes)
    top = h.new_full((len(graphs), h.shape[1]), float("-inf")).scatter_reduce(0, batch[:, None].expand_as(h), h,
                                                                               "amax")
    from_first = (h[first] >= top).to(torch.float64).mean(dim=1)  # ties count for the first node
    labels = pool.x[first, 0].long()
    return {"share": float(from_first.mean()), "uniform": float((1.0 / pool.num_nodes.double()).mean()),
            "graphs": len(graphs), "first_label": int(torch.bincount(labels).argmax())}


def graph_batches(spec: GCNSpec, pool: GraphPool, settings: np.ndarray):
    """The batch function (`monolib.retrieval.training.train`'s ``epoch_batches(rng, gen)``) of `spec.mining` over
    the training graphs held in `pool` (of `settings`): the paper's random triplets (`family`: with a share of the
    negatives redrawn from the anchor's family, `family_negatives`), or batches of a few graphs of each of a few
    settings (`batch_hard`) or families (`batch_hard_family`) under the batch-hard loss. Every draw of an epoch is
    made when the function is called, from `rng`."""
    def epoch_batches(rng: np.random.Generator, gen: torch.Generator):
        if spec.mining in ("batch_hard", "batch_hard_family"):
            draw = batch_hard_batches if spec.mining == "batch_hard" else family_batches
            return (Batch(pool.batch(idx), partial(batch_hard_loss, settings=settings[idx], margin=spec.margin),
                          len(idx)) for idx in draw(settings, spec.batch_size, rng))
        a, p, n = draw_triplets(settings, rng)
        if spec.mining == "family":
            n = family_negatives(settings, n, spec.family_share, rng)
        return triplet_batches(a, p, n, batch_size=spec.batch_size, rng=rng, margin=spec.margin,
                               input_of=pool.batch)

    return epoch_batches


def train(train_graphs: list[Data], val_graphs: list[Data], spec: GCNSpec, *, seed: int, threads: int = 2,
          progress: bool = False, deterministic: bool = True, on_epoch=None) -> TrainResult:
    """Train the encoder of `spec` (its colour statistics from `train_graphs`) with the triplet loss and
    `spec.mining`'s batches (`graph_batches`), by `spec`'s training rule (`monolib.retrieval.training.train`: the
    schedule, the validation on `val_graphs` and the model kept). `on_epoch(model)`, when given, adds columns to
    each epoch's history row (it must not draw from the seed's random streams)."""
    def make_model() -> GraphEncoder:
        model = GraphEncoder(spec)
        model.set_colour_stats(train_graphs)
        return model

    pool = GraphPool(train_graphs)
    batches = graph_batches(spec, pool, np.array([g.setting for g in train_graphs]))
    return training.train(make_model, batches, rule=training_rule(spec), seed=seed, val_inputs=val_graphs,
                          val_settings=np.array([g.setting for g in val_graphs]), embed=embed, threads=threads,
                          deterministic=deterministic, progress=progress, on_epoch=on_epoch)
