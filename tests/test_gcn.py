"""The encoder: empty graphs, deterministic training, and a triplet loss that falls on separable settings."""
import math

import numpy as np
import pytest
import torch

from monolib.graphs.build import at_threshold, complete_graph
from monolib.params import GCNSpec
from monolib.retrieval.gcn import GraphEncoder, embed, encoder_graph, train
from monolib.retrieval.training import draw_triplets


def toy_graphs(n_settings=4, per=6, seed=0):
    """Settings differ by which labels they hold; frames jitter positions and colours."""
    rng = np.random.default_rng(seed)
    graphs = []
    for s in range(n_settings):
        labels = np.array([1, 2] + [3 + s, 10 + 2 * s])
        for i in range(per):
            colour = np.full((len(labels), 3), s / n_settings) + rng.normal(0, 0.02, (len(labels), 3))
            x = np.column_stack([labels, colour]).astype(np.float32)
            pos = rng.normal(size=(len(labels), 3)).astype(np.float32)
            graphs.append(at_threshold(complete_graph(x, pos, f"ai_900_{s:03d}", f"ai_900_{s:03d}/cam_00/{i:04d}"),
                                       1.5))
    return graphs


def test_empty_and_one_node_graphs_embed_to_finite_vectors():
    spec = GCNSpec(epochs=1)
    model = GraphEncoder(spec)
    empty = at_threshold(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "a", "a/0"), math.inf)
    one = at_threshold(complete_graph(np.ones((1, 4)), np.zeros((1, 3)), "b", "b/0"), math.inf)
    z = embed(model, [empty, one, empty])
    assert z.shape == (3, 64) and torch.isfinite(z).all()
    assert (z[0] == 0).all()


def test_triplets_respect_settings():
    s = np.array(["a"] * 3 + ["b"] * 2 + ["c"])
    a, p, n = draw_triplets(s, np.random.default_rng(0))
    assert sorted(a) == list(range(6))
    assert (s[a] == s[p]).all() and (s[a] != s[n]).all()


def test_the_training_rule_is_a_specs_training_keys():
    """`training_rule` reads exactly the spec's `TRAINING_KEYS`, in their order; what the encoder is (its mining
    among them) stays in the spec."""
    import dataclasses

    from monolib.params import TRAINING_KEYS
    from monolib.retrieval.training import training_rule

    spec = GCNSpec(epochs=7, lr=0.003, schedule="cosine", select="last", patience=3, min_epochs=2, batch_size=16,
                   weight_decay=0.01, margin=0.5, mining="family", hidden=32)
    rule = training_rule(spec)
    assert tuple(f.name for f in dataclasses.fields(rule)) == TRAINING_KEYS
    assert dataclasses.astuple(rule) == (7, 0.003, "cosine", "last", 3, 2, 16, 0.01, 0.5)


def test_training_lowers_the_loss_and_is_deterministic():
    graphs = toy_graphs()
    spec = GCNSpec(epochs=15, batch_size=8, patience=100, lr=1e-3)
    r1 = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    losses = [h["train_loss"] for h in r1.history]
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3])
    r2 = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    assert [h["train_loss"] for h in r2.history] == pytest.approx(losses)
    torch.testing.assert_close(embed(r1.model, graphs), embed(r2.model, graphs))


CHOICES = [
    {"edges": "both"},
    {"linear": True},
    {"node_order": "shuffled"},
    {"label_encoding": "embedding", "colour_encoding": "standardised"},
    {"label_encoding": "onehot"},
    {"edge_weight": "inverse"},
    {"conv": "gine"},
    {"conv": "gatv2"},
    {"pooling": "meanmax"},
    {"mining": "batch_hard"},
]


def graphs_at(threshold, spec):
    """The toy graphs at a threshold, with edges as `spec.edges` and `spec.node_order` say (as a cell builds them)."""
    return [encoder_graph(complete_graph(g.x, g.pos, g.setting, g.frame), threshold, spec, None) for g in toy_graphs()]


_DEFAULT = {}


