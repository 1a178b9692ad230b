"""`gcn` is the encoder the original code ran: its graphs hold each pair once (i -> j for i < j in ascending NYU40
id, as the published files do), PyG's `models.GCN(in, 128, num_layers=5, out_channels=64)` with those edges as given
and max over the nodes. Our encoder against that layer sequence, weight for weight; what the direction does; the
node orders of the direction ablation."""
import math

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch, Data
from torch_geometric.nn import global_max_pool
from torch_geometric.nn.models import GCN

from monolib.graphs.build import complete_graph, directed_by, node_rank
from monolib.params import GCNSpec
from monolib.retrieval.gcn import GraphEncoder, embed, encoder_graph


def published_graph(labels, colours, pos, threshold, setting="ai_900_001", frame="f"):
    """A graph as the original code writes it: nodes in ascending NYU40 id, x = [id, R, G, B], one edge i -> j for
    each pair i < j closer than `threshold`, edge_attr = its length (written out here, not through our builder)."""
    order = np.argsort(labels)
    labels, colours, pos = np.asarray(labels)[order], np.asarray(colours)[order], np.asarray(pos)[order]
    pairs = [(i, j) for i in range(len(labels)) for j in range(i + 1, len(labels))
             if np.linalg.norm(pos[i] - pos[j]) < threshold]
    edge_index = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2).T.contiguous()
    length = torch.tensor([np.linalg.norm(pos[i] - pos[j]) for i, j in pairs], dtype=torch.float32).reshape(-1, 1)
    x = torch.as_tensor(np.column_stack([labels, colours]), dtype=torch.float32)
    return Data(x=x, edge_index=edge_index, edge_attr=length, pos=torch.as_tensor(pos, dtype=torch.float32),
                setting=setting, frame=frame, num_nodes=len(labels))


def random_graphs(n, seed=0, threshold=2.5):
    rng = np.random.default_rng(seed)
    graphs = []
    for k in range(n):
        labels = rng.choice(np.arange(1, 41), size=int(rng.integers(1, 9)), replace=False)
        graphs.append(published_graph(labels, rng.random((len(labels), 3)) * 3, rng.normal(size=(len(labels), 3)) * 2,
                                      threshold, frame=f"f{k}"))
    return graphs


def original_encoder(ours: GraphEncoder) -> GCN:
    """PyG's GCN of the original code (5 layers, 128 hidden, 64 out, ReLU between layers, none after the last),
    holding our encoder's weights."""
    ref = GCN(4, 128, num_layers=5, out_channels=64).eval()
    state = {k: v for k, v in ours.state_dict().items() if k.startswith("convs.")}
    assert set(state) == set(ref.state_dict())                     # the same layers, nothing more on either side
    ref.load_state_dict(state)
    return ref