def trained_default(threshold):
    """The paper's encoder trained like the variants below (same seed, data and epochs), once per threshold."""
    if threshold not in _DEFAULT:
        spec = GCNSpec(epochs=2, batch_size=8, patience=5)
        graphs = graphs_at(threshold, spec)
        _DEFAULT[threshold] = embed(train(graphs[:18], graphs[18:], spec, seed=0, threads=1).model, graphs)
    return _DEFAULT[threshold]


@pytest.mark.parametrize("choice", CHOICES)
@pytest.mark.parametrize("threshold", [1.5, 0.0])
def test_every_encoder_variant_trains_and_embeds(choice, threshold):
    """... at a threshold, and at 0 (no edges: the encoder sees the nodes only); and each variant's embeddings differ
    from the paper encoder's trained with the same seed on the same graphs, except at threshold 0 those of the
    options that act through the edges alone (their weight, direction or order change nothing without edges)."""
    import dataclasses

    spec = dataclasses.replace(GCNSpec(epochs=2, batch_size=8, patience=5), **choice)
    graphs = graphs_at(threshold, spec)
    assert (threshold == 0) == all(g.edge_index.shape[1] == 0 for g in graphs)
    empty = at_threshold(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "ai_900_009", "e"), threshold)
    result = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    assert result.model.spec == spec
    z = embed(result.model, graphs + [empty])
    assert z.shape == (len(graphs) + 1, result.model.out_channels) and torch.isfinite(z).all()
    assert all(np.isfinite(h["train_loss"]) for h in result.history)
    default = trained_default(threshold)
    if threshold == 0 and set(choice) <= {"edge_weight", "edges", "node_order"}:
        torch.testing.assert_close(z[:-1], default)
    else:
        assert z[:-1].shape != default.shape or not torch.allclose(z[:-1], default)


def twin_encoders(**choice):
    """The paper's encoder and the variant `choice`, built from the same random state (same weights where their
    parameters have the same names and shapes)."""
    import dataclasses

    torch.manual_seed(0)
    base = GraphEncoder(GCNSpec())
    torch.manual_seed(0)
    return base, GraphEncoder(dataclasses.replace(GCNSpec(), **choice))


def shapes(model):
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def with_lengths_times(graphs, factor):
    return [g.clone().update({"edge_attr": g.edge_attr * factor}) for g in graphs]


def test_label_and_colour_encodings_change_the_node_features():
    graphs = graphs_at(math.inf, GCNSpec())
    base, emb_ = twin_encoders(label_encoding="embedding")
    assert shapes(base)["convs.0.lin.weight"] == (128, 4)                       # raw id + R, G, B
    assert shapes(emb_)["label_embedding.weight"] == (41, 16) and shapes(emb_)["convs.0.lin.weight"] == (128, 19)
    assert "label_embedding.weight" not in shapes(base)
    _, onehot = twin_encoders(label_encoding="onehot")
    assert shapes(onehot)["convs.0.lin.weight"] == (128, 44)                    # 41 one-hot + R, G, B
    x = torch.cat([g.x for g in graphs])
    f = onehot.features(x)
    assert (f[:, :41].sum(1) == 1).all() and (f[:, :41].argmax(1) == x[:, 0].long()).all()
    torch.testing.assert_close(base.features(x), x)                            # the paper: the numbers as they are
    _, std = twin_encoders(colour_encoding="standardised")
    std.set_colour_stats(graphs)
    colour = std.features(x)[:, 1:]
    torch.testing.assert_close(colour.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(colour.std(0), torch.ones(3), atol=1e-5, rtol=0)
    base.set_colour_stats(graphs)
    torch.testing.assert_close(base.features(x), x)                            # raw colour: the stats are unused


def test_structure_options_change_the_layers_and_the_output():
    graphs = graphs_at(1.5, GCNSpec())  # not complete graphs: on those every node ends the same, and mean = max
    base, head = twin_encoders(linear=True)  # the paper's code: the 5th conv maps to 64; the ablation adds a head
    assert shapes(head)["lin.weight"] == (64, 128) and shapes(head)["convs.4.lin.weight"] == (128, 128)
    assert not any(k.startswith("lin.") for k in shapes(base)) and shapes(base)["convs.4.lin.weight"] == (64, 128)
    base, meanmax = twin_encoders(pooling="meanmax")
    assert shapes(base) == shapes(meanmax) and meanmax.out_channels == 128
    z, zm = embed(base, graphs), embed(meanmax, graphs)
    assert zm.shape == (len(graphs), 128)
    torch.testing.assert_close(zm[:, 64:], z)                                   # max pooling, as the paper's
    assert not torch.allclose(zm[:, :64], z)                                    # and the mean beside it
    for conv, cls in (("gine", "GINEConv"), ("gatv2", "GATv2Conv")):
        _, m = twin_encoders(conv=conv)
        assert [type(c).__name__ for c in m.convs] == [cls] * 5


def test_edge_options_change_what_the_encoder_reads_of_the_edges():
    both, upper = graphs_at(1.5, GCNSpec(edges="both")), graphs_at(1.5, GCNSpec())
    assert sum(g.edge_index.shape[1] for g in upper) > 0
    assert [2 * g.edge_index.shape[1] for g in upper] == [g.edge_index.shape[1] for g in both]
    assert all((g.edge_index[0] < g.edge_index[1]).all() for g in upper)       # i < j only, as the published code
    base, _ = twin_encoders()
    assert not torch.allclose(embed(base, upper), embed(base, both))          # the encoder sees one direction less
    # the paper's GCNConv ignores the lengths; the edge weight, GINE and GATv2 read them
    longer = with_lengths_times(both, 3.0)
    torch.testing.assert_close(embed(base, longer), embed(base, both))
    for choice in ({"edge_weight": "inverse"}, {"conv": "gine"}, {"conv": "gatv2"}):
        _, m = twin_encoders(**choice)
        assert not torch.allclose(embed(m, longer), embed(m, both)), choice
    # the edge weight is the paper's encoder (same weights) with weighted edges: different with edges, same without
    base, weighted = twin_encoders(edge_weight="inverse")
    assert not torch.allclose(embed(weighted, both), embed(base, both))
    none = graphs_at(0.0, GCNSpec())
    torch.testing.assert_close(embed(weighted, none), embed(base, none))


def test_batch_hard_mining_trains_differently():
    import dataclasses

    graphs = toy_graphs()
    spec = GCNSpec(epochs=3, batch_size=8, patience=10)
    random = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    hard = train(graphs[:18], graphs[18:], dataclasses.replace(spec, mining="batch_hard"), seed=0, threads=1)
    assert [h["train_loss"] for h in hard.history] != pytest.approx([h["train_loss"] for h in random.history])
    assert not torch.allclose(embed(hard.model, graphs), embed(random.model, graphs))


def test_a_pool_batch_holds_the_tensors_of_batch_from_data_list():
    """`GraphPool.batch` against PyG's own collation, bit for bit: repeats, reversed order, empty graphs and
    graphs without edges (threshold 0) among them."""
    from torch_geometric.data import Batch

    from monolib.retrieval.gcn import GraphPool

    empty = at_threshold(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "a", "a/0"), math.inf)
    x, pos = np.column_stack([[1, 2, 5], np.full((3, 3), 0.5)]).astype(np.float32), np.eye(3, dtype=np.float32)
    no_edges = at_threshold(complete_graph(x, pos, "c", "c/0"), 0.0)
    assert no_edges.edge_index.shape[1] == 0 and no_edges.num_nodes == 3
    graphs = toy_graphs(3, 3) + [empty, no_edges]
    pool = GraphPool(graphs)
    for idx in ([0, 1, 2], [10, 9, 9, 0, 10, 4], list(range(len(graphs)))[::-1], [9]):
        got, want = pool.batch(idx), Batch.from_data_list([graphs[i] for i in idx])
        assert torch.equal(got.x, want.x) and torch.equal(got.edge_index, want.edge_index), idx
        assert torch.equal(got.edge_attr, want.edge_attr) and torch.equal(got.batch, want.batch), idx
        assert got.num_graphs == want.num_graphs == len(idx)
    with pytest.raises(ValueError, match="at least one graph"):
        GraphPool([])