def test_gcn_is_the_original_layer_sequence_weight_for_weight():
    torch.manual_seed(0)
    ours = GraphEncoder(GCNSpec()).eval()
    assert ours.lin is None and [c.out_channels for c in ours.convs] == [128, 128, 128, 128, 64]
    ref = original_encoder(ours)
    graphs = random_graphs(12) + [published_graph([5], [[1.0, 2.0, 3.0]], [[0.0, 0.0, 1.0]], 2.5, frame="one")]
    assert sum(g.edge_index.shape[1] for g in graphs) > 0
    batch = Batch.from_data_list(graphs)
    want = global_max_pool(ref(batch.x, batch.edge_index), batch.batch)
    # our graphs of the same nodes: built from the pairs (every pair, then the threshold), as a cell builds them
    built = [encoder_graph(complete_graph(g.x, g.pos, g.setting, g.frame), 2.5, GCNSpec(), None) for g in graphs]
    for b, g in zip(built, graphs):
        assert torch.equal(b.edge_index, g.edge_index)             # each pair once, i < j, in the published order
    torch.testing.assert_close(embed(ours, built), want, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(embed(ours, graphs), want, atol=1e-5, rtol=1e-5)


def test_the_first_node_hears_nobody_and_the_undirected_encoder_differs():
    torch.manual_seed(0)
    ours = GraphEncoder(GCNSpec()).eval()
    ref = original_encoder(ours)
    g = published_graph([1, 7, 12], [[0.5, 0.5, 0.5], [1.0, 0.2, 0.1], [0.1, 0.3, 0.9]],
                        [[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0]], math.inf)
    h = ref(g.x, g.edge_index)
    alone = ref(g.x[:1], torch.zeros((2, 0), dtype=torch.long))
    torch.testing.assert_close(h[:1], alone)                         # node 0 (the wall, say) gets no message
    assert not torch.allclose(h[1:2], ref(g.x[1:2], torch.zeros((2, 0), dtype=torch.long)))
    undirected = encoder_graph(complete_graph(g.x, g.pos, g.setting, g.frame), math.inf, GCNSpec(edges="both"), None)
    assert undirected.edge_index.shape[1] == 2 * g.edge_index.shape[1]
    assert not torch.allclose(embed(ours, [undirected]), embed(ours, [g]))


def test_node_orders_direct_each_pair_once_along_their_order():
    g = published_graph([3, 1, 22, 8], [[0.9, 0.9, 0.9], [0.1, 0.1, 0.1], [0.5, 0.5, 0.5], [0.2, 0.3, 0.1]],
                        [[0, 0, 4], [0, 0, 1], [0, 0, 2], [0, 0, 3]], math.inf)
    assert g.x[:, 0].tolist() == [1, 3, 8, 22]
    assert node_rank(g, "label").tolist() == [0, 1, 2, 3]
    assert node_rank(g, "reversed").tolist() == [3, 2, 1, 0]
    assert node_rank(g, "brightness").tolist() == [0, 3, 1, 2]        # sum of R, G, B: darkest first
    assert node_rank(g, "distance").tolist() == [0, 3, 2, 1]          # nearest the camera first
    rev = directed_by(g, "reversed")
    assert torch.equal(rev.edge_index, g.edge_index.flip(0)) and torch.equal(rev.edge_attr, g.edge_attr)
    for order in ("brightness", "distance", "shuffled"):
        d = directed_by(g, order)
        rank = node_rank(g, order)
        assert (rank[d.edge_index[0]] < rank[d.edge_index[1]]).all(), order
        assert {frozenset(e) for e in d.edge_index.T.tolist()} == {frozenset(e) for e in g.edge_index.T.tolist()}
    assert torch.equal(directed_by(g, "label").edge_index, g.edge_index)
    # shuffled: fixed per graph (setting and frame), other graphs other orders
    assert torch.equal(node_rank(g, "shuffled"), node_rank(g.clone(), "shuffled"))
    others = {tuple(node_rank(published_graph(list(range(1, 9)), np.zeros((8, 3)), np.zeros((8, 3)), 1.0,
                                              frame=f"f{k}"), "shuffled").tolist()) for k in range(6)}
    assert len(others) > 1
    # renumbering the nodes along an order is the same input as directing the edges along it (max pooling)
    torch.manual_seed(0)
    model = GraphEncoder(GCNSpec()).eval()
    perm = torch.argsort(node_rank(g, "brightness"))
    inverse = torch.empty_like(perm)
    inverse[perm] = torch.arange(len(perm))
    renumbered = Data(x=g.x[perm], edge_index=inverse[directed_by(g, "brightness").edge_index], num_nodes=4)
    assert (renumbered.edge_index[0] < renumbered.edge_index[1]).all()
    torch.testing.assert_close(embed(model, [renumbered]), embed(model, [directed_by(g, "brightness")]))


def test_distance_order_needs_positions():
    g = published_graph([1, 2], np.zeros((2, 3)), np.zeros((2, 3)), math.inf)
    del g.pos
    with pytest.raises(ValueError, match="no node positions.*distance"):
        node_rank(g, "distance")


def test_first_node_share_counts_the_pooled_entries_the_first_node_gives():
    from monolib.retrieval.gcn import first_node_share

    torch.manual_seed(0)
    graphs = random_graphs(20, seed=3)
    model = GraphEncoder(GCNSpec()).eval()
    got = first_node_share(model, graphs)
    counted = [g for g in graphs if g.num_nodes >= 2]
    shares = []
    for g in counted:  # one graph at a time, by hand: which node gives each entry of the max
        h = model.node_embeddings(Batch.from_data_list([g]))[0]
        shares.append(float((h[0] >= h.max(dim=0).values).double().mean()))
    assert got["graphs"] == len(counted) < len(graphs)            # one-node graphs are left out
    assert got["share"] == pytest.approx(np.mean(shares))
    assert got["uniform"] == pytest.approx(np.mean([1 / g.num_nodes for g in counted]))
    labels = [int(g.x[0, 0]) for g in counted]
    assert got["first_label"] == max(set(labels), key=lambda v: (labels.count(v), -v))
    # reversed: the first node is the one of the highest label id
    rev = first_node_share(GraphEncoder(GCNSpec(node_order="reversed")).eval(), graphs)
    assert rev["graphs"] == got["graphs"] and rev["uniform"] == got["uniform"]