@pytest.mark.parametrize("edge_weight", ["none", "inverse"])
def test_the_sparse_adjacency_gives_what_gcnconv_computes_from_the_edge_list(edge_weight):
    """The encoder's layers (one normalised adjacency per batch, sparse products) against PyG's GCNConv with its
    own normalisation on the edge list, with the same weights: the same embeddings up to float rounding."""
    from torch_geometric.data import Batch
    from torch_geometric.nn import GCNConv

    spec = GCNSpec(edge_weight=edge_weight)
    model = GraphEncoder(spec).eval()
    batch = Batch.from_data_list(toy_graphs(3, 2))
    keep = batch.edge_index[0] < batch.edge_index[1]  # one direction only: a transposed adjacency would show
    batch.edge_index, batch.edge_attr = batch.edge_index[:, keep], batch.edge_attr[keep]
    with torch.no_grad():
        got = model(batch)
        h = model.features(batch.x)
        w = 1.0 / (1.0 + batch.edge_attr[:, 0]) if edge_weight == "inverse" else None
        for i, conv in enumerate(model.convs):
            reference = GCNConv(conv.in_channels, conv.out_channels)  # normalize=True: PyG's own path
            reference.load_state_dict(conv.state_dict())
            h = reference(h, batch.edge_index, w)
            if i < len(model.convs) - 1 or model.lin is not None:
                h = h.relu()
        from torch_geometric.nn import global_max_pool
        want = global_max_pool(h if model.lin is None else model.lin(h), batch.batch)
    assert torch.allclose(got, want, atol=1e-5), (got - want).abs().max()


def test_the_adjacency_is_built_as_coalesce_would_and_its_backward_is_autograds_bit_for_bit():
    """`csr_of` holds the arrays of ``sparse_coo_tensor(...).coalesce().to_sparse_csr()`` (repeated entries
    summed), and `SparseProduct`'s gradient (the transpose built once per batch) is autograd's own through
    `torch.sparse.mm`, bit for bit, with and without the transpose given; a training step's weights likewise."""
    import warnings

    from torch_geometric.data import Batch
    from torch_geometric.nn.conv.gcn_conv import gcn_norm

    from monolib.retrieval import gcn

    warnings.simplefilter("ignore", UserWarning)  # "Sparse CSR tensor support is in beta"
    g = torch.Generator().manual_seed(0)
    for n, e in [(1, 0), (7, 12), (40, 300), (300, 2000)]:
        ei = torch.randint(0, n, (2, e), generator=g)
        ei = torch.unique(ei[:, ei[0] != ei[1]], dim=1)
        index, value = gcn_norm(ei, None, n, False, True, "source_to_target", torch.float32)
        want = torch.sparse_coo_tensor(index.flip(0), value, (n, n)).coalesce().to_sparse_csr()
        got = gcn.csr_of(index[1], index[0], value, n)
        for a, b in [(got.crow_indices(), want.crow_indices()), (got.col_indices(), want.col_indices()),
                     (got.values(), want.values())]:
            assert torch.equal(a, b), (n, e)
        x = torch.randn(n, 16, generator=g, requires_grad=True)
        grad = torch.randn(n, 16, generator=g)
        torch.sparse.mm(want, x).backward(grad)
        reference, x.grad = x.grad, None
        for transposed in (gcn.csr_of(index[0], index[1], value, n), None):
            out = gcn.SparseProduct.apply(got, transposed, x)
            assert torch.equal(out, torch.sparse.mm(want, x.detach()))
            out.backward(grad)
            assert torch.equal(x.grad, reference), (n, e, transposed is None)
            x.grad = None
    repeated = gcn.csr_of(torch.tensor([0, 0, 1]), torch.tensor([1, 1, 0]), torch.tensor([1.0, 2.0, 3.0]), 2)
    assert torch.equal(repeated.to_dense(), torch.tensor([[0.0, 3.0], [3.0, 0.0]]))

    # one training step of the encoder, through GCNConv's own forward (autograd's backward) and through ours
    batch = Batch.from_data_list(toy_graphs(3, 2))
    steps = []
    for ours in (True, False):
        torch.manual_seed(0)
        model = GraphEncoder(GCNSpec())
        opt = torch.optim.Adam(model.parameters(), lr=0.01)
        if not ours:
            adjacency = gcn.normalised_adjacency(batch.edge_index, None, batch.num_nodes, torch.float32)
            h = model.features(batch.x)
            for i, conv in enumerate(model.convs):
                h = conv(h, adjacency.matrix)
                h = h.relu() if i < len(model.convs) - 1 else h
            from torch_geometric.nn import global_max_pool
            z = global_max_pool(h, batch.batch)
        else:
            z = model(batch)
        z.square().sum().backward()
        opt.step()
        steps.append([p.detach().clone() for p in model.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*steps))


def test_the_edge_list_path_of_devices_without_sparse_products_gives_the_same_embeddings(monkeypatch):
    """Where torch has no sparse CSR product (`meta`, some backends) the encoder propagates over the edge list with
    the same normalised weights: the same embeddings up to float rounding."""
    from torch_geometric.data import Batch

    from monolib.retrieval import gcn

    model = GraphEncoder(GCNSpec()).eval()
    batch = Batch.from_data_list(toy_graphs(3, 2))
    with torch.no_grad():
        sparse = model(batch)
        monkeypatch.setattr(gcn, "SPARSE_DEVICES", ())
        edges = model(batch)
    assert torch.allclose(sparse, edges, atol=1e-5) and not torch.equal(sparse, torch.zeros_like(sparse))


@pytest.mark.parametrize("choice", [{}, {"edges": "upper"},
                                    {"label_encoding": "embedding", "colour_encoding": "standardised"},
                                    {"edge_weight": "inverse"}, {"conv": "gine"}, {"conv": "gatv2"},
                                    {"pair_readout": True, "message_passing": False}])
def test_reads_edge_attr_says_whether_the_lengths_reach_the_embedding(choice):
    """`reads_edge_attr` (what the runner's cross-scenario copies rely on) agrees with the encoder: the embedding
    moves with the edge lengths exactly when it says the encoder reads them; the input fingerprint likewise."""
    import dataclasses

    from monolib.retrieval.gcn import input_fingerprint, reads_edge_attr

    spec = dataclasses.replace(GCNSpec(), **choice)
    both = graphs_at(1.5, spec)
    longer = with_lengths_times(both, 3.0)
    torch.manual_seed(0)
    model = GraphEncoder(spec)
    moved = not torch.allclose(embed(model, longer), embed(model, both))
    assert moved == reads_edge_attr(spec)
    scene = [complete_graph(g.x, g.pos, g.setting, g.frame) for g in toy_graphs()]  # as the graph stage caches them
    farther = [complete_graph(g.x, g.pos * 3.0, g.setting, g.frame) for g in toy_graphs()]
    same = input_fingerprint(scene, math.inf, spec, None) == input_fingerprint(farther, math.inf, spec, None)
    assert same == (not reads_edge_attr(spec))  # every pair joined at inf: only the lengths differ
    recoloured = [complete_graph(g.x + 0.01 * (i == 0), g.pos, g.setting, g.frame) for i, g in enumerate(toy_graphs())]
    assert input_fingerprint(recoloured, 0.0, spec, None) != input_fingerprint(scene, 0.0, spec, None)


def test_the_cosine_schedule_sets_each_epochs_learning_rate(monkeypatch):
    """`schedule: cosine` runs epoch e at lr (1 + cos(pi (e - 1) / epochs)) / 2; `constant` at lr throughout; the two
    train differently from the same seed."""
    import dataclasses

    from monolib.retrieval import training

    seen = []
    real = training.set_epoch_lr

    def spy(opt, rule, epoch):
        real(opt, rule, epoch)
        seen.append(opt.param_groups[0]["lr"])

    monkeypatch.setattr(training, "set_epoch_lr", spy)
    graphs = toy_graphs()
    spec = GCNSpec(epochs=4, batch_size=8, patience=10, lr=0.01, select="last")
    constant = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    assert seen == [0.01] * 4
    seen.clear()
    cosine = train(graphs[:18], graphs[18:], dataclasses.replace(spec, schedule="cosine"), seed=0, threads=1)
    assert seen == pytest.approx([0.01, 0.01 * (1 + math.cos(math.pi / 4)) / 2, 0.005,
                                  0.01 * (1 + math.cos(3 * math.pi / 4)) / 2])
    assert constant.best_epoch == cosine.best_epoch == 4  # select: last keeps the last epoch
    assert not torch.allclose(embed(constant.model, graphs), embed(cosine.model, graphs))
